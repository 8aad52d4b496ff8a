"""Standard errors of the regression that hold on noisy, overlapping weak-form rows.

The textbook covariance ``sigma² (BᵀB)⁻¹`` of least squares assumes independent rows.  Weak-form
windows overlap (stride = window / 4, :mod:`identified.fit.derivatives`), so neighbouring rows
share noise, and with errors in variables the regressors carry noise too: the textbook errors come
out too small.  Rows of different episodes, however, share nothing -- windows never cross an
episode, the sensor noise is independent between them -- so the covariance is estimated by the
cluster-robust sandwich over episodes (Liang and Zeger 1986, Biometrika 73: 13; Cameron and
Miller 2015, J. Human Resources 50: 317):

    Var(z) = A⁻¹ [ G/(G-1) sum_g psi_g psi_gᵀ ] A⁻¹

with ``A`` the curvature of the fit's objective in the anchor's null space and ``psi_g`` the
contribution of episode ``g`` to its estimating equation (:mod:`identified.fit.regression`).  Each
run keeps its own triangular factors, so ``psi_g = sum_b a_b R_gbᵀ R_gb theta - ...`` needs no
second pass over the data.  With fewer than :data:`MIN_RUNS` runs the sandwich is too noisy and
the iid formula is used (``Solution.covariance`` says which).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_RUNS", "BlockFactors", "LinearSolve", "covariance"]

#: fewest independent runs (episodes) for the cluster-robust covariance
MIN_RUNS = 10


@dataclass
class BlockFactors:
    """Triangular factors of each equation block (rod, equation), merged and per independent run.

    ``R``: (n_full, n_full) merged factor per block; ``rows``: equations summed into it;
    ``blocks``: (rod, equation 0-5) of each block; ``columns``: full-vector index of each local
    column of a block; ``cluster_R``: [run][block] local triangular factor of that run's rows;
    ``noise`` / ``cluster_noise``: the same layout for the measured noise Gram ``E[ΔAᵀΔA]``
    (``None`` without a noise model).
    """

    R: list[np.ndarray]
    rows: list[int]
    blocks: list[tuple[int, int]]
    columns: list[np.ndarray]
    cluster_R: list[list[np.ndarray]]
    noise: list[np.ndarray] | None = None
    cluster_noise: list[list[np.ndarray]] | None = None


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
        psi -= psi.mean(axis=0)
        meat = psi.T @ psi * (runs / (runs - 1))
        cov_z = Ainv @ meat @ Ainv
        how = f"cluster-robust sandwich over {runs} independent runs (episodes)"
    else:
        dof = max(int(sum(factors.rows)) - Nul.shape[1], 1)
        cov_z = (lin.residual / dof) * (lin.M @ IKinv @ IKinv @ lin.M.T)
        how = f"iid rows (only {runs} independent runs: the overlap of weak-form windows is ignored)"
    return Nul @ cov_z @ Nul.T, how


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
