"""The physics backend protocol: what the env may ask of a plant or of a twin.

A backend is a spring-rod system that takes cable commands (and optional pushes) and gives back
rod states and the cables' actual rest lengths. Nothing else flows from a backend to the env: the
env (:mod:`tensegrity_gym.envs.tensegrity_ico_v0`) computes observation, reward and termination
from :class:`~identified.state.RodState` and rest lengths alone, so that the MuJoCo plant and
the identified twin cannot drift apart (as Brax puts one env API over several pipelines).

Static metadata a backend exposes (fixed for its lifetime):

* ``rod_names`` (R,), ``tendon_names`` (S,), ``actuated_names`` (A,) — actuated in command order;
* ``dt`` — one physics step, s;
* ``motor`` — the :class:`~tensegrity_gym.cables.MotorSpec` (speed, rest_min, rest_max per
  actuated cable), the one motor model both backends share;
* ``actuator_names`` (U,) — MuJoCo tendon actuators (``motor``, ``position``, ``general``), with
  :meth:`Backend.ctrl_bounds` their ``ctrlrange``; commanded by :meth:`Backend.set_ctrl` (held
  until changed), their state read by :meth:`Backend.actuator_state`. Empty by default.

Dynamic interface: :meth:`Backend.reset`, :meth:`Backend.step`, :meth:`Backend.states`,
:meth:`Backend.rest_lengths`, plus :meth:`Backend.nominal_states` and
:meth:`Backend.nominal_rest_lengths` (the standing pose the env perturbs at reset). Two backends
of one robot must return the same nominal pose (the plant's MJCF keyframe ``nominal``) for the
env's reset distribution to be the same on both.

Input checks live in :mod:`tensegrity_gym.checks`, once, for every backend and for the plant itself
(:func:`~tensegrity_gym.checks.check_rest_lengths`, :func:`~tensegrity_gym.checks.check_targets`,
:func:`~tensegrity_gym.checks.check_push`, :func:`~tensegrity_gym.checks.check_substeps`): a backend
calls them at its entry points, so a bad shape or a NaN gives the same message whichever physics is
behind the env.

Divergence: a backend never raises when its physics blows up; it returns non-finite rod states
(NaN) until the next :meth:`Backend.reset`, and the env ends the episode.

Adding a backend (the identified twin): subclass :class:`Backend` in a module of this package and
add ``name: "module:Class"`` to :data:`tensegrity_gym.backends.BACKENDS`; then
``gym.make("TensegrityIco-v0", backend=name, model=...)`` builds it as ``Class(model, **backend_kwargs)``.

Drawing: a backend that is not MuJoCo (the twin) still renders through MuJoCo, by putting its rod
states into a MuJoCo model that is used purely for drawing. It only has to return that model's
MJCF from :meth:`Backend.drawing_model`; :meth:`Backend.render` and :meth:`Backend.show` do the
rest. The MuJoCo backend overrides both to draw its own simulation directly.
"""

from __future__ import annotations

import abc
import os
from typing import TYPE_CHECKING

import numpy as np

from identified.state import RodState
from tensegrity_gym.cables import MotorSpec
from tensegrity_gym.checks import check_substeps

if TYPE_CHECKING:
    from tensegrity_gym.plant import MujocoPlant

__all__ = ["Backend", "MotorSpec", "RodState"]


