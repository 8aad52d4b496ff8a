"""The MuJoCo plant: the "real" spring-rod system behind the environment.

One call of :meth:`MujocoPlant.step` is one physics step of length ``dt`` and does, in order:

1. the cable motors move every actuated rest length toward its target (:mod:`tensegrity_gym.cables`)
   and the result is written into ``model.tendon_lengthspring``;
2. the optional push (force ``(R, 3)`` in the world frame, applied at a point given in each rod's
   body frame) is converted to a force and torque at the rod's centre of mass (``xfrc_applied``);
3. ``mujoco.mj_step`` integrates; then the push is cleared.

Recording semantic (what a dataset row ``t`` holds)::

    s_t  = plant.states()            # the state before step t
    plant.set_targets(u_t)           # the command of step t
    plant.step(f_t, p_t)             # the push applied during step t
    r_t  = plant.rest_lengths()      # the rest lengths used during step t
    s_t1 = plant.states()            # the state after step t

Angular velocity is in the world frame everywhere in this API; the conversion from MuJoCo's
body-frame free-joint velocity happens in :meth:`MujocoPlant.states` and its inverse in
:meth:`MujocoPlant.set_states`, nowhere else.
"""

from __future__ import annotations

import os
import sys

# Offscreen rendering on a headless Linux machine: MuJoCo picks its GL back-end from MUJOCO_GL when
# mujoco is first imported, and its default (GLFW) needs a display. When nobody chose and there is
# no display, ask for EGL (works with Mesa's software EGL too). Has no effect if mujoco was already
# imported, or if MUJOCO_GL is set.
if sys.platform.startswith("linux") and "mujoco" not in sys.modules and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from identified.mjcf import ActuatorInfo, SystemDescription, read_system
from identified.rotation import quat_to_matrix
from identified.state import RodState
from tensegrity_gym.cables import MotorSpec, motor_step, read_motor_spec
from tensegrity_gym.checks import check_push, check_rest_lengths, check_targets

__all__ = ["MujocoPlant", "RodState", "standing_pose"]

_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
}


def _load(model: str | os.PathLike | mujoco.MjModel) -> mujoco.MjModel:
    if isinstance(model, mujoco.MjModel):
        return model
    s = os.fspath(model)
    try:
        if s.lstrip().startswith("<"):
            return mujoco.MjModel.from_xml_string(s)
        if not os.path.isfile(s):
            raise ValueError(f"model file '{s}' does not exist")
        return mujoco.MjModel.from_xml_path(s)
    except ValueError as exc:
        msg = [m.strip() for m in str(exc).strip().splitlines() if m.strip()]
        where = f"'{s}'" if not s.lstrip().startswith("<") else "the model"
        # every line of MuJoCo's detail (the XML element and line number), on one line
        raise ValueError(f"MuJoCo cannot load {where}: {'; '.join(msg) if msg else exc}") from None


