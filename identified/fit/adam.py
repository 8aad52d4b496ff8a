"""The paper's training of the linear regression: a single linear layer, Adam, 30 epochs.

Paper, "Integration Module and Method Implementation": the regression is a single-layer network
without activation, trained for 30 epochs with Adam, learning rate 0.1 halved every 3 epochs,
parameters initialised to 1.  Here the layer acts on the same equations as the closed-form solve,
under the same scale anchor; its weights are the logarithms of the physical parameters (so that
a step of 0.1 moves K = 1 toward K = 100 in tens of steps rather than thousands, and every
parameter stays positive), mini-batches of 32 steps; the parameters that may be negative are
projected out.  This solver exists to compare against the
closed form (accuracy and time, ``benchmarks/bench_fit.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch

from identified.fit.features import RodColumns
from identified.fit.layout import ParameterLayout
from identified.fit.regression import Anchor, Solution

__all__ = ["adam_solve"]


def adam_solve(
    rows: Callable[[], Iterable[torch.Tensor]],
    columns: RodColumns,
    layout: ParameterLayout,
    anchor: Anchor,
    fixed: dict[int, float],
    epochs: int = 30,
    lr: float = 0.1,
    batch_steps: int = 32,
    seed: int = 0,
    cache_bytes: float = 2e9,
) -> Solution:
    """Minimise the mean squared equation error with Adam; ``rows()`` yields compact (N, R, 6, L) chunks.

    The layer's weights are the logarithms of the free parameters that are physical magnitudes
    (every K, c, M, I and h is positive), initialised at 0, i.e. every parameter at 1 as in the
    paper.  The parameters that may be negative (:attr:`ParameterLayout.signed`: the preloads
    ``P = K (l0 - l_ref)``, an actuator's bias, effects' signed parameters) enter the equations
    linearly and are projected out (variable projection, Golub & Pereyra 1973): on each mini-batch
    they are the least-squares solution given the weights, and at the end the one on all rows.
    The anchor is imposed by rescaling (the equations are homogeneous, so the loss only sees ratios).
    """
    G = torch.as_tensor(layout.tie)
    fix_idx = torch.as_tensor(sorted(fixed), dtype=torch.long)
    fix_val = torch.as_tensor([fixed[i] for i in sorted(fixed)], dtype=torch.float64)
    held = np.zeros(layout.n_full, dtype=bool)
    held[sorted(fixed)] = True
    signed = (layout.tie.T @ layout.signed) > 0  # per free parameter
    free_held = (layout.tie.T @ held) > 0
    sig = np.flatnonzero(signed & ~free_held)  # projected out
    pos = torch.as_tensor(~signed)
    Sx = torch.zeros(layout.n_full + 1, len(sig), dtype=torch.float64)  # x -> full (padding row 0)
    Sx[: layout.n_full] = G[:, torch.as_tensor(sig, dtype=torch.long)] * torch.as_tensor(~held)[:, None]
    a = torch.as_tensor(anchor.coeff)
    if np.any(anchor.coeff[layout.tie[:, sig].any(axis=1)] != 0):
        raise ValueError("the Adam solver's anchor must be on positive parameters (a mass, the push scale)")
    u = torch.nn.Parameter(torch.zeros(G.shape[1], dtype=torch.float64))
    opt = torch.optim.Adam([u], lr=lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=3, gamma=0.5)
    gen = torch.Generator().manual_seed(seed)
    gather = torch.as_tensor(np.where(columns.full >= 0, columns.full, layout.n_full))  # padding -> a zero
    local_x = Sx[gather]  # (R, L, X)

    def theta_pos() -> torch.Tensor:
        """The full vector with the projected parameters at 0: positive weights, anchor, fixed values."""
        theta = G @ torch.where(pos, torch.exp(u), 0.0)
        theta = theta * (anchor.value / (a @ theta))
        if len(fix_idx):
            theta = theta.index_put((fix_idx,), fix_val)
        return theta

    def local(theta: torch.Tensor) -> torch.Tensor:
        return torch.cat([theta, theta.new_zeros(1)])[gather]  # (R, L)

    def normal(A: torch.Tensor, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The normal equations ``BᵀB``, ``Bᵀb`` of x on ``A`` (``b``: the residual at x = 0)."""
        b = torch.einsum("nrkl,rl->nrk", A, local(theta))
        B = torch.einsum("nrkl,rlx->nrkx", A, local_x).reshape(-1, len(sig))
        return B.T @ B, B.T @ b.reshape(-1)

    def project(BtB: torch.Tensor, Btb: torch.Tensor) -> torch.Tensor:
        ridge = 1e-12 * BtB.diagonal().sum() / max(len(sig), 1) + 1e-300
        return torch.linalg.solve(BtB + ridge * torch.eye(len(sig), dtype=BtB.dtype), -Btb)

    row_scale: torch.Tensor | None = None
    total_rows = 0
    cache: list[torch.Tensor] | None = []  # keep the rows after the first epoch while they fit
    for epoch in range(epochs):
        source = rows() if not cache or epoch == 0 else cache
        for A in source:
            if epoch == 0 and cache is not None:
                cache.append(A)
                if sum(x.numel() for x in cache) * A.element_size() > cache_bytes:
                    cache = None
            if row_scale is None:  # equilibrate force and torque rows once, from the first chunk
                row_scale = 1.0 / A.norm(dim=-1).square().mean(dim=(0, 1)).sqrt().clamp_min(1e-300)
            A = A * row_scale[:, None]  # (6,) -> broadcast over (N, R, 6, L)
            perm = torch.randperm(A.shape[0], generator=gen)
            for start in range(0, A.shape[0], batch_steps):
                batch = A[perm[start : start + batch_steps]]
                theta = theta_pos()
                if len(sig):
                    BtB, Btb = normal(batch, theta)
                    x = project(BtB, Btb)
                    theta = theta + Sx[: layout.n_full] @ x
                loss = torch.einsum("nrkl,rl->nrk", batch, local(theta)).square().mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            if epoch == 0:
                total_rows += A.shape[0] * A.shape[1] * A.shape[2]
        sched.step()
    with torch.no_grad():
        theta = theta_pos()
        if len(sig):  # the projected parameters on all rows
            BtB = torch.zeros(len(sig), len(sig), dtype=torch.float64)
            Btb = torch.zeros(len(sig), dtype=torch.float64)
            for A in cache if cache else rows():
                gtg, gtb = normal(A * row_scale[:, None], theta)
                BtB, Btb = BtB + gtg, Btb + gtb
            theta = theta + Sx[: layout.n_full] @ project(BtB, Btb)
        theta = theta.numpy()
    return Solution(theta=theta, cov=None, residual_rms=[float("nan")] * (2 * layout.n_rods),
                    condition=float("nan"), rows=total_rows, free=G.shape[1])
