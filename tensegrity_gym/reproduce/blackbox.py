"""The black-box side of the simple-system experiment: a MuJoCo simulator of the parameters, and
MuJoCo's own system-identification module as a solver.

:class:`TrajectorySimulator` is what LS, CMA-ES and ``mujoco.sysid`` search through: it runs the
plant's MJCF with candidate parameters (K, c of both springs, M of the rod, the inertia following
the mass as ``I = M · I_true / M_true``: "we assume inertia I is inferred from the rod geometry",
paper Sec. "Simple Spring-Rod System Identification") from the reference trajectory's initial
state and returns its error against the reference ("they resample a new trajectory from the
simulator after each optimization iteration").  Each rollout is one ``mujoco.rollout`` call.

:class:`MujocoSysId` adapts ``mujoco.sysid`` (MuJoCo >= 4, the ``mujoco[sysid]`` extra) to the
:class:`~identified.baselines.base.ParameterSolver` interface: its ``optimize`` (MuJoCo's bounded
Gauss-Newton/Levenberg-Marquardt, ``mujoco.minimize.least_squares``, finite-difference Jacobian)
on the same trajectory residual.
"""

from __future__ import annotations

import contextlib
import io
import time

import mujoco
import numpy as np

from identified.baselines.base import Estimate, ParameterProblem
from identified.dataset import Dataset
from tensegrity_gym.plant import MujocoPlant, RodState

__all__ = ["MujocoSysId", "TrajectorySimulator", "sysid_available"]


class TrajectorySimulator:
    """MuJoCo rollouts of the plant with candidate ``(K, c[, M])`` from one reference episode.

    ``names``: the estimated parameters, a subset of ``("K", "c", "M")``; ``known``: the others
    (e.g. ``{"M": 10.0}``).  ``objective(theta)``: mean over steps of the squared position error
    (m², summed over rods) plus the squared quaternion distance; ``residual(theta)``: the vector
    whose squared sum is the objective.
    """

    def __init__(self, xml_path: str, reference: Dataset, names: tuple[str, ...], known: dict[str, float]) -> None:
        if reference.n_episodes != 1:
            raise ValueError("the reference must be one episode")
        self.plant = MujocoPlant(xml_path)
        self.names, self.known = names, dict(known)
        m = self.plant.model
        self.bid = self.plant._bid
        self.inertia_per_mass = m.body_inertia[self.bid] / m.body_mass[self.bid][:, None]
        self.ref_pos = reference.pos[0, 1:]
        self.ref_quat = reference.quat[0, 1:]
        self.nstep = reference.n_steps
        self.plant.set_states(RodState(reference.pos[0, 0], reference.quat[0, 0], reference.vel[0, 0],
                                        reference.angvel[0, 0]))
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.state0 = np.empty(mujoco.mj_stateSize(m, spec))
        mujoco.mj_getState(m, self.plant.data, self.state0, spec)
        self.qadr = self.plant._qadr  # (R, 7) qpos addresses of each rod
        self._data = mujoco.MjData(m)
        self.calls = 0

    def _apply(self, theta: np.ndarray) -> None:
        v = dict(self.known)
        v.update(zip(self.names, np.asarray(theta, dtype=float)))
        m = self.plant.model
        m.tendon_stiffness[:] = v["K"]
        m.tendon_damping[:] = v["c"]
        m.body_mass[self.bid] = v["M"]
        m.body_inertia[self.bid] = v["M"] * self.inertia_per_mass

    def simulate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (T, R, 3) and quaternions (T, R, 4) after each of the reference's T steps."""
        from mujoco import rollout

        self.calls += 1
        self._apply(theta)
        state, _ = rollout.rollout(self.plant.model, self._data, self.state0[None], nstep=self.nstep)
        qpos = state[0, :, 1:1 + self.plant.model.nq]
        return qpos[:, self.qadr[:, :3]], qpos[:, self.qadr[:, 3:]]

    def residual(self, theta: np.ndarray) -> np.ndarray:
        pos, quat = self.simulate(theta)
        dq = quat - self.ref_quat
        flip = np.sum(quat * self.ref_quat, axis=-1, keepdims=True) < 0  # q and -q are one rotation
        dq = np.where(flip, quat + self.ref_quat, dq)
        r = np.concatenate([(pos - self.ref_pos).reshape(-1), dq.reshape(-1)])
        r = r / np.sqrt(self.nstep)
        return np.where(np.isfinite(r), r, 1e3)  # a diverged run: a large, finite residual

    def objective(self, theta: np.ndarray) -> float:
        return float(np.sum(self.residual(theta) ** 2))


def sysid_available() -> tuple[bool, str]:
    """Whether ``mujoco.sysid`` can be used here, and why not."""
    try:
        from mujoco import sysid
    except ImportError as exc:  # pragma: no cover - depends on the installed mujoco
        return False, f"mujoco {mujoco.__version__} has no sysid module ({exc})"
    if not hasattr(sysid, "optimize"):
        return False, (f"mujoco {mujoco.__version__} ships mujoco.sysid but its optional dependencies are "
                       "missing (pip install 'mujoco[sysid]')")
    return True, f"mujoco {mujoco.__version__} mujoco.sysid.optimize"


class MujocoSysId:
    """``mujoco.sysid.optimize`` (optimizer ``"mujoco"``: bounded Levenberg-Marquardt with a
    finite-difference Jacobian) on the problem's trajectory residual, at most ``max_iter``
    iterations."""

    name = "mujoco.sysid"

    def __init__(self, max_iter: int = 100, optimizer: str = "mujoco") -> None:
        self.max_iter, self.optimizer = max_iter, optimizer

    def estimate(self, problem: ParameterProblem) -> Estimate:
        from absl import logging as absl_logging
        from mujoco import sysid

        if problem.residual is None:
            raise ValueError("mujoco.sysid needs a residual function; the problem has none")
        calls = [0]

        n = len(problem.names)

        def residual_fn(x, params):
            # vectorised as mujoco.minimize wants: x (n,) or (n, k) -> residuals (m,) or (m, k)
            x = np.asarray(x, dtype=float)
            cols = x.reshape(n, -1)
            calls[0] += cols.shape[1]
            r = np.stack([np.asarray(problem.residual(cols[:, k])) for k in range(cols.shape[1])], axis=-1)
            return [r if x.ndim == 2 else r[:, 0]], None, None

        params = sysid.ParameterDict({n: sysid.Parameter(n, float(x), float(lo), float(hi))
                                      for n, x, (lo, hi) in zip(problem.names, problem.x0, problem.bounds)})
        old = absl_logging.get_verbosity()
        absl_logging.set_verbosity(absl_logging.ERROR)  # its "starts at a bound" warning: x0 = 1 is the paper's
        t0 = time.perf_counter()
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # its per-iteration table
                opt, res = sysid.optimize(params, residual_fn, optimizer=self.optimizer, verbose=False,
                                          max_iters=self.max_iter)
        finally:
            absl_logging.set_verbosity(old)
        sec = time.perf_counter() - t0
        x = np.asarray(opt.as_vector(), dtype=float)
        cands = res.get("extras", {}).get("candidate", [])
        trace = np.array([np.asarray(c, dtype=float).reshape(-1) for c in cands]).reshape(-1, x.size)
        iters = max(len(cands), 1)
        return Estimate(dict(zip(problem.names, x.tolist())), iters, calls[0], sec, trace,
                        info={"optimizer": self.optimizer, "max_iter": self.max_iter,
                              "objective": float(np.sum(problem.residual(x) ** 2))})
