"""Prediction with an identified model: the free run's error curves, their plot and the fit's metrics.

The paper's figures plot, against the time step, the error between a free-running identified
model (started from the recorded initial state, driven by the recorded rest lengths and pushes)
and the recorded trajectory.  :func:`rollout_errors` computes those curves
(:mod:`identified.evaluate`, where every error measure lives); :func:`write_error_plot` draws
them; :func:`attach_metrics` stores one-step and free-run errors in the model's ``metrics``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from identified.dataset import Dataset, atomic_write
from identified.evaluate import one_step_state_errors, quat_distance, rollout, rollout_errors
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel

__all__ = ["attach_metrics", "quat_distance", "rollout", "rollout_errors", "write_error_plot"]


def attach_metrics(model: IdentifiedModel, data: Dataset, free_run_steps: int = 1000, free_run_episodes: int = 5) -> None:
    """Store one-step and free-run errors on the fitting data in ``model.metrics`` (None: diverged)."""
    model.metrics["one_step_rms"] = {k: finite_or_none(v) for k, v in one_step_state_errors(model, data).items()}
    sub = data.select(episodes=slice(0, free_run_episodes))
    fr = rollout_errors(model, sub, horizon=free_run_steps)
    model.metrics["free_run"] = {k: fr[k] for k in ("horizon", "episodes")}
    model.metrics["free_run"].update({k: finite_or_none(fr[k]) for k in ("pos_mean", "pos_final", "quat_mean", "quat_final")})


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
