"""Prediction with an identified model: free-run rollouts, error curves and fit metrics.

The paper's figures plot, against the time step, the error between a free-running identified
model (started from the recorded initial state, driven by the recorded rest lengths and pushes)
and the recorded trajectory.  :func:`rollout_errors` computes those curves;
:func:`write_error_plot` draws them; :func:`attach_metrics` stores one-step and free-run errors
in the model's ``metrics``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from identified.dataset import Dataset, atomic_write
from identified.engine.integration import RodState
from identified.model import IdentifiedModel
from identified.twin import engine_from_model

__all__ = ["attach_metrics", "one_step_errors", "quat_distance", "rollout", "rollout_errors", "write_error_plot"]


def quat_distance(q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Sign-invariant quaternion distance ``min(|q - q_ref|, |q + q_ref|)`` over the last axis."""
    return np.minimum(np.linalg.norm(q - q_ref, axis=-1), np.linalg.norm(q + q_ref, axis=-1))


def rollout(model: IdentifiedModel, data: Dataset, horizon: int | None = None,
            episodes: slice | list[int] = slice(None), effects=()) -> RodState:
    """Free-run the model from each recorded initial state: states (E, H + 1, R, .) as numpy-able tensors."""
    H = data.n_steps if horizon is None else min(int(horizon), data.n_steps)
    if H < 1:
        raise ValueError(f"horizon must be >= 1 step, got {horizon}")
    if data.rod_names != model.topology.rod_names or data.tendon_names != model.topology.spring_names:
        raise ValueError("the dataset's rods/tendons do not match the identified model's")
    eng = engine_from_model(model, effects=effects)
    ep = episodes
    s0 = eng.state(data.pos[ep, 0], data.quat[ep, 0], data.vel[ep, 0], data.angvel[ep, 0])
    with torch.no_grad():
        return eng.rollout(s0, data.rest_length[ep, :H], data.push_force[ep, :H], data.push_point[ep, :H])


def rollout_errors(model: IdentifiedModel, data: Dataset, horizon: int | None = None, effects=()) -> dict[str, Any]:
    """Position (m) and quaternion error per step of the free run, averaged over episodes and rods."""
    states = rollout(model, data, horizon, effects=effects)
    H = states.pos.shape[1] - 1
    pos = states.pos.numpy()
    quat = states.quat.numpy()
    pe = np.linalg.norm(pos - data.pos[:, : H + 1], axis=-1).mean(axis=(0, 2))
    qe = quat_distance(quat, data.quat[:, : H + 1]).mean(axis=(0, 2))
    finite = np.isfinite(pe) & np.isfinite(qe)
    return {
        "horizon": H,
        "episodes": data.n_episodes,
        "dt": data.dt,
        "pos_mean": float(np.mean(pe)) if finite.all() else float("inf"),
        "pos_final": float(pe[-1]) if finite.all() else float("inf"),
        "quat_mean": float(np.mean(qe)) if finite.all() else float("inf"),
        "quat_final": float(qe[-1]) if finite.all() else float("inf"),
        "per_step": {"pos": pe, "quat": qe},
    }


def one_step_errors(model: IdentifiedModel, data: Dataset, max_steps: int = 20000, effects=()) -> dict[str, float]:
    """RMS error of one engine step from every recorded state (up to ``max_steps`` steps)."""
    eng = engine_from_model(model, effects=effects)
    T = min(data.n_steps, max(1, max_steps // max(data.n_episodes, 1)))
    sl = (slice(None), slice(0, T))
    flat = lambda a: a[sl].reshape(-1, *a.shape[2:])
    s = eng.state(flat(data.pos), flat(data.quat), flat(data.vel), flat(data.angvel))
    nxt = (slice(None), slice(1, T + 1))
    with torch.no_grad():
        out = eng.step(s, flat(data.rest_length), flat(data.push_force), flat(data.push_point))
    tgt = {k: getattr(data, k)[nxt].reshape(-1, *getattr(data, k).shape[2:]) for k in ("pos", "quat", "vel", "angvel")}
    res = {}
    for k in ("pos", "vel", "angvel"):
        res[k] = float(np.sqrt(np.mean(np.sum((getattr(out, k).numpy() - tgt[k]) ** 2, axis=-1))))
    res["quat"] = float(np.sqrt(np.mean(quat_distance(out.quat.numpy(), tgt["quat"]) ** 2)))
    return res


def attach_metrics(model: IdentifiedModel, data: Dataset, free_run_steps: int = 1000, free_run_episodes: int = 5) -> None:
    """Store one-step and free-run errors on the fitting data in ``model.metrics`` (None: diverged)."""
    finite = lambda x: float(x) if np.isfinite(x) else None
    model.metrics["one_step_rms"] = {k: finite(v) for k, v in one_step_errors(model, data).items()}
    sub = data.select(episodes=slice(0, free_run_episodes))
    fr = rollout_errors(model, sub, horizon=free_run_steps)
    model.metrics["free_run"] = {k: fr[k] for k in ("horizon", "episodes")}
    model.metrics["free_run"].update({k: finite(fr[k]) for k in ("pos_mean", "pos_final", "quat_mean", "quat_final")})


def write_error_plot(path: str | os.PathLike, errs: dict[str, Any], title: str = "identified model, free run") -> None:
    """PNG of position and quaternion error against the time step (the paper's figures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.arange(errs["horizon"] + 1)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    for ax, key, label in ((axes[0], "pos", "position error (m)"), (axes[1], "quat", "quaternion error")):
        y = np.maximum(errs["per_step"][key], 1e-18)
        ax.semilogy(steps, y)
        ax.set_xlabel("time step")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"{title} ({errs['episodes']} episodes, dt = {errs['dt'] * 1e3:g} ms)")
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110), binary=True)
    plt.close(fig)
