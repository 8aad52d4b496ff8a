"""The paper's training of the linear regression: a single linear layer, Adam, 30 epochs.

Paper, "Integration Module and Method Implementation": the regression is a single-layer network
without activation, trained for 30 epochs with Adam, learning rate 0.1 halved every 3 epochs,
parameters initialised to 1.  Here the layer acts on the same equations as the closed-form solve,
under the same scale anchor; its weights are the logarithms of the physical parameters (so that
a step of 0.1 moves K = 1 toward K = 100 in tens of steps rather than thousands, and every
parameter stays positive), mini-batches of 32 steps.  This solver exists to compare against the
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

    The layer's weights are the logarithms of the free parameters (every K, c, M, I and h is
    positive), initialised at 0, i.e. every parameter at 1 as in the paper.  The anchor is
    imposed by rescaling (the equations are homogeneous, so the loss only sees ratios).
    """
    G = torch.as_tensor(layout.tie)
    a = torch.as_tensor(anchor.coeff)
    fix_idx = torch.as_tensor(sorted(fixed), dtype=torch.long)
    fix_val = torch.as_tensor([fixed[i] for i in sorted(fixed)], dtype=torch.float64)
    u = torch.nn.Parameter(torch.zeros(G.shape[1], dtype=torch.float64))
    opt = torch.optim.Adam([u], lr=lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=3, gamma=0.5)
    gen = torch.Generator().manual_seed(seed)
    gather = torch.as_tensor(np.where(columns.full >= 0, columns.full, layout.n_full))  # padding -> a zero

    def theta_full() -> torch.Tensor:
        theta = G @ torch.exp(u)
        theta = theta * (anchor.value / (a @ theta))
        if len(fix_idx):
            theta = theta.index_put((fix_idx,), fix_val)
        return theta

    def local(theta: torch.Tensor) -> torch.Tensor:
        return torch.cat([theta, theta.new_zeros(1)])[gather]  # (R, L)

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
                loss = torch.einsum("nrkl,rl->nrk", batch, local(theta_full())).square().mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            if epoch == 0:
                total_rows += A.shape[0] * A.shape[1] * A.shape[2]
        sched.step()
    with torch.no_grad():
        theta = theta_full().numpy()
    return Solution(theta=theta, cov=None, residual_rms=[float("nan")] * (2 * layout.n_rods),
                    condition=float("nan"), rows=total_rows, free=G.shape[1])
