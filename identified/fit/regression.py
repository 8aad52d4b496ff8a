"""Closed-form least squares on the regression features, with a scale anchor and error bars.

The equations of :mod:`identified.fit.features` are homogeneous: from rod states alone only the
ratios (K/M, c/M, I/M, h/M) follow.  One linear *anchor* ``a . theta = d`` fixes the scale: a
known rod mass, a known total mass, pushes of known magnitude (``h = 1``) or, failing all of
these, a normalisation (mean rod mass 1) that the identified model reports as such.

The data are reduced block by block (translation / rotation rows of each rod) to triangular
factors ``R_b`` with ``||A_b theta||^2 = ||R_b theta||^2`` by a streaming QR (TSQR), so the fit
never holds the whole design matrix and keeps the accuracy of an orthogonal solve (no normal
equations: least squares on exactly matching features recovers the parameters to ~1e-13).
The blocks are then weighted by their residual scale (feasible generalised least squares) and
the anchored problem is solved in the anchor's null space.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import torch

from identified.fit.features import RodColumns
from identified.fit.layout import ParameterLayout

__all__ = ["Anchor", "BlockFactors", "IdentifiabilityError", "Solution", "accumulate", "solve"]

EPS = np.finfo(np.float64).eps


class IdentifiabilityError(ValueError):
    """The data cannot identify some parameters (rank-deficient regression)."""


@dataclass
class BlockFactors:
    """Triangular factors of each equation block, in the full parameter space."""

    R: list[np.ndarray]  # (n_full, n_full) each
    rows: list[int]


@dataclass(frozen=True)
class Anchor:
    """A linear constraint ``coeff . theta_full = value`` that fixes the global scale."""

    coeff: np.ndarray
    value: float
    description: str


@dataclass
class Solution:
    """Least-squares estimate in the full parameter space, with covariance and diagnostics."""

    theta: np.ndarray  # (n_full,)
    cov: np.ndarray | None  # (n_full, n_full); None when the solver gives no covariance
    residual_rms: list[float]  # per block, RMS equation error
    condition: float  # of the (column-scaled) anchored problem
    rows: int
    free: int


def accumulate(
    chunks: Iterable[torch.Tensor],
    columns: RodColumns,
    n_full: int,
) -> BlockFactors:
    """Stream chunks of compact equation rows (N, R, 6, 2D + 5) into per-block triangular factors.

    Blocks are ``[translation rod0, rotation rod0, translation rod1, ...]``.
    """
    R = columns.full.shape[0]
    local = [columns.block_columns(i, rotation=bool(k)) for i in range(R) for k in range(2)]
    sub = [np.zeros((0, len(c))) for c in local]
    rows = [0] * len(local)
    for A in chunks:
        An = A.detach().cpu().numpy()
        for b, cols in enumerate(local):
            i, k = divmod(b, 2)
            blk = np.take(An[:, i, 3 * k : 3 * k + 3], cols, axis=-1).reshape(-1, len(cols))
            # Householder: each block is (nearly) rank-deficient by one on clean data -- its rows
            # are satisfied exactly by the true parameters -- so Gram/Cholesky shortcuts fail here
            r = np.linalg.qr(np.concatenate([sub[b], blk]), mode="r")
            sub[b] = _square(r, len(cols))
            rows[b] += blk.shape[0]
    full = []
    for b, cols in enumerate(local):
        i = b // 2
        F = np.zeros((n_full, n_full))
        F[np.ix_(np.arange(len(cols)), columns.full[i, cols])] = sub[b]
        full.append(F)
    return BlockFactors(R=full, rows=rows)


def solve(
    factors: BlockFactors,
    layout: ParameterLayout,
    anchor: Anchor,
    fixed: dict[int, float] | None = None,
    reweight: bool = True,
) -> Solution:
    """Anchored least squares ``min sum_b w_b^2 ||R_b G phi||^2`` s.t. the anchor and fixed values.

    ``fixed`` pins full-vector entries (e.g. ``h = 1`` when there are no pushes, which leaves it
    out of the data).  Raises :class:`IdentifiabilityError` naming the parameters that the data
    cannot determine.
    """
    G = layout.tie
    cons_rows = [anchor.coeff @ G]
    cons_vals = [anchor.value]
    for idx, val in (fixed or {}).items():
        e = np.zeros(layout.n_full)
        e[idx] = 1.0
        cons_rows.append(e @ G)
        cons_vals.append(val)
    C = np.array(cons_rows)
    d = np.array(cons_vals)
    # drop duplicate constraints (single regressors tie many entries to one column)
    C, keep = _independent_rows(C)
    d = d[keep]
    phi_p = np.linalg.lstsq(C, d, rcond=None)[0]
    Nul = sla.null_space(C)
    n_free = Nul.shape[1]

    Rg = [R @ G for R in factors.R]
    # initial weights equilibrate the units of force and torque rows
    w = np.array([1.0 / max(np.linalg.norm(r) / np.sqrt(max(m, 1)), 1e-300) for r, m in zip(Rg, factors.rows)])
    for it in range(2 if reweight else 1):
        B = np.vstack([wb * r for wb, r in zip(w, Rg)])
        BN = B @ Nul
        scale = np.linalg.norm(BN, axis=0)
        scale[scale == 0] = 1.0
        U, s, Vt = np.linalg.svd(BN / scale, full_matrices=False)
        tol = s[0] * max(BN.shape) * EPS * 10 if s.size else 0.0
        bad = s <= tol
        if bad.any():
            names: list[str] = []
            for v in Vt[bad]:
                direction = Nul @ (v / scale)
                for n in layout.describe_free(direction):
                    if n not in names:
                        names.append(n)
            raise IdentifiabilityError(
                "the data cannot identify " + ", ".join(names[:12]) + (" ..." if len(names) > 12 else "")
                + " (rank-deficient regression: excite these with more varied motion, pushes or longer runs)"
            )
        rhs = -(B @ phi_p)
        z = (Vt.T @ ((U.T @ rhs) / s)) / scale
        phi = phi_p + Nul @ z
        rms = [float(np.linalg.norm(r @ phi) / np.sqrt(max(m, 1))) for r, m in zip(Rg, factors.rows)]
        if reweight:
            floor = [EPS * np.linalg.norm(r) * np.linalg.norm(phi) / np.sqrt(max(m, 1)) for r, m in zip(Rg, factors.rows)]
            w = np.array([1.0 / max(x, f, 1e-300) for x, f in zip(rms, floor)])
    m_rows = int(sum(factors.rows))
    dof = max(m_rows - n_free, 1)
    resid = float(sum((wb * np.linalg.norm(r @ phi)) ** 2 for wb, r in zip(w, Rg)))
    sigma2 = resid / dof
    Vs = Vt.T / s  # (BN/scale)^+ = V S^-1 U^T  -> cov_z = sigma2 * D^-1 V S^-2 V^T D^-1
    cov_z = sigma2 * (Vs @ Vs.T) / np.outer(scale, scale)
    cov_phi = Nul @ cov_z @ Nul.T
    return Solution(
        theta=G @ phi,
        cov=G @ cov_phi @ G.T,
        residual_rms=rms,
        condition=float(s[0] / s[-1]) if s.size else 1.0,
        rows=m_rows,
        free=n_free,
    )


def _square(r: np.ndarray, n: int) -> np.ndarray:
    """Pad a QR ``R`` factor with fewer rows than columns to (n, n)."""
    if r.shape[0] == n:
        return r
    out = np.zeros((n, n))
    out[: r.shape[0]] = r
    return out


def _independent_rows(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep: list[int] = []
    for i in range(C.shape[0]):
        trial = C[keep + [i]]
        if np.linalg.matrix_rank(trial) == len(keep) + 1:
            keep.append(i)
    return C[keep], np.array(keep, dtype=int)