class MujocoPlant:
    """A spring-rod system simulated by MuJoCo, seen as rod states and cable rest lengths.

    Args:
        model: an MJCF path, MJCF text, or a compiled ``mujoco.MjModel`` (used as is, not copied).
        integrator: ``None`` keeps the model's integrator; ``"euler"``, ``"rk4"``, ``"implicit"``
            or ``"implicitfast"`` overrides it.

    Raises:
        ValueError: the model is not a spring-rod system as :func:`identified.mjcf.read_system`
            reads it (a body moving on a joint that is not a rod, a tendon over a site on no rod or
            between two sites of one rod, a rod with one attachment site, a rod no cable attaches,
            an actuator on something other than a tendon, an actuated name that is not a tendon);
            the message names the element.

    A rod is a free body with all its jointless descendants; its state is the free body's frame
    (MuJoCo's ``qpos`` of its free joint), its centre of mass anywhere in that frame.

    Attributes:
        rod_names, site_names, tendon_names, actuated_names: names in model order (actuated in
            command order: the cables with rest-length motors).
        actuators: the MuJoCo tendon actuators (:class:`~identified.mjcf.ActuatorInfo`), commanded
            by :meth:`set_ctrl`.
        system: the :class:`~identified.mjcf.SystemDescription` read from the compiled model.
        dt: physics time step, s.
        motor: the :class:`~tensegrity_gym.cables.MotorSpec`.
        model, data: the raw MuJoCo objects. As with any ``mj_step``, after :meth:`step` the derived
            quantities in ``data`` (``xpos``, ``site_xpos``, ``ten_length`` ...) still describe the
            state *before* the step; :meth:`states`, :meth:`end_points` and
            :meth:`tendon_lengths` are always current (or call ``mujoco.mj_forward``). The motor
            state lives in the plant: set rest lengths with :meth:`reset`, not by writing
            ``model.tendon_lengthspring``.
    """

    def __init__(self, model: str | os.PathLike | mujoco.MjModel, integrator: str | None = None) -> None:
        self.model = _load(model)
        m = self.model
        if integrator is not None:
            key = str(integrator).lower()
            if key not in _INTEGRATORS:
                raise ValueError(
                    f"unknown integrator '{integrator}'; valid integrators are: {', '.join(_INTEGRATORS)}"
                )
            m.opt.integrator = _INTEGRATORS[key]
        self.data = mujoco.MjData(m)
        try:
            self._validate_and_index()
        except ValueError as exc:  # name the user's file
            if isinstance(model, mujoco.MjModel) or os.fspath(model).lstrip().startswith("<"):
                raise
            raise ValueError(f"'{os.fspath(model)}': {exc}") from None
        self.motor: MotorSpec = read_motor_spec(m)
        tid = {n: i for i, n in enumerate(self.tendon_names)}
        for n in self.motor.names:
            if n not in tid:
                raise ValueError(f"actuated cable '{n}' in tensegrity_actuated is not a tendon of the model")
        self.actuated_names: tuple[str, ...] = self.motor.names
        self._act_idx = np.array([tid[n] for n in self.motor.names], dtype=int)
        self._pull_only = self.model.tendon_lengthspring[:, 0] < self.model.tendon_lengthspring[:, 1]
        self._spring0 = self.model.tendon_lengthspring.copy()  # the MJCF values
        key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "nominal")
        self._key = key if key >= 0 else (0 if m.nkey else -1)  # "nominal", else the first keyframe
        self._act_both = np.flatnonzero(~self._pull_only[self._act_idx])  # actuated push-pull springs
        self._dt = float(m.opt.timestep)
        self._target = np.zeros(len(self.actuated_names))
        self._rest_act = np.zeros(len(self.actuated_names))
        self.reset()

    # ------------------------------------------------------------------ the system, as MuJoCo compiled it
    def _validate_and_index(self) -> None:
        m = self.model
        self.system: SystemDescription = read_system(m)  # rods, sites, cables, actuators (one line on error)
        sysd = self.system
        rods = [r.name for r in sysd.rods]
        bids = [r.body for r in sysd.rods]
        joints = [m.body_jntadr[b] for b in bids]
        self.rod_names: tuple[str, ...] = tuple(rods)
        self.tendon_names: tuple[str, ...] = tuple(t.name for t in sysd.tendons)
        self.site_names: tuple[str, ...] = tuple(
            mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, i) or f"site#{i}" for i in range(m.nsite))
        self._qadr = np.array([m.jnt_qposadr[j] for j in joints])[:, None] + np.arange(7)
        self._vadr = np.array([m.jnt_dofadr[j] for j in joints])[:, None] + np.arange(6)
        self._bid = np.array(bids)
        #: (R, 2, 3) each rod's two attachment sites farthest apart, in the rod frame
        self._ends = np.array([_farthest_pair(r.site_pos[[r.sites.index(a) for a in r.attachments]])
                               for r in sysd.rods])
        self._radius = np.array([r.radius for r in sysd.rods])
        self._mass = m.body_subtreemass[self._bid].copy()
        #: MuJoCo tendon actuators (motor, position, general), in model order
        self.actuators: tuple[ActuatorInfo, ...] = tuple(a for a in sysd.actuators if a.kind != "rest_length")
        self._act_ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a.name)
                                  for a in self.actuators], dtype=int)
        self._act_has_state = np.array([a.dynamics != "none" for a in self.actuators], dtype=bool)
        self._act_stateadr = np.array([m.actuator_actadr[i] for i in self._act_ids], dtype=int)

    # ------------------------------------------------------------------ basic facts
    @property
    def dt(self) -> float:
        """Physics time step, s (``model.opt.timestep``, read once at construction)."""
        return self._dt

    @property
    def n_rods(self) -> int:
        return len(self.rod_names)

    def rod_lengths(self) -> np.ndarray:
        """(R,) distance between each rod's two attachment sites farthest apart (its ends), m."""
        return np.linalg.norm(self._ends[:, 1] - self._ends[:, 0], axis=1)

    def rod_radii(self) -> np.ndarray:
        """(R,) radius of each rod's largest capsule or cylinder geom, its bodies all counted (0 if
        it has none), m."""
        return self._radius.copy()

    def rod_ends(self) -> np.ndarray:
        """(R, 2, 3) each rod's ends (its two attachment sites farthest apart) in the rod frame, m."""
        return self._ends.copy()

    def rest_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(rest_min, rest_max), each (A,), m: the motor range of every actuated cable."""
        return self.motor.rest_min.copy(), self.motor.rest_max.copy()

    # ------------------------------------------------------------------ state
    def reset(self, states: RodState | None = None, rest_lengths: np.ndarray | None = None) -> None:
        """Put the plant at a state with zero time.

        Args:
            states: rod states; ``None`` takes the keyframe ``"nominal"`` (else the model's first
                keyframe, else its ``qpos0``) with zero velocities.
            rest_lengths: (S,) rest length of every tendon (the upper bound for pull-only cables);
                ``None`` restores the MJCF values. Motor targets are set to the actuated rest
                lengths, so the motors hold still until :meth:`set_targets`.
        """
        m, d = self.model, self.data
        if self._key >= 0:
            mujoco.mj_resetDataKeyframe(m, d, self._key)
        else:
            mujoco.mj_resetData(m, d)
        d.qvel[:] = 0.0
        d.ctrl[:] = 0.0 if self._key < 0 else m.key_ctrl[self._key]
        m.tendon_lengthspring[:] = self._spring0
        if rest_lengths is not None:
            self._write_rest(check_rest_lengths(rest_lengths, m.ntendon, self._act_idx, self.motor))
        self._rest_act = m.tendon_lengthspring[self._act_idx, 1].copy()
        self._target = self._rest_act.copy()
        if states is not None:
            self.set_states(states)
        else:
            mujoco.mj_forward(m, d)

    def _write_rest(self, r: np.ndarray) -> None:
        ls = self.model.tendon_lengthspring
        ls[:, 1] = r
        ls[~self._pull_only, 0] = r[~self._pull_only]  # push-pull springs: both ends of the "dead-band"

    def states(self) -> RodState:
        """Current rod states (copies). Angular velocity converted to the world frame: w = R w_body."""
        q = self.data.qpos[self._qadr]  # fancy indexing copies
        v = self.data.qvel[self._vadr]
        quat = q[:, 3:7]
        quat /= np.sqrt(np.einsum("ri,ri->r", quat, quat))[:, None]
        rot = quat_to_matrix(quat)
        return RodState(pos=q[:, :3], quat=quat, vel=v[:, :3], angvel=(rot @ v[:, 3:6, None])[:, :, 0])

    def set_states(self, states: RodState) -> None:
        """Set every rod's state (quaternions normalised; w_body = R^T w) and recompute kinematics."""
        s = RodState(states.pos, states.quat, states.vel, states.angvel).validate(self.n_rods)
        quat = s.quat / np.linalg.norm(s.quat, axis=1, keepdims=True)
        rot = quat_to_matrix(quat)
        d = self.data
        d.qpos[self._qadr[:, :3]] = s.pos
        d.qpos[self._qadr[:, 3:]] = quat
        d.qvel[self._vadr[:, :3]] = s.vel
        d.qvel[self._vadr[:, 3:]] = (rot.transpose(0, 2, 1) @ s.angvel[:, :, None])[:, :, 0]
        mujoco.mj_forward(self.model, d)

    def contact_wrenches(self) -> tuple[np.ndarray, np.ndarray, list[list[int]]]:
        """MuJoCo's contact wrench on every rod at the current state (after :meth:`set_states` or a
        step): force (R, 3) and torque about the rod's centre of mass (R, 3), world, summed over its
        contacts (``mj_contactForce``; a geom of a body nested in a rod is the rod's), and each rod's
        contact indices into ``data.contact``. A developer's view of the plant's contact, for checks
        of a contact law against the truth: the identification never reads it."""
        m, d = self.model, self.data
        if not hasattr(self, "_rod_of_geom"):
            rods = {int(b): r for r, b in enumerate(self._bid)}
            self._rod_of_geom = {}
            for g in range(m.ngeom):
                b = int(m.geom_bodyid[g])
                while b > 0 and b not in rods:
                    b = int(m.body_parentid[b])
                if b in rods:
                    self._rod_of_geom[g] = rods[b]
        force, torque = np.zeros((self.n_rods, 3)), np.zeros((self.n_rods, 3))
        which: list[list[int]] = [[] for _ in range(self.n_rods)]
        c6 = np.zeros(6)
        for i in range(d.ncon):
            con = d.contact[i]
            r = self._rod_of_geom.get(con.geom2, self._rod_of_geom.get(con.geom1))
            if r is None:
                continue
            mujoco.mj_contactForce(m, d, i, c6)
            sign = 1.0 if con.geom2 in self._rod_of_geom else -1.0  # the force on geom2 is +
            frame = con.frame.reshape(3, 3)
            fw, tw = sign * frame.T @ c6[:3], sign * frame.T @ c6[3:]
            force[r] += fw
            torque[r] += np.cross(con.pos - d.subtree_com[self._bid[r]], fw) + tw
            which[r].append(i)
        return force, torque, which

    def rest_lengths(self) -> np.ndarray:
        """(S,) current rest length of every tendon, m (upper bound of a pull-only cable's dead-band)."""
        return self.model.tendon_lengthspring[:, 1].copy()

    def tendon_lengths(self) -> np.ndarray:
        """(S,) current length of every tendon at the current positions, m."""
        mujoco.mj_fwdPosition(self.model, self.data)
        return self.data.ten_length.copy()

    def end_points(self) -> np.ndarray:
        """(R, 2, 3) world positions of every rod's ends (:meth:`rod_ends`), m."""
        s = self.states()
        return s.pos[:, None, :] + np.einsum("rij,rej->rei", quat_to_matrix(s.quat), self._ends)

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def masses(self) -> np.ndarray:
        """(R,) rod masses from the model (each rod's bodies together), kg."""
        return self._mass.copy()

    # ------------------------------------------------------------------ MuJoCo actuators
    @property
    def actuator_names(self) -> tuple[str, ...]:
        """Names of the MuJoCo tendon actuators (``motor``, ``position``, ``general``), model order."""
        return tuple(a.name for a in self.actuators)

    def ctrl_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high), each (U,): every actuator's ``ctrlrange``; ValueError naming an actuator
        without one (an action cannot be scaled onto an unlimited command)."""
        missing = [a.name for a in self.actuators if a.ctrlrange is None]
        if missing:
            raise ValueError(f"actuator '{missing[0]}' has no ctrlrange: give it ctrlrange=\"low high\" "
                             "so that commands can be scaled onto it")
        r = np.array([a.ctrlrange for a in self.actuators], dtype=float).reshape(-1, 2)
        return r[:, 0].copy(), r[:, 1].copy()

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        """Set the (U,) actuator commands (``data.ctrl``; held until changed, clipped by MuJoCo to
        ``ctrlrange`` where the actuator is ctrl-limited)."""
        u = check_targets(ctrl, len(self.actuators))
        self.data.ctrl[self._act_ids] = u

    @property
    def ctrl(self) -> np.ndarray:
        """(U,) current actuator commands."""
        return self.data.ctrl[self._act_ids].copy()

    def actuator_state(self) -> np.ndarray:
        """(U,) what each actuator's force acts on now: its activation (filter or integrator
        dynamics), else its command (in command units, so both normalise alike)."""
        out = self.data.ctrl[self._act_ids].copy()
        if self._act_has_state.any():
            out[self._act_has_state] = self.data.act[self._act_stateadr[self._act_has_state]]
        return out

    # ------------------------------------------------------------------ commands and stepping
    @property
    def targets(self) -> np.ndarray:
        """(A,) current motor targets, m."""
        return self._target.copy()

    def set_targets(self, target_rest: np.ndarray) -> None:
        """Set the (A,) motor targets in metres (clipped into the motor bounds)."""
        t = check_targets(target_rest, len(self.actuated_names))
        self._target = np.minimum(np.maximum(t, self.motor.rest_min), self.motor.rest_max)

    def step(self, push_force: np.ndarray | None = None, push_point: np.ndarray | None = None) -> None:
        """One physics step: motors, then the push, then ``mj_step`` (see the module docstring).

        Args:
            push_force: (R, 3) world-frame force on each rod, N, held during this step only.
            push_point: (R, 3) point of application of each force in the rod's body frame, m
                (``None``: the centre of mass). The torque is (R p) x F about the centre of mass.
        """
        m, d = self.model, self.data
        if self._act_idx.size:
            rest = motor_step(self._rest_act, self._target, self.motor.speed, self._dt,
                              self.motor.rest_min, self.motor.rest_max)
            self._rest_act = rest
            ls = m.tendon_lengthspring
            ls[self._act_idx, 1] = rest
            if self._act_both.size:
                ls[self._act_idx[self._act_both], 0] = rest[self._act_both]
        pushed = push_force is not None
        if pushed or push_point is not None:
            d.xfrc_applied[self._bid] = self._push_wrench(*check_push(push_force, push_point, self.n_rods))
        mujoco.mj_step(m, d)
        if pushed:
            d.xfrc_applied[self._bid] = 0.0

    def _push_wrench(self, push_force: np.ndarray, push_point: np.ndarray | None) -> np.ndarray:
        """(R, 6) force and torque about the free body's own centre of mass (where MuJoCo's
        ``xfrc_applied`` acts), world frame: [F, R (p - c) x F], c that centre in the rod frame."""
        f, p = push_force, push_point  # checked by check_push
        wrench = np.zeros((self.n_rods, 6))
        wrench[:, :3] = f
        ipos = self.model.body_ipos[self._bid]
        if p is not None or np.any(ipos):
            p = np.zeros((self.n_rods, 3)) if p is None else p
            quat = self.data.qpos[self._qadr[:, 3:]]
            quat /= np.sqrt(np.einsum("ri,ri->r", quat, quat))[:, None]
            a = (quat_to_matrix(quat) @ (p - ipos)[:, :, None])[:, :, 0]  # lever arm in the world frame
            wrench[:, 3] = a[:, 1] * f[:, 2] - a[:, 2] * f[:, 1]
            wrench[:, 4] = a[:, 2] * f[:, 0] - a[:, 0] * f[:, 2]
            wrench[:, 5] = a[:, 0] * f[:, 1] - a[:, 1] * f[:, 0]
        return wrench

    # ------------------------------------------------------------------ rendering
    def render(self, width: int = 640, height: int = 480, camera: str | int | None = None,
               distance: float | None = None) -> np.ndarray:
        """(height, width, 3) uint8 RGB image of the current state (offscreen, ``mujoco.Renderer``).

        ``camera=None`` uses a free camera looking at the mean rod position from ``distance``
        (default: 2.5 times the longest rod). Offscreen GL must work: set ``MUJOCO_GL=egl`` (GPU) or
        ``MUJOCO_GL=osmesa`` (software) before importing mujoco if the default does not.
        Raises RuntimeError with that advice when no GL context can be made.
        """
        if self._renderer is None or self._renderer_size != (width, height):
            self.close()
            try:
                self._renderer = mujoco.Renderer(self.model, height=height, width=width)
            except Exception as exc:  # noqa: BLE001 - GL back-ends raise assorted types
                raise RuntimeError(
                    f"offscreen rendering is not available ({type(exc).__name__}: {exc}); set "
                    "MUJOCO_GL=egl or MUJOCO_GL=osmesa (needs libEGL or libOSMesa) before importing mujoco"
                ) from None
            self._renderer_size = (width, height)
        mujoco.mj_fwdPosition(self.model, self.data)  # current poses (mj_step leaves the previous ones)
        if camera is None:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FREE
            cam.lookat[:] = self.states().pos.mean(axis=0)
            cam.distance = distance if distance is not None else 2.5 * float(self.rod_lengths().max())
            cam.azimuth, cam.elevation = 135.0, -25.0
            self._renderer.update_scene(self.data, camera=cam)
        else:
            self._renderer.update_scene(self.data, camera=camera)
        return self._renderer.render().copy()

    _renderer: mujoco.Renderer | None = None
    _renderer_size: tuple[int, int] | None = None

    def close(self) -> None:
        """Free the renderer (if one was made)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def standing_pose(plant: MujocoPlant, settle_time: float = 5.0) -> tuple[RodState, str]:
    """The pose a model stands in, with zero velocities, and where it came from.

    Its keyframe ``"nominal"``, else its first keyframe; a model without a keyframe is released
    from ``qpos0`` (motors and actuators at rest) and simulated for ``settle_time`` seconds, and
    the pose it has then is its standing pose (what a lab does with a robot put on the floor).
    The plant is left reset.
    """
    plant.reset()
    if plant._key >= 0:
        name = mujoco.mj_id2name(plant.model, mujoco.mjtObj.mjOBJ_KEY, plant._key) or str(plant._key)
        how = f"keyframe '{name}'"
    else:
        for _ in range(max(1, round(settle_time / plant.dt))):
            plant.step()
        how = f"settled for {settle_time:g} s from qpos0"
    s = plant.states()
    plant.reset()
    zero = np.zeros_like(s.pos)
    return RodState(s.pos, s.quat, zero, zero.copy()), how


def _farthest_pair(p: np.ndarray) -> np.ndarray:
    """(2, 3) the two points of ``p`` (n, 3) farthest apart."""
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    return p[[i, j]]
