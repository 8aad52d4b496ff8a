"""The natively batched twin: N TensegrityIco-v0 (or Tensegrity-v0) envs on the identified engine
in one vector env.

``gym.make_vec("TensegrityIco-v0", num_envs=N, vectorization_mode="vector_entry_point",
backend="identified", model="F.json")`` builds :class:`TensegrityIcoVectorEnv`: the N envs' rod
states live in tensors ``(N, R, ·)`` and every physics substep is ONE batched engine call
(:class:`~tensegrity_gym.backends.twin_physics.TwinPhysics`). ``gym.make_vec("Tensegrity-v0",
num_envs=N, backend="identified", xml_file=PATH, model="F.json")`` is the same for any tensegrity
MJCF: its actions are the rest-length motors' targets, then its MuJoCo tendon actuators' commands,
whose force and activation the batch steps with the identified law of the single twin
(:class:`~identified.engine.actuators.ActuatorBank`, one batched call). Observation, reward and
termination are the env's pure functions (:mod:`tensegrity_gym.envs.tensegrity_ico_v0`) applied to
the batch — the same functions, which work over a leading batch dimension (:func:`batch_observation`,
:func:`batch_termination_reason` and :func:`batch_reward_terms` are thin aliases); tests check them
against the single-env calls. The batched functions cost about 1 ms per step at N = 1024, a Python
loop over the single-env functions ~30 times more (measured 2026-11-23, ``benchmarks/README.md``).

Semantics are those of a :class:`gymnasium.vector.SyncVectorEnv` over N single twin envs made with
``gym.make`` (same seeds, same actions, same results, infos in the same dict-of-arrays layout with
``_key`` masks): sub-env ``i`` of ``reset(seed=s)`` is seeded with ``s + i``; the episode time
limit (``max_episode_steps``, 1000 from the registration) truncates; autoreset follows
``autoreset_mode`` (:class:`gymnasium.vector.AutoresetMode`; ``NEXT_STEP`` by default, also
``SAME_STEP`` and ``DISABLED``); ``reset(options={"reset_mask": mask})`` resets some sub-envs. A
sub-env whose physics diverges terminates with ``info["termination_reason"] = "non-finite state"``
and its last finite observation, exactly as the single env.

The registered ``vector_entry_point`` is :func:`make_vector_env` (:func:`make_tensegrity_vector_env`
for Tensegrity-v0): with ``backend="identified"`` it builds this class; with any other backend
(the MuJoCo plant, which cannot be batched) it returns a ``SyncVectorEnv`` of single envs, so
``gym.make_vec("TensegrityIco-v0", num_envs=N)`` keeps giving N plants.

Domain randomization (``randomize=``, a :class:`~tensegrity_gym.randomize.Randomization`): every
sub-env draws its own spring, rod, contact, rest-offset and motor parameters, its command latency,
at each of its resets from its own generator (seeded as its reset state is: the same seed, the same
draw); observation noise and pushes come from one generator seeded by ``reset(seed=...)``. The
latency delays the actuators' commands with the motors' targets. The
physics carries the parameters as tensors with a leading env dimension
(:class:`~tensegrity_gym.backends.twin_physics.TwinPhysics` ``per_env``), so a step is still one
batched engine call. Without ``randomize`` (or with nothing to draw) nothing of this runs.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from identified.effects import EFFECTS
from identified.state import RodState
from tensegrity_gym.backends.identified_backend import IdentifiedBackend
from tensegrity_gym.backends.twin_physics import TwinPhysics
from tensegrity_gym.envs.tensegrity_ico_v0 import (
    TensegrityIcoEnv,
    action_to_rest,
    observation,
    perturb_start,
    reward_terms,
    termination_reasons,
    turn_about_vertical,
)
from tensegrity_gym.randomize import CONTACT_LAWS, CONTACT_PARAMETERS, Randomization

__all__ = [
    "TensegrityIcoVectorEnv",
    "batch_observation",
    "batch_reward_terms",
    "batch_termination_reason",
    "make_tensegrity_vector_env",
    "make_vector_env",
]

NON_FINITE = "non-finite state"


# ---------------------------------------------------------------------- batched pure functions
def batch_observation(pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
                      rest_lengths: np.ndarray, actuated_index: np.ndarray, rest_min: np.ndarray,
                      rest_max: np.ndarray, exclude_current_positions: bool = True,
                      actuator_state: np.ndarray | None = None, ctrl_low: np.ndarray | None = None,
                      ctrl_high: np.ndarray | None = None) -> np.ndarray:
    """(N, n_obs) float64: the env's own :func:`~tensegrity_gym.envs.tensegrity_ico_v0.observation`
    on a batch (``pos``, ``vel``, ``angvel`` (N, R, 3), ``quat`` (N, R, 4), ``rest_lengths`` (N, S),
    ``actuator_state`` (N, U) or ``None`` without MuJoCo actuators)."""
    return observation(RodState(pos, quat, vel, angvel), rest_lengths, actuated_index, rest_min, rest_max,
                       exclude_current_positions, actuator_state, ctrl_low, ctrl_high)


def batch_termination_reason(pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
                             rest_lengths: np.ndarray, healthy_z_range: tuple[float, float] | None
                             ) -> np.ndarray:
    """(N,) object array: the env's own termination reasons of every row (``None``: goes on)."""
    return termination_reasons(pos, quat, vel, angvel, rest_lengths, healthy_z_range)


