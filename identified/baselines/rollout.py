"""One evaluation path for every row: free-run a step model on recorded test trajectories.

A *step model* is any callable ``step(state, rest_length, push_force, push_point) -> RodState``
(the identified engine's :meth:`~identified.engine.SpringRodEngine.step`, a neural baseline's
``step``, Koopman+Int's ``step``).  :func:`rollout_errors` starts it from each recorded initial
state, drives it with the recorded rest lengths and pushes, and returns the paper's curves:
position error (m) and quaternion distance against the time step, averaged over episodes and
rods (as :func:`identified.evaluate.rollout_errors` does for the identified model).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from identified.dataset import Dataset
from identified.engine.integration import RodState
from identified.evaluate import quat_distance

__all__ = ["StepModel", "rollout", "rollout_errors"]

StepModel = Callable[[RodState, torch.Tensor, torch.Tensor | None, torch.Tensor | None], RodState]


def rollout(step: StepModel, data: Dataset, horizon: int | None = None, dtype: torch.dtype = torch.float64
            ) -> dict[str, np.ndarray]:
    """States (E, H + 1, R, ·) of the free run as numpy arrays ``pos``, ``quat``; a trajectory that
    diverges (non-finite) stays non-finite from there on."""
    H = data.n_steps if horizon is None else min(int(horizon), data.n_steps)
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)
    s = RodState(t(data.pos[:, 0]), t(data.quat[:, 0]), t(data.vel[:, 0]), t(data.angvel[:, 0]))
    rest, pf, pp = t(data.rest_length), t(data.push_force), t(data.push_point)
    pushes = bool(np.any(data.push_force != 0))
    pos, quat = [s.pos.numpy().copy()], [s.quat.numpy().copy()]
    with torch.no_grad():
        for k in range(H):
            s = step(s, rest[:, k], pf[:, k] if pushes else None, pp[:, k] if pushes else None)
            s = RodState(*(x.to(dtype) for x in s))
            pos.append(s.pos.numpy().copy())
            quat.append(s.quat.numpy().copy())
    return {"pos": np.stack(pos, axis=1), "quat": np.stack(quat, axis=1)}


def rollout_errors(step: StepModel, data: Dataset, horizon: int | None = None) -> dict[str, Any]:
    """Per-step position and quaternion error of the free run, and their mean and final values
    (inf where a trajectory diverged)."""
    out = rollout(step, data, horizon)
    H = out["pos"].shape[1] - 1
    with np.errstate(invalid="ignore", over="ignore"):
        pe = np.linalg.norm(out["pos"] - data.pos[:, : H + 1], axis=-1).mean(axis=(0, 2))
        qe = quat_distance(out["quat"], data.quat[:, : H + 1]).mean(axis=(0, 2))
    pe = np.where(np.isfinite(pe), pe, np.inf)
    qe = np.where(np.isfinite(qe), qe, np.inf)
    return {"horizon": H, "episodes": data.n_episodes, "dt": data.dt,
            "pos_mean": float(np.mean(pe)), "pos_final": float(pe[-1]),
            "quat_mean": float(np.mean(qe)), "quat_final": float(qe[-1]),
            "per_step": {"pos": pe, "quat": qe}}
