"""The MuJoCo backend: the plant (:class:`~tensegrity_gym.plant.MujocoPlant`) behind the env.

A thin adapter: the plant already speaks rod states, rest lengths and motor targets; this class
adds the control period (``n_substeps`` physics steps per :meth:`MujocoBackend.step`), the
nominal pose the env starts from, and drawing of the live simulation.
"""

from __future__ import annotations

import functools
import os

import mujoco
import numpy as np

from tensegrity_gym.backends.base import Backend, RodState, _sync_viewer
from tensegrity_gym.checks import check_substeps
from tensegrity_gym.plant import MujocoPlant, standing_pose

__all__ = ["MujocoBackend", "default_robot_xml"]

#: MuJoCo warnings after which it has reset its data: the simulation diverged
_BAD = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)


@functools.lru_cache(maxsize=1)
def default_robot_xml() -> str:
    """MJCF text of the ``ico``/``robot`` preset, built once per process (the build settles the
    keyframe ``nominal``, which takes a simulation of a few seconds)."""
    from tensegrity_gym.models import build_model

    return build_model("ico", preset="robot")


class MujocoBackend(Backend):
    """The MuJoCo plant as an env backend.

    Args:
        model: MJCF path or text, or a compiled ``mujoco.MjModel`` (used as is); ``None`` builds
            the ``ico``/``robot`` preset in memory.
        integrator: ``None`` keeps the model's integrator; else ``"euler"``, ``"rk4"``,
            ``"implicit"`` or ``"implicitfast"``.

    The nominal pose is the model's standing pose (:func:`~tensegrity_gym.plant.standing_pose`:
    keyframe ``"nominal"``, else its first keyframe, else the pose it settles in from ``qpos0``)
    with zero velocities, and the MJCF rest lengths. MuJoCo tendon actuators are commanded by
    :meth:`set_ctrl` (``data.ctrl``, zero after :meth:`reset`).

    Divergence: when MuJoCo finds a bad position, velocity or acceleration it warns and silently
    resets its data to ``qpos0``. This backend reports that instead as non-finite rod states (NaN)
    until the next :meth:`reset`, so the env can end the episode rather than see a teleport.
    """

    name = "mujoco"

    def __init__(self, model: str | os.PathLike | mujoco.MjModel | None = None,
                 integrator: str | None = None) -> None:
        self._source = default_robot_xml() if model is None else model
        self.plant = MujocoPlant(self._source, integrator=integrator)
        p = self.plant
        self.rod_names = p.rod_names
        self.tendon_names = p.tendon_names
        self.actuated_names = p.actuated_names
        self.motor = p.motor
        self.actuator_names = p.actuator_names
        self.ground = p.system.ground
        self._ctrl_bounds = p.ctrl_bounds() if p.actuators else (np.zeros(0), np.zeros(0))
        self._nominal, self.nominal_source = standing_pose(p)
        p.reset()  # the keyframe, zero velocities, MJCF rest lengths
        self._nominal_rest = p.rest_lengths()
        self._diverged = False

    @property
    def dt(self) -> float:
        return self.plant.dt

    def nominal_states(self) -> RodState:
        return self._nominal.copy()

    def nominal_rest_lengths(self) -> np.ndarray:
        return self._nominal_rest.copy()

    def ctrl_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._ctrl_bounds[0].copy(), self._ctrl_bounds[1].copy()

    def set_ctrl(self, ctrl: np.ndarray) -> None:
        self.plant.set_ctrl(ctrl)

    def actuator_state(self) -> np.ndarray:
        return self.plant.actuator_state()

    def reset(self, states: RodState, rest_lengths: np.ndarray) -> None:
        # MujocoPlant.reset restores the keyframe (mj_resetDataKeyframe clears time, warm start
        # and applied forces), writes the rest lengths and motor targets, then sets the states.
        self.plant.reset(states, rest_lengths)
        self._diverged = False

    def step(self, target_rest: np.ndarray, n_substeps: int, push_force: np.ndarray | None = None,
             push_point: np.ndarray | None = None) -> None:
        n_substeps = check_substeps(n_substeps)
        plant = self.plant
        plant.set_targets(target_rest)
        if self._diverged:
            return
        warnings = plant.data.warning
        before = sum(warnings[w].number for w in _BAD)
        for _ in range(int(n_substeps)):
            plant.step(push_force, push_point)
        if sum(warnings[w].number for w in _BAD) != before:
            self._diverged = True

    def states(self) -> RodState:
        if self._diverged:
            nan = np.full((self.n_rods, 3), np.nan)
            return RodState(nan.copy(), np.full((self.n_rods, 4), np.nan), nan.copy(), nan.copy())
        return self.plant.states()

    def rest_lengths(self) -> np.ndarray:
        return self.plant.rest_lengths()

    # ------------------------------------------------------------------ drawing: the live simulation
    def drawing_model(self) -> str | os.PathLike | None:
        return None if isinstance(self._source, mujoco.MjModel) else self._source

    def render(self, width: int = 480, height: int = 480, camera: str | int | None = None) -> np.ndarray:
        return self.plant.render(width=width, height=height, camera=camera)

    def show(self) -> None:
        self._viewer = _sync_viewer(self._viewer, self.plant)

    def close(self) -> None:
        super().close()
        self.plant.close()