class Backend(abc.ABC):
    """A spring-rod system seen through cable commands, rod states and rest lengths.

    Subclasses set ``rod_names``, ``tendon_names``, ``actuated_names``, ``motor`` in their
    constructor and implement the abstract methods. Shapes: R rods, S tendons (springs and
    cables), A actuated cables. All arrays are numpy float64; angular velocity is in the world
    frame; quaternions are w-x-y-z.

    A backend is constructed as ``Factory(model, **kwargs)`` where ``model`` is the file it needs
    (an MJCF for MuJoCo, an identified-model JSON for the twin) or ``None`` for its default; see
    :func:`tensegrity_gym.backends.make_backend`.
    """

    #: short name used in ``gym.make(..., backend=name)``
    name: str = "base"
    rod_names: tuple[str, ...]
    tendon_names: tuple[str, ...]
    actuated_names: tuple[str, ...]
    motor: MotorSpec
    actuator_names: tuple[str, ...] = ()
    #: height of the model's ground plane, m (``None``: no ground)
    ground: float | None = None

    # ------------------------------------------------------------------ metadata
    @property
    @abc.abstractmethod
    def dt(self) -> float:
        """One physics step, s."""

    @property
    def n_rods(self) -> int:
        return len(self.rod_names)

    @property
    def actuated_index(self) -> np.ndarray:
        """(A,) int: position of every actuated cable in ``tendon_names``."""
        idx = {n: i for i, n in enumerate(self.tendon_names)}
        return np.array([idx[n] for n in self.actuated_names], dtype=int)

    # ------------------------------------------------------------------ MuJoCo actuators
    def ctrl_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high), each (U,): the actuators' command ranges."""
        return np.zeros(0), np.zeros(0)

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        """Set the (U,) actuator commands, held until changed (cleared by :meth:`reset`)."""
        if np.asarray(ctrl).size:
            raise ValueError(f"the {self.name!r} backend has no actuators")

    def actuator_state(self) -> np.ndarray:
        """(U,) what each actuator's force acts on now: its activation where it has dynamics, else
        its command."""
        return np.zeros(0)

    # ------------------------------------------------------------------ the standing pose
    @abc.abstractmethod
    def nominal_states(self) -> RodState:
        """The settled standing pose (zero velocities) the env starts from, before reset noise."""

    @abc.abstractmethod
    def nominal_rest_lengths(self) -> np.ndarray:
        """(S,) rest lengths at the nominal pose (the neutral cable setting), m."""

    # ------------------------------------------------------------------ dynamics
    @abc.abstractmethod
    def reset(self, states: RodState, rest_lengths: np.ndarray) -> None:
        """Put the system at ``states`` with rest lengths ``rest_lengths`` (S,), time zero.

        Motor targets are set to the actuated rest lengths (the motors hold still), any
        internal solver state (warm starts, applied forces) is cleared: after ``reset`` the
        future depends only on the arguments and the commands that follow.
        """

    @abc.abstractmethod
    def step(self, target_rest: np.ndarray, n_substeps: int, push_force: np.ndarray | None = None,
             push_point: np.ndarray | None = None) -> None:
        """Advance the physics by ``n_substeps`` steps of ``dt`` (one control period).

        Args:
            target_rest: (A,) motor targets, m (clipped into ``[motor.rest_min, motor.rest_max]``);
                the motors move the rest lengths toward them at ``motor.speed`` at every substep.
            n_substeps: number of physics steps, >= 1.
            push_force: optional (R, 3) world-frame force on each rod, N, held for all substeps.
            push_point: optional (R, 3) point of application in each rod's body frame, m.
        """

    def engine_steps(self, n_substeps: int) -> int:
        """Steps of the backend's own integrator for ``n_substeps`` physics steps of ``dt``
        (ValueError, in the user's words, where it cannot take that period): ``n_substeps`` here;
        the identified twin integrates coarser when given ``physics_dt``."""
        return check_substeps(n_substeps)

    @abc.abstractmethod
    def states(self) -> RodState:
        """Current rod states (copies the caller may keep)."""

    @abc.abstractmethod
    def rest_lengths(self) -> np.ndarray:
        """(S,) current actual rest lengths of every tendon, m (copy)."""

    # ------------------------------------------------------------------ drawing
    def drawing_model(self) -> str | os.PathLike | None:
        """MJCF (text or path) of a MuJoCo model with the same rod and site names, used only to
        draw this backend's rod states; ``None``: this backend cannot draw."""
        return None

    _drawing: MujocoPlant | None = None
    _viewer: object | None = None

    def _drawing_plant(self) -> MujocoPlant:
        if self._drawing is None:
            from tensegrity_gym.plant import MujocoPlant

            src = self.drawing_model()
            if src is None:
                raise NotImplementedError(f"the {self.name!r} backend has no drawing model; it cannot render")
            self._drawing = MujocoPlant(src)
            missing = set(self.rod_names) - set(self._drawing.rod_names)
            if missing:
                raise ValueError(f"the drawing model lacks the rods {sorted(missing)}")
        plant = self._drawing
        if plant.rod_names == self.rod_names:
            plant.set_states(self.states())
        else:  # same rods, another order
            s, order = self.states(), [self.rod_names.index(n) for n in plant.rod_names]
            plant.set_states(RodState(s.pos[order], s.quat[order], s.vel[order], s.angvel[order]))
        return plant

    def render(self, width: int = 480, height: int = 480, camera: str | int | None = None) -> np.ndarray:
        """(height, width, 3) uint8 image of the current rod states.

        ``camera=None`` follows the structure (a free camera looking at the mean rod position);
        a name or index selects a camera of the drawing model.
        """
        return self._drawing_plant().render(width=width, height=height, camera=camera)

    def show(self) -> None:
        """Draw the current rod states in an interactive ``mujoco.viewer`` window (opened on first
        call). Raises RuntimeError with a clear message where no display is available."""
        plant = self._drawing_plant()
        self._viewer = _sync_viewer(self._viewer, plant)

    def close(self) -> None:
        """Free renderers and windows."""
        if self._viewer is not None:
            self._viewer.close()  # type: ignore[attr-defined]
            self._viewer = None
        if self._drawing is not None:
            self._drawing.close()
            self._drawing = None


def _sync_viewer(viewer: object | None, plant: MujocoPlant) -> object:
    """Open (once) a passive ``mujoco.viewer`` on the plant's model and data and sync it."""
    if viewer is None:
        import sys

        headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        if sys.platform.startswith("linux") and headless:
            raise RuntimeError("render_mode='human' needs a display (DISPLAY is not set); "
                               "use render_mode='rgb_array' on a headless machine")
        try:
            import mujoco.viewer

            viewer = mujoco.viewer.launch_passive(plant.model, plant.data)
        except Exception as exc:  # noqa: BLE001 - GLFW and the viewer raise assorted types
            raise RuntimeError(f"render_mode='human' could not open mujoco.viewer ({type(exc).__name__}: "
                               f"{exc}); use render_mode='rgb_array'") from None
    viewer.sync()  # type: ignore[attr-defined]
    return viewer
