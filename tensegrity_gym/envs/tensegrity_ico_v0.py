"""TensegrityIco-v0: a six-rod icosahedron tensegrity robot that rolls, on one of two backends.

The env is split in two, as dm_control splits Physics from Task:

* a backend (:mod:`tensegrity_gym.backends`) takes cable commands and returns rod states and
  rest lengths: the MuJoCo plant, or the identified twin;
* the module-level pure functions below turn rod states and rest lengths into observation,
  reward and termination. They are the only place where this happens, so plant and twin cannot
  drift apart; tests call them directly.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from identified.rotation import quat_exp, quat_multiply, quat_to_matrix
from identified.state import RodState
from tensegrity_gym.backends import Backend, make_backend

__all__ = [
    "TensegrityIcoEnv",
    "action_to_rest",
    "healthy_range",
    "observation",
    "observation_names",
    "perturb_start",
    "rest_to_action",
    "reward_terms",
    "structure_com",
    "termination_reason",
    "termination_reasons",
]


# ---------------------------------------------------------------------- pure functions
def action_to_rest(action: np.ndarray, rest_min: np.ndarray, rest_max: np.ndarray) -> np.ndarray:
    """(A,) target rest lengths, m, of an (A,) action in [-1, 1] (clipped): -1 -> rest_min, +1 -> rest_max."""
    a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
    return rest_min + 0.5 * (a + 1.0) * (rest_max - rest_min)


#: physics steps of the model's dt per env step (20 x 1 ms: 50 Hz control)
FRAME_SKIP = 20


def rest_to_action(rest: np.ndarray, rest_min: np.ndarray, rest_max: np.ndarray) -> np.ndarray:
    """Inverse of :func:`action_to_rest`: (A,) rest lengths, m -> [-1, 1] (0 where the range is empty)."""
    span = np.asarray(rest_max, dtype=float) - rest_min
    safe = np.where(span > 0, span, 1.0)
    return np.where(span > 0, 2.0 * (np.asarray(rest, dtype=float) - rest_min) / safe - 1.0, 0.0)


def structure_com(states: RodState) -> np.ndarray:
    """(3,) the structure's centre: the mean of the rods' centres of mass, m.

    Unweighted on purpose: it needs no mass, so the plant and a twin with identified (slightly
    different) masses measure progress in exactly the same way. The robot's rods are equal, where
    this is its true centre of mass.
    """
    return np.asarray(states.pos, dtype=float).mean(axis=0)


def observation(states: RodState, rest_lengths: np.ndarray, actuated_index: np.ndarray,
                rest_min: np.ndarray, rest_max: np.ndarray,
                exclude_current_positions: bool = True, actuator_state: np.ndarray | None = None,
                ctrl_low: np.ndarray | None = None, ctrl_high: np.ndarray | None = None) -> np.ndarray:
    """The observation vector (float64; the env casts it to float32) of rod states and rest lengths.

    Works on one env (``pos`` (R, 3) -> (n_obs,)) and on a batch (``pos`` (N, R, 3), ``rest_lengths``
    (N, S) -> (N, n_obs)): the batched twin calls this same function.

    Layout (R rods, A actuated cables; see :func:`observation_names`):
    ``[x_com, y_com]`` (only with ``exclude_current_positions=False``), ``z_com`` (1),
    rod centres relative to the structure's centre (3R), rod rotation matrices body -> world,
    row-major (9R), rod linear velocities (3R), rod angular velocities (3R), actuated rest lengths
    normalised as actions, -1 = rest_min, +1 = rest_max (A), then the MuJoCo actuators' states
    (activation, or command where an actuator has no dynamics) normalised over their ``ctrlrange``
    (U, only when ``actuator_state`` is given). Everything in the world frame, SI.

    Args:
        states: rod states (R rods).
        rest_lengths: (S,) actual rest lengths of all tendons, m.
        actuated_index: (A,) positions of the actuated cables in ``rest_lengths``.
        rest_min, rest_max: (A,) motor bounds, m.
        exclude_current_positions: leave out the structure's x, y (the task is invariant to them).
        actuator_state, ctrl_low, ctrl_high: (U,) the actuators' states and command ranges.
    """
    pos = np.asarray(states.pos, dtype=float)
    lead = pos.shape[:-2]  # () for one env, (N,) for a batch

    def flat(x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=float).reshape(*lead, -1)

    com = pos.mean(axis=-2)
    rot = quat_to_matrix(np.asarray(states.quat, dtype=float))
    rest = np.asarray(rest_lengths, dtype=float)[..., np.asarray(actuated_index, dtype=int)]
    parts = [] if exclude_current_positions else [com[..., :2]]
    parts += [
        com[..., 2:3],
        flat(pos - com[..., None, :]),
        flat(rot),
        flat(states.vel),
        flat(states.angvel),
        rest_to_action(rest, rest_min, rest_max),
    ]
    if actuator_state is not None:
        parts.append(rest_to_action(np.asarray(actuator_state, dtype=float), ctrl_low, ctrl_high))
    return np.concatenate(parts, axis=-1)


def observation_names(rod_names: tuple[str, ...], actuated_names: tuple[str, ...],
                      exclude_current_positions: bool = True, actuator_names: tuple[str, ...] = ()) -> list[str]:
    """A name for every element of :func:`observation`, in order (e.g. ``"rod2_R01"``, ``"cable5_rest"``,
    ``"winch0_act"``)."""
    names = [] if exclude_current_positions else ["x_com", "y_com"]
    names.append("z_com")
    names += [f"{r}_rel_{c}" for r in rod_names for c in "xyz"]
    names += [f"{r}_R{i}{j}" for r in rod_names for i in range(3) for j in range(3)]
    names += [f"{r}_vel_{c}" for r in rod_names for c in "xyz"]
    names += [f"{r}_angvel_{c}" for r in rod_names for c in "xyz"]
    names += [f"{a}_rest" for a in actuated_names]
    names += [f"{a}_act" for a in actuator_names]
    return names


def healthy_range(nominal: RodState, ground: float | None) -> tuple[float, float] | None:
    """The healthy height range of the structure's centre derived from a model: from a quarter to
    three times its standing height ``h`` above the ground plane, ``(g + h/4, g + 3h)`` (a prism
    tipped onto its side keeps about half its height; a collapsed structure lies flat); ``None``
    (no height check) for a model without a ground plane or standing on nothing above it."""
    if ground is None:
        return None
    h = float(structure_com(nominal)[2]) - ground
    if not (np.isfinite(h) and h > 0):
        return None
    return ground + 0.25 * h, ground + 3.0 * h


def reward_terms(com_before: np.ndarray, com_after: np.ndarray, action: np.ndarray, dt_control: float,
                 forward_reward_weight: float, ctrl_cost_weight: float) -> dict[str, float]:
    """``reward_forward`` = w_f (x_after - x_before) / dt_control and ``reward_ctrl`` = -w_c ||a||^2.

    The reward is their sum. ``action`` is the (clipped) action in [-1, 1]. One env: ``com_*`` (3,),
    ``action`` (A,) -> floats; a batch: (N, 3), (N, A) -> (N,) arrays.
    """
    x_velocity = (np.asarray(com_after, dtype=float)[..., 0] - np.asarray(com_before, dtype=float)[..., 0]) / dt_control
    a = np.asarray(action, dtype=float)
    terms = {
        "reward_forward": forward_reward_weight * x_velocity,
        "reward_ctrl": -ctrl_cost_weight * np.einsum("...i,...i->...", a, a),
    }
    return {k: float(v) if np.ndim(v) == 0 else v for k, v in terms.items()}


def termination_reason(states: RodState, rest_lengths: np.ndarray,
                       healthy_z_range: tuple[float, float] | None) -> str | None:
    """Why the episode must end, or ``None``.

    ``"non-finite state"``: a rod state or rest length is NaN or infinite (the physics diverged).
    ``"collapsed"`` / ``"left the ground"``: the structure's centre is below / above
    ``healthy_z_range`` (``None``: no such check).
    """
    return termination_reasons(states.pos, states.quat, states.vel, states.angvel, rest_lengths,
                               healthy_z_range)[()]


def termination_reasons(pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
                        rest_lengths: np.ndarray, healthy_z_range: tuple[float, float] | None) -> np.ndarray:
    """:func:`termination_reason` over any leading dimensions: an object array of str or ``None``.

    ``pos`` (..., R, 3), ``quat`` (..., R, 4), ``vel``/``angvel`` (..., R, 3), ``rest_lengths`` (..., S).
    """
    pos = np.asarray(pos, dtype=float)
    lead = pos.shape[:-2]
    finite = np.isfinite(np.asarray(rest_lengths, dtype=float)).reshape(*lead, -1).all(axis=-1)
    for x in (pos, quat, vel, angvel):
        finite &= np.isfinite(np.asarray(x, dtype=float)).reshape(*lead, -1).all(axis=-1)
    out = np.full(lead, None, dtype=object)
    if healthy_z_range is not None:
        with np.errstate(invalid="ignore"):
            z = pos[..., 2].mean(axis=-1)
            out[z < healthy_z_range[0]] = "collapsed"
            out[z > healthy_z_range[1]] = "left the ground"
    out[~finite] = "non-finite state"
    return out


def perturb_start(nominal: RodState, rng: np.random.Generator, scale: float) -> RodState:
    """The starting state: ``nominal`` with independent uniform noise U(-scale, scale) on every
    rod's position (m), orientation (a rotation vector about the rod's centre, rad), linear
    velocity (m/s) and angular velocity (rad/s). Rods stay rigid; cables take up the difference."""
    R = nominal.pos.shape[0]
    u = rng.uniform(-scale, scale, size=(4, R, 3))
    q = quat_multiply(quat_exp(u[1]), nominal.quat)
    return RodState(
        pos=nominal.pos + u[0],
        quat=q / np.linalg.norm(q, axis=-1, keepdims=True),
        vel=nominal.vel + u[2],
        angvel=nominal.angvel + u[3],
    )


def turn_about_vertical(state: RodState, yaw: float) -> RodState:
    """``state`` turned by ``yaw`` rad about the vertical (world z) through its centre of mass:
    positions, orientations, velocities and angular velocities (world frame) alike, so the shape,
    the contact with a horizontal ground and every speed are unchanged, only the heading."""
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    com = state.pos.mean(axis=0)
    q = quat_multiply(np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), state.quat)
    return RodState(pos=com + (state.pos - com) @ rz.T, quat=q / np.linalg.norm(q, axis=-1, keepdims=True),
                    vel=state.vel @ rz.T, angvel=state.angvel @ rz.T)


# ---------------------------------------------------------------------- the env
class TensegrityIcoEnv(gym.Env):
    r"""
    ## Description
    A six-rod icosahedron ("expanded octahedron") tensegrity robot, SUPERball-like: six rigid
    rods of about 1.7 m held only by 24 pull-only cables, standing on a ground plane. Every cable
    has a motor that reels its rest length toward a target at a bounded speed. The robot moves
    by changing its shape until it tips over onto a neighbouring face: the goal is to roll in the
    +x direction.

    The env runs on one of two physics backends with the same spaces, reward, reset distribution
    and rendering:
    * `backend="mujoco"` (default), the plant: a MuJoCo model of the robot;
    * `backend="identified"`, the twin: the spring-rod engine identified from plant data.

    A backend only turns cable commands into rod states (position, orientation, velocity,
    angular velocity) and actual rest lengths; observation, reward and termination are computed
    from those alone, by the module-level functions `observation`, `reward_terms` and
    `termination_reason`.

    ## Action Space
    `Box(-1, 1, (A,), float32)`, A = 24 for the robot: the motor target of every actuated cable,
    mapped linearly onto its rest-length range, -1 → `rest_min`, +1 → `rest_max` (about 0.55 and
    1.15 times the neutral rest length; the neutral setting is +0.5). Actions are clipped into
    [-1, 1]. The motors move toward the targets at most `motor_speed` (0.3 m/s), so a target is
    reached over several control steps; the observation carries where the motors actually are.

    ## Observation Space
    `Box(-inf, inf, (1 + 18 R + A,), float32)`, 133 for the robot (135 with
    `exclude_current_positions_from_observation=False`). World frame, SI units; the
    structure's centre c is the mean of the rod centres (no masses needed, so plant and twin
    measure it identically).

    | Num | Observation | Unit |
    |-----|-------------|------|
    | 0 | z of the structure's centre c (its height) | m |
    | 1 … 3R | every rod's centre relative to c (rod-major: x, y, z) | m |
    | 3R+1 … 12R | every rod's rotation matrix body → world, row-major (9 per rod) | 1 |
    | 12R+1 … 15R | every rod's linear velocity | m/s |
    | 15R+1 … 18R | every rod's angular velocity | rad/s |
    | 18R+1 … 18R+A | actuated cables' actual rest lengths, normalised like the action | 1 |

    Why this representation: positions relative to c make the policy invariant to where the
    robot is (x, y are excluded by default, as in Ant-v5; c_z stays because height tells
    standing from tipping); rotation matrices are continuous and unique, unlike quaternions
    (q and -q) or Euler angles; the rod axis alone (the third column) would suffice for the
    thin rods, the full matrix costs 6 numbers per rod and keeps the representation free of
    assumptions about the rod frame; velocities are in the world frame because the task (+x) is;
    the rest lengths are the motors' state, which the speed limit makes differ from the last
    action. `observation_names(...)` names every element.

    ## Rewards
    `reward = reward_forward + reward_ctrl`, both in `info`:
    * `reward_forward = forward_reward_weight · (c_x(t+1) − c_x(t)) / dt`, with `dt =
      frame_skip · physics dt` the control period: the structure's forward speed;
    * `reward_ctrl = −ctrl_cost_weight · ‖action‖²`: favours moderate, mid-range targets.

    ## Starting State
    The backend's nominal standing pose (the robot at rest on a face, its MJCF keyframe
    `nominal`), neutral cable rest lengths (motors at rest), and independent uniform noise
    U(−s, s), s = `reset_noise_scale`, on every rod's position (m), orientation (rotation vector
    about the rod's centre, rad), linear velocity (m/s) and angular velocity (rad/s). Drawn from
    `self.np_random`: `reset(seed=s)` is reproducible, and so is every step after it.

    ## Episode End
    ### Termination
    * the physics diverged (a rod state or rest length is not finite):
      `info["termination_reason"] = "non-finite state"`; the observation returned is the last
      finite one and `reward_forward` is 0, so nothing NaN leaves the env;
    * with `terminate_when_unhealthy=True` (default): the structure's centre leaves
      `healthy_z_range`; below it the robot has collapsed (cables slack, rods flat on the ground;
      this does not recover), above it the robot was thrown: `"collapsed"` / `"left the ground"`.
    ### Truncation
    Never by the env (`truncated` is always False); `gym.make` adds a `TimeLimit` of 1000 steps
    (20 s at the default 50 Hz).

    ## Arguments
    | Parameter | Default | Description |
    |-----------|---------|-------------|
    | `backend` | `"mujoco"` | `"mujoco"` (plant), `"identified"` (twin), or a `Backend` instance |
    | `model` | `None` | MJCF path/text (mujoco) or identified-model JSON (twin); `None`: the robot preset |
    | `backend_kwargs` | `None` | extra keyword arguments of the backend (e.g. `{"integrator": "rk4"}`) |
    | `xml_file` | `None` | an MJCF path (Gymnasium's MuJoCo convention): the plant's model, or the twin's source MJCF (its `mjcf`) |
    | `frame_skip` | `20` | physics steps per env step (20 × 1 ms = 50 Hz control) |
    | `forward_reward_weight` | `1.0` | weight of the forward speed |
    | `ctrl_cost_weight` | `0.01` | weight of ‖action‖² (≤ 0.24 per step for A = 24) |
    | `reset_noise_scale` | `0.01` | half-width of the uniform reset noise (m, rad, m/s, rad/s) |
    | `terminate_when_unhealthy` | `True` | end the episode when the centre leaves `healthy_z_range` |
    | `healthy_z_range` | `(0.4, 2.0)` | healthy height of the structure's centre, m (standing: 0.71); `"auto"`: from the model (`healthy_range`); `None`: no height check |
    | `exclude_current_positions_from_observation` | `True` | leave the centre's x, y out |
    | `render_mode` | `None` | `"rgb_array"` (H×W×3 uint8) or `"human"` (`mujoco.viewer`) |
    | `width`, `height` | `480`, `480` | image size for `"rgb_array"` |
    | `camera` | `None` | `None`: a camera that follows the robot; else a camera name or id of the model |

    ## Version History
    * v0: first version.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"], "render_fps": 50}

    def __init__(
        self,
        backend: str | Backend = "mujoco",
        model: str | os.PathLike | Any | None = None,
        frame_skip: int = FRAME_SKIP,
        forward_reward_weight: float = 1.0,
        ctrl_cost_weight: float = 0.01,
        reset_noise_scale: float = 0.01,
        terminate_when_unhealthy: bool = True,
        healthy_z_range: tuple[float, float] | str | None = (0.4, 2.0),
        exclude_current_positions_from_observation: bool = True,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
        camera: str | int | None = None,
        backend_kwargs: dict[str, Any] | None = None,
        xml_file: str | os.PathLike | None = None,
    ) -> None:
        if int(frame_skip) != frame_skip or frame_skip < 1:
            raise ValueError(f"frame_skip must be an integer >= 1, got {frame_skip}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, "
                             f"got {render_mode!r}")
        if not (np.isfinite(reset_noise_scale) and 0 <= reset_noise_scale <= 1):
            # beyond 1 the reset perturbation (m, rad, m/s) throws the rods apart: no usable start
            raise ValueError(f"reset_noise_scale must be a finite number in [0, 1], got {reset_noise_scale}")
        for name, w in (("ctrl_cost_weight", ctrl_cost_weight), ("forward_reward_weight", forward_reward_weight)):
            if not np.isfinite(w):  # a NaN weight would make every reward NaN
                raise ValueError(f"{name} must be a finite number, got {w}")
        z_range: tuple[float, float] | None = None
        if healthy_z_range is not None and not (isinstance(healthy_z_range, str) and healthy_z_range == "auto"):
            try:
                lo_z, hi_z = (float(v) for v in healthy_z_range)  # type: ignore[union-attr]
            except (TypeError, ValueError):
                raise ValueError(f"healthy_z_range must be (low, high), 'auto' or None, got {healthy_z_range!r}") from None
            if not (np.isfinite(lo_z) and np.isfinite(hi_z) and lo_z < hi_z):
                raise ValueError(f"healthy_z_range must be (low, high) with low < high, got {healthy_z_range}")
            z_range = (lo_z, hi_z)

        if xml_file is not None:  # Gymnasium's MuJoCo convention: the plant's MJCF
            if isinstance(backend, Backend):
                raise ValueError("xml_file applies to a backend given by name, not to a Backend instance")
            if backend == "mujoco":
                if model is not None:
                    raise ValueError("give the MJCF once: as xml_file or as model, not both")
                model = xml_file
            else:  # the twin: the MJCF its model was fitted against (motors, pose, drawing)
                if backend_kwargs and "mjcf" in backend_kwargs:
                    raise ValueError("give the MJCF once: as xml_file or as backend_kwargs['mjcf'], not both")
                backend_kwargs = {**(backend_kwargs or {}), "mjcf": xml_file}
        if isinstance(backend, Backend):
            if model is not None or backend_kwargs:
                raise ValueError("model and backend_kwargs apply to a backend given by name, "
                                 "not to a Backend instance")
            self.backend = backend
        else:
            self.backend = make_backend(backend, model, **(backend_kwargs or {}))
        b = self.backend
        if b.motor.n == 0 and not b.actuator_names:
            raise ValueError("the model has no actuated cables and no actuators: nothing to control")

        self.frame_skip = int(frame_skip)
        b.engine_steps(self.frame_skip)  # the backend can take the control period (ValueError if not)
        self.forward_reward_weight = float(forward_reward_weight)
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        self.reset_noise_scale = float(reset_noise_scale)
        self.terminate_when_unhealthy = bool(terminate_when_unhealthy)
        if healthy_z_range is None:
            self.healthy_z_range = None
        elif z_range is None:  # "auto": from the model's standing pose and ground
            self.healthy_z_range = healthy_range(b.nominal_states(), b.ground)
        else:
            self.healthy_z_range = z_range
        self.exclude_current_positions = bool(exclude_current_positions_from_observation)
        self.render_mode = render_mode
        self.width, self.height, self.camera = int(width), int(height), camera

        self.rest_min = b.motor.rest_min.copy()
        self.rest_max = b.motor.rest_max.copy()
        self.ctrl_low, self.ctrl_high = b.ctrl_bounds()
        self.actuated_index = b.actuated_index
        self.dt = self.frame_skip * b.dt  # control period, s
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.dt)}

        A, U, R = b.motor.n, len(b.actuator_names), b.n_rods
        self._n_motors = A
        self.action_space = spaces.Box(-1.0, 1.0, shape=(A + U,), dtype=np.float32)
        n_obs = len(observation_names(b.rod_names, b.actuated_names, self.exclude_current_positions,
                                      b.actuator_names))
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np.float32)
        assert n_obs == 1 + 18 * R + A + U + (0 if self.exclude_current_positions else 2)

        # the last finite states and observation (what a diverged step falls back to)
        self._states: RodState | None = None
        self._obs: np.ndarray | None = None

    # ------------------------------------------------------------------ helpers
    def _observe(self, states: RodState, rest: np.ndarray) -> np.ndarray:
        act = self.backend.actuator_state() if self.backend.actuator_names else None
        obs = observation(states, rest, self.actuated_index, self.rest_min, self.rest_max,
                          self.exclude_current_positions, act, self.ctrl_low, self.ctrl_high)
        return obs.astype(np.float32)

    def _info(self, com: np.ndarray, com_before: np.ndarray | None) -> dict[str, Any]:
        x, y, z = com.tolist()
        vx = vy = 0.0
        if com_before is not None:
            vx, vy = (x - com_before[0]) / self.dt, (y - com_before[1]) / self.dt
        return {
            "x_position": x,
            "y_position": y,
            "com_height": z,
            "distance_from_origin": (x * x + y * y) ** 0.5,
            "x_velocity": float(vx),
            "y_velocity": float(vy),
            "com": com.copy(),
        }

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        b = self.backend
        start = perturb_start(b.nominal_states(), self.np_random, self.reset_noise_scale)
        b.reset(start, b.nominal_rest_lengths())
        states, rest = b.states(), b.rest_lengths()
        if termination_reason(states, rest, None) is not None:
            raise RuntimeError(f"the {b.name!r} backend returned a non-finite state right after reset")
        self._states, self._obs = states, self._observe(states, rest)
        if self.render_mode == "human":
            self.render()
        return self._obs.copy(), self._info(structure_com(states), None)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._states is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        a = np.asarray(action, dtype=float)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("action must be finite")
        a = np.clip(a, -1.0, 1.0)
        com_before = structure_com(self._states)

        A = self._n_motors
        if self.backend.actuator_names:
            self.backend.set_ctrl(action_to_rest(a[A:], self.ctrl_low, self.ctrl_high))
        self.backend.step(action_to_rest(a[:A], self.rest_min, self.rest_max), self.frame_skip)
        states, rest = self.backend.states(), self.backend.rest_lengths()

        z_range = self.healthy_z_range if self.terminate_when_unhealthy else None
        reason = termination_reason(states, rest, z_range)
        weights = (self.forward_reward_weight, self.ctrl_cost_weight)
        obs = None
        if reason != "non-finite state":
            obs = self._observe(states, rest)
            if not np.all(np.isfinite(obs)):  # finite in float64 but out of float32's range
                reason, obs = "non-finite state", None
        if obs is None:  # diverged: keep the last finite observation, no forward reward
            terms = reward_terms(com_before, com_before, a, self.dt, *weights)
            info = self._info(com_before, com_before)
            obs = self._obs
        else:
            com = structure_com(states)
            terms = reward_terms(com_before, com, a, self.dt, *weights)
            info = self._info(com, com_before)
            self._states, self._obs = states, obs
        info.update(terms)
        terminated = reason is not None
        if terminated:
            info["termination_reason"] = reason
        if self.render_mode == "human":
            self.render()
        return obs.copy(), terms["reward_forward"] + terms["reward_ctrl"], terminated, False, info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; "
                            "pass render_mode='rgb_array' or 'human' to gym.make")
            return None
        if self.render_mode == "rgb_array":
            return self.backend.render(width=self.width, height=self.height, camera=self.camera)
        self.backend.show()
        return None

    def close(self) -> None:
        self.backend.close()
        super().close()
