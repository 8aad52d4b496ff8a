"""Closed-form least squares on the regression features, with a scale anchor and error bars.

The equations of :mod:`identified.fit.features` are homogeneous: from rod states alone only the
ratios (K/M, c/M, I/M, h/M) follow.  One linear *anchor* ``a . theta = d`` fixes the scale: a
known rod mass, a known total mass, pushes of known magnitude (``h = 1``) or, failing all of
these, a normalisation (mean rod mass 1) that the identified model reports as such.

The data are reduced block by block -- one block per rod and equation: translation along world
x, y, z, rotation about the rod's x, y, z -- to triangular factors ``R_b`` with
``||A_b theta||^2 = ||R_b theta||^2`` by a streaming QR (TSQR), so the fit never holds the whole
design matrix and keeps the accuracy of an orthogonal solve (no normal equations: least squares on
exactly matching features recovers the parameters to ~1e-13).  Every independent run of rows
(an episode, :func:`accumulate`; with fewer than ten, consecutive blocks of each) keeps its own
factors too, for the error bars (:mod:`identified.fit.uncertainty`).

Weighting (feasible generalised least squares): without a noise model, the three translation and
the three rotation equations of a rod share one weight, the inverse of their residual scale.
When the dataset records its sensor noise, the noise Gram ``C_b = E[ΔA_bᵀ ΔA_b]`` of every block
is measured (:mod:`identified.fit.noise`) and the fit maximises the profile likelihood of Gaussian
residuals whose variance per row the noise model predicts, ``thetaᵀ C_b theta / m_b``, up to one
free factor per block:

    min  sum_b m_b log(thetaᵀ G_b theta / thetaᵀ C_b theta)     (G_b = R_bᵀ R_b, m_b rows)

-- the approximate maximum-likelihood cost of errors-in-variables fitting, ``sum thetaᵀG theta /
thetaᵀC theta`` (Chojnacki, Brooks, van den Hengel and Gawley 2000, IEEE TPAMI 22: 1294), with
each block's noise level left free.  Its stationarity condition ``sum_b (a_b G_b - c_b C_b) theta
= 0``, ``a_b = m_b / thetaᵀG_b theta``, ``c_b = m_b / thetaᵀC_b theta``, is weighted least squares
with the errors-in-variables bias ``E[G_b] - G_b,clean = C_b`` subtracted (scaled by the fitted
noise factor); it is solved by fixed-point iteration.  Every equation gets its own weight: the
axial rotation row, free of spring torques, is far less noisy than the transverse ones, and with
the pushes' torque about the axis it fixes the axial inertia.  An equation whose rows are noise
only has ``G_b ~ C_b``: its ratio is ~1 whatever the parameters and it pulls on none of them,
where weighted least squares would shrink the parameters it multiplies towards zero.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import torch

from identified.fit.features import RodColumns
from identified.fit.layout import ParameterLayout
from identified.fit.uncertainty import BlockFactors, LinearSolve, block_slices, covariance

__all__ = ["Anchor", "BlockFactors", "IdentifiabilityError", "Solution", "accumulate", "free_parameters", "solve"]

EPS = np.finfo(np.float64).eps
EQUATIONS = 6  # per rod: translation x, y, z (world), rotation x, y, z (rod frame)
EIV_ITERATIONS = 50
EIV_TOL = 1e-10


class IdentifiabilityError(ValueError):
    """The data cannot identify some parameters (rank-deficient regression); ``names``: all of them."""

    def __init__(self, message: str, names: list[str] | None = None) -> None:
        super().__init__(message)
        self.names = list(names or [])


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
    residual_rms: list[float]  # per rod: translation, rotation RMS equation error
    condition: float  # of the (column-scaled) anchored problem
    rows: int
    free: int
    covariance: str = ""  # how ``cov`` was estimated (uncertainty.covariance)
    errors_in_variables: bool = False  # the noise model's bias correction was applied


def accumulate(
    chunks: Iterable[torch.Tensor | tuple],
    columns: RodColumns,
    n_full: int,
    blocks: int = 1,
    clusters: str = "",
) -> BlockFactors:
    """Reduce chunks of compact equation rows (N, R, 6, 2D + 5) to per-block triangular factors.

    A chunk is ``A``, ``(A, n_runs)`` or ``(A, n_runs, replicates)``: its N rows are ``n_runs``
    equal, consecutive runs independent of each other (episodes; a bare ``A`` is one run), and
    ``replicates`` the same rows computed from the data with fresh sensor noise
    (:func:`identified.fit.noise.with_noise_replicates`), whose differences to ``A`` measure the
    noise Gram.  ``blocks`` > 1 cuts every run into that many consecutive blocks of its rows
    (:func:`identified.fit.uncertainty.block_slices`: rows in time order, so stretches of time),
    each kept as a run of its own for the error bars (``clusters`` says so in the covariance's
    description); the merged factors, hence the estimate, are the same whatever the cut (to rounding).
    """
    n_rods = columns.full.shape[0]
    per_run = blocks
    blocks = [(i, k) for i in range(n_rods) for k in range(EQUATIONS)]
    local = [columns.block_columns(i, rotation=k >= 3) for i, k in blocks]
    cluster_R: list[list[np.ndarray]] = []
    cluster_C: list[list[np.ndarray]] = []
    rows = [0] * len(blocks)
    for item in chunks:
        A, n_runs, reps = (item, 1, []) if isinstance(item, torch.Tensor) else (tuple(item) + ([],))[:3]
        An = A.detach().cpu().numpy()
        D = [r.detach().cpu().numpy() - An for r in reps]
        N = An.shape[0]
        if N % n_runs:
            raise ValueError(f"{N} rows do not split into {n_runs} equal runs")
        per = N // n_runs
        parts = [slice(g * per + b.start, g * per + b.stop) for g in range(n_runs) for b in block_slices(per, per_run)]
        for part in parts:
            Rg, Cg = [], []
            for b, (i, k) in enumerate(blocks):
                x = An[part, i, k][:, local[b]]
                # Householder: a block is (nearly) rank-deficient by one on clean data -- its rows
                # are satisfied exactly by the true parameters -- so Gram/Cholesky shortcuts fail here
                # a run with no more rows than the block's columns keeps its rows as they are (the
                # same RᵀR as their factor, no QR, no padding): many one-step runs (randomly drawn
                # steps) would otherwise cost a QR and hold a full square each
                Rg.append(x if x.shape[0] <= x.shape[1] else np.linalg.qr(x, mode="r"))
                rows[b] += x.shape[0]
                if D:
                    dx = [d[part, i, k][:, local[b]] for d in D]
                    Cg.append(sum(e.T @ e for e in dx) / len(D))
            cluster_R.append(Rg)
            if D:
                cluster_C.append(Cg)
    full_cols = [columns.full[i, c] for (i, _), c in zip(blocks, local)]
    merged = []
    for b, cols in enumerate(full_cols):
        stack = np.concatenate([Rg[b] for Rg in cluster_R]) if cluster_R else np.zeros((0, len(cols)))
        r = _square(np.linalg.qr(stack, mode="r"), len(cols))
        merged.append(_embed(r, np.arange(len(cols)), cols, n_full))
    noise = None
    if cluster_C and len(cluster_C) == len(cluster_R):
        noise = [_embed(sum(Cg[b] for Cg in cluster_C), cols, cols, n_full)
                 for b, cols in enumerate(full_cols)]
    return BlockFactors(R=merged, rows=rows, blocks=blocks, columns=full_cols, cluster_R=cluster_R,
                        noise=noise, cluster_noise=cluster_C if noise is not None else None,
                        clusters=clusters if per_run > 1 else "")


def solve(
    factors: BlockFactors,
    layout: ParameterLayout,
    anchor: Anchor,
    fixed: dict[int, float] | None = None,
    reweight: bool = True,
) -> Solution:
    """Anchored weighted least squares ``min sum_b a_b ||R_b G phi||^2`` s.t. the anchor and fixed
    values; with a noise model (``factors.noise``), the errors-in-variables estimator of the module
    docstring.

    ``fixed`` pins full-vector entries (e.g. ``h = 1`` when there are no pushes, which leaves it
    out of the data).  Raises :class:`IdentifiabilityError` naming the parameters that the data
    cannot determine.
    """
    G = layout.tie
    phi_p, Nul = _constrained(layout, anchor, fixed)
    Rg = [R @ G for R in factors.R]
    m = np.array([max(r, 1) for r in factors.rows], dtype=float)
    eiv = reweight and factors.noise is not None
    Cg = [G.T @ c @ G for c in factors.noise] if eiv else None

    # FGLS with one weight per rod and kind (translation / rotation); the initial weights
    # equilibrate the units of force and torque rows
    groups = [2 * i + (k >= 3) for i, k in factors.blocks]
    gsize = np.bincount(groups, weights=m)
    energy = np.bincount(groups, weights=[np.linalg.norm(r) ** 2 for r in Rg])
    a = gsize[groups] / np.maximum(energy[groups], 1e-300)
    phi, lin = _weighted_solve(Rg, a, None, Nul, phi_p, layout)
    if reweight:
        res = np.bincount(groups, weights=[np.linalg.norm(r @ phi) ** 2 for r in Rg])
        floor = EPS**2 * energy * (phi @ phi)
        a = gsize[groups] / np.maximum(np.maximum(res, floor)[groups], 1e-300)
        phi, lin = _weighted_solve(Rg, a, None, Nul, phi_p, layout)
    c = None
    if eiv:
        for _ in range(EIV_ITERATIONS):
            a, c = _eiv_weights(Rg, Cg, m, phi)
            new, lin = _weighted_solve(Rg, a, sum(cb * C for cb, C in zip(c, Cg)), Nul, phi_p, layout)
            change = np.max(np.abs(new - phi)) / max(np.max(np.abs(new)), 1e-300)
            phi = new
            if change < EIV_TOL:
                break
    cov_phi, how = covariance(factors, G, Nul, phi, a, c, lin)
    per_rod = np.zeros((layout.n_rods * 2, 2))
    for (i, k), r, mb in zip(factors.blocks, Rg, m):
        per_rod[2 * i + (k >= 3)] += (np.linalg.norm(r @ phi) ** 2, mb)
    s = lin.singular_values
    return Solution(
        theta=G @ phi,
        cov=G @ cov_phi @ G.T,
        residual_rms=[float(np.sqrt(e / max(n, 1))) for e, n in per_rod],
        condition=float(s[0] / s[-1]) if s.size else 1.0,
        rows=int(sum(factors.rows)),
        free=Nul.shape[1],
        covariance=how,
        errors_in_variables=eiv,
    )


def free_parameters(layout: ParameterLayout, anchor: Anchor, fixed: dict[int, float] | None = None) -> int:
    """How many free parameters a solve with this anchor and these fixed values has."""
    return int(_constrained(layout, anchor, fixed)[1].shape[1])


def _weighted_solve(
    Rg: list[np.ndarray],
    a: np.ndarray,
    comp: np.ndarray | None,
    Nul: np.ndarray,
    phi_p: np.ndarray,
    layout: ParameterLayout,
) -> tuple[np.ndarray, LinearSolve]:
    """``phi = phi_p + Nul z`` minimising ``sum_b a_b ||R_b phi||^2 - phiᵀ comp phi``.

    Orthogonal solve: the SVD ``BN / scale = U S Vᵀ`` of the weighted, column-scaled factors, then
    the compensation as the well-conditioned ``(I - K) y = ...`` in the rotated coordinates
    ``z = M y``, ``M = scale⁻¹ V S⁻¹`` (with ``comp = 0`` this is the plain orthogonal solve).
    """
    B = np.vstack([np.sqrt(ab) * r for ab, r in zip(a, Rg)])
    BN = B @ Nul
    scale = np.linalg.norm(BN, axis=0)
    scale[scale == 0] = 1.0
    U, s, Vt = np.linalg.svd(BN / scale, full_matrices=False)
    tol = s[0] * max(BN.shape) * EPS * 10 if s.size else 0.0
    _check_rank(s <= tol, Vt, scale, Nul, layout, "rank-deficient regression")
    M = (Vt.T / s) / scale[:, None]
    y = U.T @ -(B @ phi_p)
    IK = None
    if comp is not None:
        IK = np.eye(len(s)) - M.T @ (Nul.T @ comp @ Nul) @ M
        IK = 0.5 * (IK + IK.T)
        ev, evec = np.linalg.eigh(IK)
        # a direction whose curvature the noise accounts for entirely is not identified beyond noise
        _check_rank(ev <= 1e3 * EPS * max(1.0, ev.max()), (M @ evec).T * scale, scale, Nul, layout,
                    "the rows' noise accounts for all of their variation")
        y = np.linalg.solve(IK, y + M.T @ (Nul.T @ comp @ phi_p))
    phi = phi_p + Nul @ (M @ y)
    resid = float(sum(ab * np.linalg.norm(r @ phi) ** 2 for ab, r in zip(a, Rg)))
    return phi, LinearSolve(M=M, IK=IK, singular_values=s, residual=resid)


def _eiv_weights(
    Rg: list[np.ndarray], Cg: list[np.ndarray], m: np.ndarray, phi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``a_b = m_b / phiᵀG_b phi`` (residual) and ``c_b = m_b / phiᵀC_b phi`` (predicted noise)."""
    res = np.array([np.linalg.norm(r @ phi) ** 2 for r in Rg])
    noise = np.array([phi @ C @ phi for C in Cg])
    floor = EPS**2 * np.array([np.linalg.norm(r) ** 2 for r in Rg]) * (phi @ phi)
    a = m / np.maximum(np.maximum(res, floor), 1e-300)
    c = np.where(noise > floor, m / np.maximum(noise, 1e-300), 0.0)
    return a, c


