"""Standard errors of the regression that hold on noisy, overlapping weak-form rows.

The textbook covariance ``sigma² (BᵀB)⁻¹`` of least squares assumes independent rows.  Weak-form
windows overlap (stride = window / 4, :mod:`identified.fit.derivatives`), so neighbouring rows
share noise, and with errors in variables the regressors carry noise too: the textbook errors come
out too small.  Rows of different episodes, however, share nothing -- windows never cross an
episode, the sensor noise is independent between them -- so the covariance is estimated over
these independent runs, by the cluster jackknife (Cameron and Miller 2015, J. Human Resources 50:
317, section VI.B; MacKinnon and White 1985, J. Econometrics 29: 305):

    Var(z) = (G-1)/G sum_g (d_g - mean d)(d_g - mean d)ᵀ,    d_g = (A - A_g)⁻¹ psi_g

with ``A`` the curvature of the fit's objective in the anchor's null space, ``A_g`` run ``g``'s
part of it and ``psi_g`` its contribution to the estimating equation
(:mod:`identified.fit.regression`): ``d_g`` is the shift of the estimate when run ``g`` is left
out (the Newton step from the full solution, exact for least squares).  The plain cluster-robust
sandwich ``A⁻¹ [G/(G-1) sum_g psi_g psi_gᵀ] A⁻¹`` (Liang and Zeger 1986, Biometrika 73: 13) is
its first-order form ``A - A_g ~ A``: it is too narrow when a few runs hold most of the
information about a parameter (a cable taut in one take only, an impact in one), the jackknife
widens it by each run's leverage.  Each run keeps its own triangular factors, so ``psi_g`` and
``A_g`` need no second pass over the data.

With fewer than :data:`MIN_RUNS` independent runs the spread of the runs is too noisy: each run
is then cut into consecutive blocks of its rows (:func:`blocks_per_run`, :func:`block_slices`) --
contiguous in time, each at least :data:`MIN_BLOCK_SECONDS` and :data:`MIN_BLOCK_WINDOWS`
weak-form windows long -- so that there are ``MIN_RUNS`` blocks or more, and the same jackknife
runs over the blocks (large contiguous blocks of dependent data as clusters, whose dependence
lives near their borders: Bester, Conley and Hansen 2011, J. Econometrics 165: 137).  Two
neighbouring blocks of a run are not independent: the rows near their border share noise, through
the windows that overlap across it and the correlation that the splines of a reconstruction leave
in the states (over the splines' smoothing length).  For rows whose noise correlates over
``l`` steps (a triangle ``rho(t) = (1 - |t|/l)+``; ``l`` the window ``w`` plus the smoothing
length), two adjacent blocks of ``B`` steps have a covariance ``l/(6B)`` times each one's variance,
so the jackknife, which takes the blocks as independent, misses at most ``2 l/(6B)`` of the
variance: with ``l = w``, ``<= 1/(3 MIN_BLOCK_WINDOWS) = 8 %`` (4 % of a standard error; ~3 % for
the 2 s blocks of 4 s takes), and with a smoothing length as long again twice that: small against the
jackknife's own spread over ~10 blocks (~45 % in variance), so no window is dropped at a cut (which
would also change the estimate).  Measured on the robot from 6 takes of 4 s (README, "Fewer than
10 takes"), the z-scores of K, c and M against the truth have an RMS of 1.2-1.3 (2.3-4.3 with the
iid formula).  Runs too short for ``MIN_RUNS`` such blocks keep the iid formula
(``Solution.covariance`` says which was used).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

__all__ = ["MIN_BLOCK_SECONDS", "MIN_BLOCK_WINDOWS", "MIN_RUNS", "BlockFactors", "LinearSolve", "block_slices",
           "blocks_per_run", "covariance"]

#: fewest independent runs (episodes) for the cluster-robust covariance
MIN_RUNS = 10
#: a block cut within a run for the jackknife spans at least this many seconds
MIN_BLOCK_SECONDS = 1.0
#: ... and at least this many weak-form windows (its border rows are then a small part of it)
MIN_BLOCK_WINDOWS = 4


@dataclass
class BlockFactors:
    """Triangular factors of each equation block (rod, equation), merged and per independent run.

    ``R``: (n_full, n_full) merged factor per block; ``rows``: equations summed into it;
    ``blocks``: (rod, equation 0-5) of each block; ``columns``: full-vector index of each local
    column of a block; ``cluster_R``: [run][block] local triangular factor of that run's rows;
    ``noise`` / ``cluster_noise``: the same layout for the measured noise Gram ``E[ΔAᵀΔA]``
    (``None`` without a noise model); ``clusters``: what the runs are when they were cut from
    longer ones (:func:`block_slices`), e.g. "12 blocks of 2 s cut within 6 runs"; "" when each is
    a whole independent run.
    """

    R: list[np.ndarray]
    rows: list[int]
    blocks: list[tuple[int, int]]
    columns: list[np.ndarray]
    cluster_R: list[list[np.ndarray]]
    noise: list[np.ndarray] | None = None
    cluster_noise: list[list[np.ndarray]] | None = None
    clusters: str = ""


@dataclass
class LinearSolve:
    """One weighted solve in the anchor's null space (:func:`identified.fit.regression.solve`).

    ``z = M y`` with ``(I - K) y = ...``; ``IK`` is ``I - K`` (``None`` without the
    errors-in-variables compensation), so the curvature of the objective in ``z`` is
    ``A = M⁻ᵀ (I - K) M⁻¹``.  ``residual``: ``sum_b a_b ||R_b theta||²``.
    """

    M: np.ndarray
    IK: np.ndarray | None
    singular_values: np.ndarray
    residual: float


def covariance(
    factors: BlockFactors,
    G: np.ndarray,
    Nul: np.ndarray,
    phi: np.ndarray,
    a: np.ndarray,
    c: np.ndarray | None,
    lin: LinearSolve,
) -> tuple[np.ndarray, str]:
    """Covariance of the free parameters ``phi`` (``theta = G phi``) and how it was estimated.

    ``a``: the blocks' weights; ``c``: their noise weights (errors-in-variables fit) or ``None``.
    """
    IKinv = np.eye(lin.M.shape[1]) if lin.IK is None else np.linalg.inv(lin.IK)
    Ainv = lin.M @ IKinv @ lin.M.T
    runs = len(factors.cluster_R)
    if runs >= MIN_RUNS:
        psi = _influences(factors, G, Nul, phi, a, c)
        GN = G @ Nul
        T = [GN[cols] for cols in factors.columns]  # each block's columns in the free coordinates
        whole = _curvature([GN] * len(T), factors.R, factors.noise, a, c)  # merged factors: full columns
        d = np.array([_left_out(whole - _curvature(T, Rg, None if c is None else factors.cluster_noise[g], a, c),
                                Ainv, p) for g, (Rg, p) in enumerate(zip(factors.cluster_R, psi))])
        d -= d.mean(axis=0)
        cov_z = (runs - 1) / runs * (d.T @ d)
        how = f"cluster-robust jackknife over {factors.clusters or f'{runs} independent runs (episodes)'}"
    else:
        dof = max(int(sum(factors.rows)) - Nul.shape[1], 1)
        cov_z = (lin.residual / dof) * (lin.M @ IKinv @ IKinv @ lin.M.T)
        how = (f"iid rows (only {runs} independent runs, too short to cut into {MIN_RUNS} blocks: the overlap of "
               "weak-form windows is ignored)")
    return Nul @ cov_z @ Nul.T, how


def blocks_per_run(runs: int, rows_per_run: int, min_rows: int, min_runs: int = MIN_RUNS) -> int:
    """Into how many consecutive blocks to cut each of ``runs`` independent runs of (at least)
    ``rows_per_run`` rows: the fewest that make ``min_runs`` blocks in all, each of ``min_rows``
    rows or more; 1 (no cut) when the runs are enough already or too short to be cut so."""
    if runs >= min_runs or runs <= 0:
        return 1
    k = -(-min_runs // runs)
    return k if rows_per_run // k >= max(min_rows, 1) else 1


def block_slices(n_rows: int, blocks: int) -> list[slice]:
    """``blocks`` consecutive, contiguous slices covering rows ``0 .. n_rows - 1`` in order, of
    equal size but the first ``n_rows % blocks``, one row longer (rows are in time order: a
    block is a stretch of time)."""
    if not 1 <= blocks <= max(n_rows, 1):
        raise ValueError(f"cannot cut {n_rows} rows into {blocks} blocks")
    size, extra = divmod(n_rows, blocks)
    edges = np.cumsum([0] + [size + (g < extra) for g in range(blocks)])
    return [slice(int(a), int(b)) for a, b in pairwise(edges)]


def _influences(
    factors: BlockFactors,
    G: np.ndarray,
    Nul: np.ndarray,
    phi: np.ndarray,
    a: np.ndarray,
    c: np.ndarray | None,
) -> np.ndarray:
    """(runs, n_free): each run's part of the estimating equation at the solution.

    Least squares: ``sum_b a_b G_gb theta``.  Errors in variables (profile likelihood, see
    :mod:`identified.fit.regression`): ``sum_b a_b G_gb theta - c_b C_gb theta`` plus the run's share
    of the fitted noise factor ``rho_b = thetaᵀG_b theta / thetaᵀC_b theta``, ``-a_b thetaᵀ(G_gb -
    C_gb)theta / thetaᵀC_b theta C_b theta``, which makes a block of pure noise contribute nothing.
    """
    theta = G @ phi
    n_full = theta.size
    Ctheta = [C @ theta for C in factors.noise] if c is not None else None
    out = np.empty((len(factors.cluster_R), Nul.shape[1]))
    for g, Rg in enumerate(factors.cluster_R):
        total = np.zeros(n_full)
        for b, cols in enumerate(factors.columns):
            x = theta[cols]
            f = Rg[b].T @ (Rg[b] @ x)
            if c is None:
                np.add.at(total, cols, a[b] * f)
                continue
            h = factors.cluster_noise[g][b] @ x
            np.add.at(total, cols, a[b] * f - c[b] * h)
            pC = float(theta @ Ctheta[b])
            if pC > 0:
                total -= a[b] * (x @ f - x @ h) / pC * Ctheta[b]
        out[g] = Nul.T @ (G.T @ total)
    return out


def _curvature(T: list[np.ndarray], R: list[np.ndarray], C: list[np.ndarray] | None, a: np.ndarray,
               c: np.ndarray | None) -> np.ndarray:
    """The objective's curvature in the free coordinates, ``sum_b T_bᵀ (a_b R_bᵀ R_b - c_b C_b) T_b``,
    from blocks' factors ``R`` and noise Grams ``C`` (``T_b``: the map from the free coordinates to
    the factor's columns).  The merged factors give ``A``, one run's give its part ``A_g``."""
    out = np.zeros((T[0].shape[1], T[0].shape[1]))
    for b, t in enumerate(T):
        rt = R[b] @ t
        out += a[b] * (rt.T @ rt)
        if c is not None and C is not None:
            out -= c[b] * (t.T @ C[b] @ t)
    return out


def _left_out(rest: np.ndarray, Ainv: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """The shift ``rest⁻¹ psi`` of the estimate without one run (``rest``: the curvature of the
    others); where the others alone do not determine the parameters (``rest`` not positive
    definite: that run holds all the information on some direction), the sandwich's ``A⁻¹ psi``."""
    rest = 0.5 * (rest + rest.T)
    try:
        np.linalg.cholesky(rest)
    except np.linalg.LinAlgError:
        return Ainv @ psi
    return np.linalg.solve(rest, psi)