def batch_reward_terms(com_before: np.ndarray, com_after: np.ndarray, action: np.ndarray,
                       dt_control: float, forward_reward_weight: float, ctrl_cost_weight: float
                       ) -> dict[str, np.ndarray]:
    """(N,) ``reward_forward`` and ``reward_ctrl``: the env's own
    :func:`~tensegrity_gym.envs.tensegrity_ico_v0.reward_terms` on a batch."""
    return reward_terms(com_before, com_after, action, dt_control, forward_reward_weight, ctrl_cost_weight)


# ---------------------------------------------------------------------- the vector env
class TensegrityIcoVectorEnv(VectorEnv):
    """N TensegrityIco-v0 (or Tensegrity-v0) twins stepped by one batched identified engine (see the
    module docstring).

    Args:
        num_envs: N, the number of sub-envs.
        model: identified-model JSON or :class:`~identified.model.IdentifiedModel` (``None``: the
            shipped robot model), as for the single twin.
        max_episode_steps: truncate an episode after this many steps (``None``: never);
            ``gym.make_vec`` passes the registration's 1000.
        autoreset_mode: :class:`gymnasium.vector.AutoresetMode` or its value.
        backend_kwargs: keyword arguments of :class:`IdentifiedBackend` (``dtype``, ``device``,
            ``effects``, ``mjcf``, ``num_threads``, ``compile``).
        chunk_size: ``None`` (default): one engine call per physics substep for all N envs; an int
            steps blocks of that many envs one after the other (faster on a CPU for large N, see
            :class:`TwinPhysics`; not with a randomization of the physics).
        randomize: a :class:`~tensegrity_gym.randomize.Randomization` (or its JSON mapping) drawn
            per sub-env at every reset (module docstring); ``None``: the identified values.
        per_env_parameters: give every sub-env its own copy of the physical parameters (the
            identified values) even when nothing is drawn: the engine a randomized twin of the same
            size steps, so its compiled substep (cached on disk) serves this twin too, e.g. the
            policy's evaluation after a randomized training.
        env_class: the single env the sub-envs are (:class:`TensegrityIcoEnv` or a subclass, e.g.
            :class:`~tensegrity_gym.envs.tensegrity_v0.TensegrityEnv`); ``xml_file`` in
            ``env_kwargs`` is the MJCF the model was fitted against, as for the single twin.
        **env_kwargs: every other keyword argument of :class:`TensegrityIcoEnv` (``frame_skip``,
            reward weights, ``reset_noise_scale``, ``healthy_z_range``, ``render_mode`` (only
            ``"rgb_array"``: :meth:`render` returns one image per sub-env), ...).

    Attributes beyond :class:`~gymnasium.vector.VectorEnv`'s: ``env`` (a single
    :class:`TensegrityIcoEnv` on the same model that holds the configuration and draws),
    ``physics`` (the batched :class:`TwinPhysics`), ``dt`` (control period, s).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"],
                                          "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, model: str | os.PathLike | Any | None = None, *,
                 max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                 backend_kwargs: dict[str, Any] | None = None, chunk_size: int | None = None,
                 randomize: Randomization | dict[str, Any] | None = None, per_env_parameters: bool = False,
                 env_class: type[TensegrityIcoEnv] = TensegrityIcoEnv, **env_kwargs: Any) -> None:
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs}")
        limit = max_episode_steps
        if limit is not None and (int(limit) != limit or limit < 1):
            raise ValueError(f"max_episode_steps must be an integer >= 1 or None, got {limit}")
        if env_kwargs.get("render_mode") not in (None, "rgb_array"):
            raise ValueError("the batched twin renders only 'rgb_array', got "
                             f"render_mode={env_kwargs['render_mode']!r}")
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        self.num_envs = int(num_envs)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)

        xml_file = env_kwargs.pop("xml_file", None)
        if xml_file is not None:  # as the single twin: the MJCF its model was fitted against
            if backend_kwargs and "mjcf" in backend_kwargs:
                raise ValueError("give the MJCF once: as xml_file or as backend_kwargs['mjcf'], not both")
            backend_kwargs = {**(backend_kwargs or {}), "mjcf": xml_file}
        backend = IdentifiedBackend(model, **(backend_kwargs or {}))
        self.env = env_class(backend=backend, **env_kwargs)  # validates the arguments
        e = self.env
        self.backend = backend
        if isinstance(randomize, dict):
            randomize = Randomization.from_json(randomize, source="mapping")
        self.randomize = randomize if randomize is not None and randomize.active else None
        per_env = bool(per_env_parameters) or (self.randomize is not None and self.randomize.physical)
        self.physics = TwinPhysics(backend.engine, backend.motor, backend.actuated_index, batch=self.num_envs,
                                   chunk_size=chunk_size, num_threads=backend.num_threads,
                                   compile=backend.compile, per_env=per_env,
                                   actuators=backend.actuator_bank if backend.actuator_names else None)
        self._n_motors, self._n_actuators = backend.motor.n, len(backend.actuator_names)
        self._engine_steps = backend.engine_steps(e.frame_skip)  # engine steps a control period (physics_dt)
        self.dt = e.dt
        self.render_mode = e.render_mode
        self.metadata = {**self.metadata, "render_fps": e.metadata["render_fps"],
                         "autoreset_mode": self.autoreset_mode}
        self.single_observation_space = e.observation_space
        self.single_action_space = e.action_space
        self.observation_space = batch_space(e.observation_space, self.num_envs)
        self.action_space = batch_space(e.action_space, self.num_envs)

        N, R = self.num_envs, backend.n_rods
        self._nominal = backend.nominal_states()
        self._nominal_rest = backend.nominal_rest_lengths()
        self._rngs: list[np.random.Generator | None] = [None] * N
        self._seeds: list[int | None] = [None] * N
        self._pos = np.zeros((N, R, 3))  # last finite states, (N, R, ·)
        self._quat = np.zeros((N, R, 4))
        self._com = np.zeros((N, 3))  # structure centre of the last finite states
        self._obs = np.zeros((N,) + e.observation_space.shape, dtype=np.float32)  # last finite observations
        self._elapsed = np.zeros(N, dtype=np.int64)
        self._autoreset = np.zeros(N, dtype=bool)
        self._needs_reset = True
        if self.randomize is not None:
            self._setup_randomization(self.randomize)

    # ------------------------------------------------------------------ randomization
    def _setup_randomization(self, r: Randomization) -> None:
        """The identified values the draws scale, the latency queue and the noise scales."""
        e, N = self.env, self.num_envs
        p = self.physics.engine.params
        self._base = {k: getattr(p, k)[0].detach().cpu().double().numpy().copy()
                      for k in ("stiffness", "damping", "mass", "inertia")}
        self._base_effects = {k: v[0, 0].detach().cpu().double().numpy().copy()
                              for k, v in self.physics.effect_parameters().items()}
        # the model's ground-contact law and where its parameters sit among CONTACT_PARAMETERS
        law = next((k for k in self._base_effects if k in CONTACT_LAWS), None)
        self._contact = None if law is None else (
            law, [CONTACT_PARAMETERS.index(b.name) for b in EFFECTS[law].blocks][:len(self._base_effects[law])])
        A, U = self._n_motors, self._n_actuators
        self._latency = np.zeros(N, dtype=np.int64)
        # the commands in flight: the motors' targets (A), then the actuators' commands (U)
        self._queue = np.tile(np.concatenate([action_to_rest(np.zeros(A), e.rest_min, e.rest_max), np.zeros(U)]),
                              (N, r.latency + 1, 1))
        R = self.backend.n_rods
        sizes = ([] if e.exclude_current_positions else [("pos", 2)]) + [
            ("pos", 1), ("pos", 3 * R), ("rot", 9 * R), ("vel", 3 * R), ("angvel", 3 * R), ("rest", A + U)]
        std = np.concatenate([np.full(n, r.obs_noise.get(g, 0.0)) for g, n in sizes])
        self._obs_std = std.astype(np.float32) if std.any() else None
        self._noise_rng = np.random.default_rng()

    def _draw(self, index: np.ndarray) -> None:
        """Every sub-env of ``index`` draws its parameters from its own generator."""
        r, b = self.randomize, self.backend
        assert r is not None
        draws = [r.draw(self._rng(int(i)), b.n_rods, len(b.tendon_names)) for i in index]
        self._latency[index] = [d.latency for d in draws]
        nominal = self.physics.rest_numpy()[index][:, b.actuated_index]
        held = np.concatenate([nominal, self.physics.ctrl.detach().cpu().double().numpy()[index]], axis=-1)
        self._queue[index] = held[:, None, :]
        if not self.physics.per_env:
            return
        base = self._base
        effects = {}
        if self._contact is not None:
            law, columns = self._contact
            th = np.tile(self._base_effects[law], (len(index), 1))
            th[:, :len(columns)] *= np.stack([d.contact[columns] for d in draws])
            effects[law] = th
        self.physics.set_parameters(
            index,
            stiffness=base["stiffness"] * np.stack([d.stiffness for d in draws]),
            damping=base["damping"] * np.stack([d.damping for d in draws]),
            mass=base["mass"] * np.stack([d.mass for d in draws]),
            inertia=base["inertia"] * np.stack([d.inertia for d in draws])[..., None],
            rest_offset=np.stack([d.rest_offset for d in draws]),
            motor_speed=b.motor.speed * np.array([d.motor_speed for d in draws]),
            effects=effects)

    def _commands(self, commands: np.ndarray) -> np.ndarray:
        """The commands that act now (N, A + U: the motors' targets, the actuators' commands): each
        sub-env's of ``latency`` steps ago."""
        if self.randomize is None or self.randomize.latency == 0:
            return commands
        q = self._queue
        q[:, 1:] = q[:, :-1].copy()
        q[:, 0] = commands
        return q[np.arange(self.num_envs), self._latency]

    def _observe(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray, rest: np.ndarray,
                 index: np.ndarray) -> np.ndarray:
        """(n, n_obs) float64 observations of the sub-envs ``index`` at these states (n rows each)."""
        e = self.env
        act = self.physics.actuator_state_numpy()[index] if self._n_actuators else None
        return batch_observation(pos, quat, vel, angvel, rest, e.actuated_index, e.rest_min, e.rest_max,
                                 e.exclude_current_positions, act, e.ctrl_low, e.ctrl_high)

    def _pushes(self) -> np.ndarray | None:
        """(N, R, 3) world forces of this step's random pushes (``None`` without pushes)."""
        r = self.randomize
        if r is None or r.push_force <= 0 or r.push_probability <= 0:
            return None
        N, R = self.num_envs, self.backend.n_rods
        g = self._noise_rng
        hit = g.random(N) < r.push_probability
        rod, angle, size = g.integers(0, R, N), g.uniform(0, 2 * np.pi, N), g.uniform(0, r.push_force, N)
        f = np.zeros((N, R, 3))
        f[np.arange(N), rod, 0] = np.where(hit, size * np.cos(angle), 0.0)
        f[np.arange(N), rod, 1] = np.where(hit, size * np.sin(angle), 0.0)
        return f

    def _observed(self, obs: np.ndarray) -> np.ndarray:
        """What the policy sees: the observations plus the randomization's sensor noise."""
        if self.randomize is None or self._obs_std is None:
            return obs
        noise = self._noise_rng.standard_normal(obs.shape).astype(np.float32) * self._obs_std
        return obs + noise

    # ------------------------------------------------------------------ seeding
    @property
    def np_random(self) -> tuple[np.random.Generator, ...]:
        """Every sub-env's generator (drawn from a random seed on first use, as a single env does)."""
        return tuple(self._rng(i) for i in range(self.num_envs))

    @property
    def np_random_seed(self) -> tuple[int | None, ...]:
        for i in range(self.num_envs):
            self._rng(i)
        return tuple(self._seeds)

    def _rng(self, i: int) -> np.random.Generator:
        if self._rngs[i] is None:
            self._rngs[i], self._seeds[i] = seeding.np_random()
        return self._rngs[i]  # type: ignore[return-value]

    # ------------------------------------------------------------------ internals
    def _restart(self, index: np.ndarray) -> dict[str, Any]:
        """Reset the sub-envs ``index`` (perturbed nominal pose from each one's generator); returns
        their reset infos in vector layout (keys masked to ``index``)."""
        e = self.env
        starts = [perturb_start(self._nominal, self._rng(int(i)), e.reset_noise_scale) for i in index]
        if self.randomize is not None and self.randomize.reset_yaw > 0:  # a heading per start
            w = self.randomize.reset_yaw
            starts = [turn_about_vertical(s, float(self._rng(int(i)).uniform(-w, w))) for s, i in zip(starts, index)]
        pos = np.stack([s.pos for s in starts])
        quat = np.stack([s.quat for s in starts])
        quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
        vel = np.stack([s.vel for s in starts])
        angvel = np.stack([s.angvel for s in starts])
        rest = np.tile(self._nominal_rest, (len(index), 1))
        self.physics.reset(pos, quat, vel, angvel, rest, index=index)
        if self.randomize is not None:
            self._draw(index)
        # read back through the engine's dtype, as the single env reads its backend
        pos, quat, vel, angvel = (x[index] for x in self.physics.states_numpy())
        quat = quat / np.sqrt(np.einsum("nri,nri->nr", quat, quat))[..., None]
        rest = self.physics.rest_numpy()[index]
        obs = self._observe(pos, quat, vel, angvel, rest, index)
        self._pos[index], self._quat[index] = pos, quat
        self._com[index] = pos.mean(axis=1)
        self._obs[index] = obs.astype(np.float32)
        self._elapsed[index] = 0
        self._autoreset[index] = False
        return self._infos(index, self._com[index], None)

    def _infos(self, index: np.ndarray, com: np.ndarray, com_before: np.ndarray | None,
               extra: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
        """The single env's info dicts of the sub-envs ``index`` in the vector layout (SyncVectorEnv's)."""
        N = self.num_envs
        mask = np.zeros(N, dtype=bool)
        mask[index] = True
        v = np.zeros((len(index), 2)) if com_before is None else (com[:, :2] - com_before[:, :2]) / self.dt
        values = {
            "x_position": com[:, 0],
            "y_position": com[:, 1],
            "com_height": com[:, 2],
            "distance_from_origin": np.sqrt(com[:, 0] ** 2 + com[:, 1] ** 2),
            "x_velocity": v[:, 0],
            "y_velocity": v[:, 1],
        }
        out: dict[str, Any] = {}
        for key, val in values.items():
            a = np.zeros(N)
            a[index] = val
            out[key], out[f"_{key}"] = a, mask.copy()
        c = np.zeros((N, 3))
        c[index] = com
        out["com"], out["_com"] = c, mask.copy()
        for key, val in (extra or {}).items():
            a = np.zeros(N)
            a[index] = val
            out[key], out[f"_{key}"] = a, mask.copy()
        return out

    @staticmethod
    def _merge(into: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
        """Merge the vector infos of two disjoint sets of sub-envs (``other``'s entries win)."""
        for key, val in other.items():
            if key.startswith("_"):
                continue
            mask = other[f"_{key}"]
            if key not in into:
                into[key], into[f"_{key}"] = val, mask.copy()
            elif isinstance(val, dict):
                into[key] = TensegrityIcoVectorEnv._merge(into[key], val)
                into[f"_{key}"] = into[f"_{key}"] | mask
            else:
                into[key][mask] = val[mask]
                into[f"_{key}"] = into[f"_{key}"] | mask
        return into

    # ------------------------------------------------------------------ Gymnasium vector API
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every sub-env (or those of ``options["reset_mask"]``); ``seed``: ``None``, an int
        (sub-env ``i`` gets ``seed + i``) or one seed (or ``None``) per sub-env."""
        N = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * N
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(N)]
        else:
            seeds = list(seed)
            if len(seeds) != N:
                raise ValueError(f"If seeds are passed as a list the length must match num_envs={N} but got "
                                 f"length={len(seeds)}.")
        mask = np.ones(N, dtype=bool)
        if options is not None and "reset_mask" in options:
            mask = options["reset_mask"]
            if not isinstance(mask, np.ndarray):
                raise TypeError(f"`options['reset_mask']` must be a numpy array, got {type(mask)}")
            if mask.shape != (N,):
                raise ValueError(f"`options['reset_mask']` must have shape `({N},)`, got {mask.shape}")
            if mask.dtype != np.bool_:
                raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got {mask.dtype}")
            if not mask.any():
                raise ValueError("`options['reset_mask']` must contain a boolean array with at least one "
                                 f"True value, got reset_mask={mask}")
        index = np.flatnonzero(mask)
        for i in index:
            if seeds[i] is not None:
                self._rngs[i], self._seeds[i] = seeding.np_random(int(seeds[i]))  # type: ignore[arg-type]
        given = [int(x) for x in seeds if x is not None]
        if self.randomize is not None and given:
            self._noise_rng = np.random.default_rng([given[0], 1])
        infos = self._restart(index)
        self._needs_reset = False
        return self._observed(self._obs.copy()), infos

    def step(self, actions: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._needs_reset:
            raise gym.error.ResetNeeded("call reset() before step()")
        e, N = self.env, self.num_envs
        a = np.asarray(actions, dtype=float)
        if a.shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("actions must be finite")
        a = np.clip(a, -1.0, 1.0)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            restart = self._autoreset.copy()
        else:
            if self.autoreset_mode == AutoresetMode.DISABLED and self._autoreset.any():
                ended = np.flatnonzero(self._autoreset).tolist()
                raise RuntimeError(f"sub-envs {ended} ended and autoreset is disabled: reset them with "
                                   "reset(options={'reset_mask': mask}) first")
            restart = np.zeros(N, dtype=bool)
        stepped = np.flatnonzero(~restart)

        # physics: one batched engine call per substep for every sub-env (restarting ones are
        # overwritten below; stepping them too is cheaper than a gather and a scatter)
        ph = self.physics
        A = self._n_motors
        now = self._commands(np.concatenate([action_to_rest(a[:, :A], e.rest_min, e.rest_max),
                                             action_to_rest(a[:, A:], e.ctrl_low, e.ctrl_high)], axis=-1))
        ph.set_targets(now[:, :A])
        if self._n_actuators:
            ph.set_ctrl(now[:, A:])
        ph.step(self._engine_steps, self._pushes())
        pos, quat, vel, angvel = ph.states_numpy()
        quat = quat / np.sqrt(np.einsum("nri,nri->nr", quat, quat))[..., None]
        rest = ph.rest_numpy()

        rewards = np.zeros(N)
        terminated = np.zeros(N, dtype=bool)
        truncated = np.zeros(N, dtype=bool)
        infos: dict[str, Any] = {}
        if stepped.size:
            s = stepped
            z_range = e.healthy_z_range if e.terminate_when_unhealthy else None
            reason = batch_termination_reason(pos[s], quat[s], vel[s], angvel[s], rest[s], z_range)
            ok = reason != NON_FINITE
            obs = np.zeros((s.size,) + self._obs.shape[1:], dtype=np.float32)
            if ok.any():
                o64 = self._observe(pos[s[ok]], quat[s[ok]], vel[s[ok]], angvel[s[ok]], rest[s[ok]], s[ok])
                o32 = o64.astype(np.float32)
                bad32 = ~np.isfinite(o32).all(axis=1)  # finite in float64, beyond float32's range
                idx = np.flatnonzero(ok)
                reason[idx[bad32]] = NON_FINITE
                ok[idx[bad32]] = False
                obs[ok] = o32[~bad32]
            com_before = self._com[s]
            com = com_before.copy()
            good = s[ok]
            com[ok] = pos[good].mean(axis=1)
            obs[~ok] = self._obs[s[~ok]]  # diverged: the last finite observation, no forward reward
            terms = batch_reward_terms(com_before, com, a[s], self.dt, e.forward_reward_weight,
                                       e.ctrl_cost_weight)
            rewards[s] = terms["reward_forward"] + terms["reward_ctrl"]
            self._obs[s] = obs
            self._com[good] = com[ok]
            self._pos[good], self._quat[good] = pos[good], quat[good]
            ended = np.array([r is not None for r in reason], dtype=bool)
            terminated[s] = ended
            self._elapsed[s] += 1
            if self.max_episode_steps is not None:
                truncated[s] = self._elapsed[s] >= self.max_episode_steps
            infos = self._infos(s, com, com_before, terms)
            if ended.any():
                tr = np.full(N, None, dtype=object)
                tr[s[ended]] = reason[ended]
                m = np.zeros(N, dtype=bool)
                m[s[ended]] = True
                infos["termination_reason"], infos["_termination_reason"] = tr, m

        done = terminated | truncated
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            if restart.any():
                infos = self._merge(infos, self._restart(np.flatnonzero(restart)))
            self._autoreset = done
        elif self.autoreset_mode == AutoresetMode.SAME_STEP:
            if done.any():
                d = np.flatnonzero(done)
                final_obs = np.full(N, None, dtype=object)
                for i in d:
                    final_obs[i] = self._obs[i].copy()
                step_info = _select(infos, done)
                top = _select(infos, ~done)
                top = self._merge(top, self._restart(d))
                top["final_obs"], top["_final_obs"] = final_obs, done.copy()
                top["final_info"], top["_final_info"] = step_info, done.copy()
                infos = top
        else:
            self._autoreset = done
        return self._observed(self._obs.copy()), rewards, terminated, truncated, infos

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One (height, width, 3) uint8 image per sub-env (the last finite rod states), with
        ``render_mode="rgb_array"``."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' to make_vec")
            return None
        return tuple(self.render_sub_env(i) for i in range(self.num_envs))

    def render_sub_env(self, index: int) -> np.ndarray:
        """The (height, width, 3) uint8 image of sub-env ``index`` alone (its last finite rod states),
        drawn as :meth:`render` draws each."""
        if not 0 <= int(index) < self.num_envs:
            raise IndexError(f"sub-env {index} of {self.num_envs}")
        e, b = self.env, self.backend
        zeros = np.zeros((b.n_rods, 3))
        return b.render_states(RodState(self._pos[index], self._quat[index], zeros, zeros), e.width, e.height,
                               e.camera)

    # ------------------------------------------------------------------ attributes (SyncVectorEnv's API)
    def get_attr(self, name: str) -> tuple[Any, ...]:
        """The single env's attribute ``name`` (shared by every sub-env), once per sub-env."""
        return tuple(getattr(self.env, name) for _ in range(self.num_envs))

    def set_attr(self, name: str, values: Any) -> None:
        """Set a configuration attribute of the (shared) single env; a list must hold one value for all."""
        if isinstance(values, (list, tuple)):
            if len(values) != self.num_envs or any(v != values[0] for v in values[1:]):
                raise ValueError("the batched twin's sub-envs share their configuration: give one value")
            values = values[0]
        setattr(self.env, name, values)

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """SyncVectorEnv's ``call``: ``"render"`` gives :meth:`render`'s images; another name must be
        a configuration attribute of the single env (the same for every sub-env), returned once per
        sub-env. Sub-envs are rows of one tensor, not objects, so their methods cannot be called."""
        if name == "render":
            frames = self.render()
            return frames if frames is not None else (None,) * self.num_envs
        attr = getattr(self.env, name)
        if callable(attr):
            raise NotImplementedError(f"the batched twin's sub-envs are rows of one tensor; they have no "
                                      f"method {name!r} to call one by one")
        return (attr,) * self.num_envs

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()


def _select(infos: dict[str, Any], mask: np.ndarray) -> dict[str, Any]:
    """The part of a vector info that belongs to the sub-envs in ``mask`` (others masked out)."""
    out: dict[str, Any] = {}
    for key, val in infos.items():
        if key.startswith("_"):
            continue
        m = infos[f"_{key}"] & mask
        if not m.any():
            continue
        if isinstance(val, dict):
            out[key] = _select(val, mask)
        else:
            v = val.copy()
            v[~m] = None if v.dtype == object else 0
            out[key] = v
        out[f"_{key}"] = m
    return out


def make_vector_env(num_envs: int = 1, backend: str | Any = "mujoco", **kwargs: Any) -> VectorEnv:
    """The ``vector_entry_point`` of TensegrityIco-v0 (``gym.make_vec``).

    ``backend="identified"``: a :class:`TensegrityIcoVectorEnv` (the batched twin); ``kwargs`` as
    for it. Any other backend: a :class:`gymnasium.vector.SyncVectorEnv` of ``num_envs`` single
    envs, each ``gym.make("TensegrityIco-v0", backend=backend, **kwargs)`` (``max_episode_steps``
    becomes their time limit; ``autoreset_mode`` goes to the SyncVectorEnv).
    """
    return _make("TensegrityIco-v0", TensegrityIcoEnv, num_envs, backend, **kwargs)


def make_tensegrity_vector_env(num_envs: int = 1, backend: str | Any = "mujoco", **kwargs: Any) -> VectorEnv:
    """The ``vector_entry_point`` of Tensegrity-v0 (any MJCF, ``xml_file=PATH``), as
    :func:`make_vector_env`: the batched twin with ``backend="identified"``, else a
    ``SyncVectorEnv`` of ``gym.make("Tensegrity-v0", ...)`` plants."""
    from tensegrity_gym.envs.tensegrity_v0 import TensegrityEnv

    return _make("Tensegrity-v0", TensegrityEnv, num_envs, backend, **kwargs)


def _make(env_id: str, env_class: type[TensegrityIcoEnv], num_envs: int, backend: str | Any,
          **kwargs: Any) -> VectorEnv:
    if backend == "identified":
        return TensegrityIcoVectorEnv(num_envs, env_class=env_class, **kwargs)
    if not isinstance(backend, str):
        raise TypeError("make_vec needs the backend by name (one backend instance cannot serve several envs)")
    autoreset_mode = kwargs.pop("autoreset_mode", AutoresetMode.NEXT_STEP)
    env_kwargs = {**kwargs, "backend": backend}

    def make_one() -> gym.Env:
        return gym.make(env_id, **env_kwargs)

    return gym.vector.SyncVectorEnv([make_one for _ in range(int(num_envs))], autoreset_mode=autoreset_mode)