def _constrained(
    layout: ParameterLayout, anchor: Anchor, fixed: dict[int, float] | None
) -> tuple[np.ndarray, np.ndarray]:
    """A particular solution of the anchor and fixed values, and the null space of these constraints."""
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
    return np.linalg.lstsq(C, d, rcond=None)[0], sla.null_space(C)


def _check_rank(bad: np.ndarray, directions: np.ndarray, scale: np.ndarray, Nul: np.ndarray,
                layout: ParameterLayout, why: str) -> None:
    if not bad.any():
        return
    names: list[str] = []
    for v in directions[bad]:
        for n in layout.describe_free(Nul @ (v / scale)):
            if n not in names:
                names.append(n)
    raise IdentifiabilityError(
        "the data cannot identify " + ", ".join(names[:12]) + (" ..." if len(names) > 12 else "")
        + f" ({why}: excite these with more varied motion, pushes or longer runs)", names
    )


def _embed(block: np.ndarray, rows: np.ndarray, cols: np.ndarray, n_full: int) -> np.ndarray:
    out = np.zeros((n_full, n_full))
    out[np.ix_(rows, cols)] = block
    return out


def _square(r: np.ndarray, n: int) -> np.ndarray:
    """Pad a QR ``R`` factor with fewer rows than columns to (n, n)."""
    if r.shape[0] == n:
        return r
    out = np.zeros((n, n))
    out[: r.shape[0]] = r
    return out


def _independent_rows(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``C`` each independent of those before it (greedily, first to last), and their
    indices.  A row equal to an earlier one never is; when the first of each distinct row are
    independent together, so is each of them of those before it (a subset of independent rows is
    independent), and one rank test decides."""
    _, first = np.unique(C, axis=0, return_index=True)
    first = np.sort(first)
    if np.linalg.matrix_rank(C[first]) == len(first):
        return C[first], first.astype(int)
    keep: list[int] = []
    for i in range(C.shape[0]):
        trial = C[keep + [i]]
        if np.linalg.matrix_rank(trial) == len(keep) + 1:
            keep.append(i)
    return C[keep], np.array(keep, dtype=int)
