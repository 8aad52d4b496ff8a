"""The residual strategy of the fit: effects fitted on what the joint model leaves
(``fit_strategy = "residual"``: ground contact).

Such a law needs the accelerations under every other force, which only a fitted model gives: the
joint fit (:func:`identified.fit.identify.identify`) leaves out the equations of the rods the effect
touches (:meth:`~identified.effects.base.Effect.rows_affected`), then this second stage fits the
effect's law on the residual wrench of those rows (its own least squares,
:meth:`~identified.effects.base.Effect.fit_residual`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from identified.dataset import Dataset
from identified.effects.base import Effect
from identified.engine.accelerations import inertial_wrench
from identified.engine.integration import RodState
from identified.model import IdentifiedModel
from identified.rotation import matrix_apply
from identified.samples import iter_chunks
from identified.twin import engine_from_model

__all__ = ["fit_residual_effects"]


def fit_residual_effects(model: IdentifiedModel, dataset: Dataset, late: Sequence[Effect], scheme: str = "forward",
                         device: str = "cpu", max_steps: int = 200_000) -> dict[str, Any]:
    """Second stage: fit residual-stage effects (ground contact) on what the joint model leaves.

    The jointly fitted model (its spring-rod parameters and joint effects) gives, at every
    recorded state, the wrench of every other force and the accelerations it alone would cause;
    the rest of the recorded wrench ``M (a - g)``, ``R (I α_b + ω_b × I ω_b)`` is the residual the
    effect's law is fitted to (on the rods it touches).  Appends each fitted effect to
    ``model.effects`` and returns per-effect fit statistics.
    """
    E = dataset.n_episodes
    per = max(1, min(E, max_steps // max(dataset.n_steps, 1)))
    data = dataset.select(episodes=slice(0, per)) if per < E else dataset
    ch, n_ep = next(iter_chunks(data, data.n_episodes * data.n_steps + 1, scheme, device=device))
    groups = np.repeat(np.arange(n_ep), ch.pos.shape[0] // n_ep)
    eng = engine_from_model(model, dtype=torch.float64, device=device)
    state = RodState(ch.pos, ch.quat, ch.vel, ch.angvel)
    push_point = torch.as_tensor(data.push_point[:, : ch.pos.shape[0] // n_ep].reshape(-1, data.n_rods, 3),
                                 dtype=ch.pos.dtype) if scheme == "forward" else None
    with torch.no_grad():
        terms = eng.dynamics(state, ch.rest, ch.push_force, push_point)
        p = eng.params
        need_f, need_tb = inertial_wrench(p.mass, p.inertia, p.gravity, ch.acc, ch.alpha_body, ch.angvel_body)
        need_t = matrix_apply(terms.ctx.rot, need_tb)
        ctx = terms.ctx._replace(base_lin_acc=terms.lin_acc, base_ang_acc_body=terms.ang_acc_body)
        stats = {}
        for e in late:
            rows = e.rows_affected(state, ctx)
            stats[e.name] = e.fit_residual(state, ctx, need_f - terms.force, need_t - terms.torque, groups, rows)
            model.effects.append(e.to_json())
    return stats
