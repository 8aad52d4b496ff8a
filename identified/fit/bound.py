"""The Cramér-Rao bound: how well any unbiased estimator can know each parameter from given data.

The measurement model is the output-error one (:mod:`identified.fit.output_error`): windows ``w``,
each with its own nuisance unknowns ``x_w`` (the rods' initial state, the ground's wrench) and the
shared parameters ``θ`` (logarithms of K, c, M, I), residuals ``r_w(θ, x_w) / σ`` with independent
unit Gaussian noise.  The Fisher information of ``θ`` with every ``x_w`` unknown is the Schur
complement of the nuisance block, window by window:

    F = Σ_w J_θwᵀ (I - P_w) J_θw,    P_w the orthogonal projector onto the range of J_xw

(the "efficient information" after the nuisances are eliminated; Kay 1993, *Fundamentals of
Statistical Signal Processing I*, sec. 3.7; a nuisance direction no marker sees has a zero column
and projects nothing out).  Equality constraints ``g(θ) = 0`` -- the known total mass, which also
fixes the global scale that marker positions cannot see -- give the constrained bound
``U (Uᵀ F U)⁺ Uᵀ`` with ``U`` a basis of the null space of ``∂g/∂θ`` (Gorman and Hero 1990,
*IEEE Trans. Inf. Theory* 36(6); Stoica and Ng 1998).  A parameter that moves along a direction of
zero information (e.g. a rod's axial moment when its markers lie on its axis) has no finite bound:
it is reported as not identifiable, never as a number.

The bound is on the logarithms, so ``sqrt(C_ii)`` is the relative standard error of parameter
``i`` to first order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

__all__ = ["CramerRao", "constrained_bound", "constraint_basis", "informative", "window_gradient",
           "window_information"]

#: singular values of a window's nuisance Jacobian below this fraction of its largest are no
#: direction the data sees (they project nothing out)
RANK_TOL = 1e-10
#: eigenvalues of the constrained information below this fraction of its largest: no information
NULL_TOL = 1e-12
#: a relative Cramér-Rao bound above this: not identifiable at this rate and noise (a 95 % interval
#: wider than ±60 % says nothing useful about the value)
NOT_IDENTIFIABLE = 0.3


def _nuisance_free(Jx: np.ndarray, Jp: np.ndarray, rank_tol: float):
    """Each window's ``(I - P_w) J_θw``: its parameter Jacobian with what the window's own
    nuisances can do projected out (rank-deficient ``Jx`` is fine)."""
    Jx, Jp = np.asarray(Jx, dtype=float), np.asarray(Jp, dtype=float)
    if Jx.ndim != 3 or Jp.ndim != 3 or Jx.shape[:2] != Jp.shape[:2]:
        raise ValueError(f"Jacobians of shapes {Jx.shape} and {Jp.shape}: want (W, m, nx) and (W, m, P)")
    for jx, jp in zip(Jx, Jp):
        if jx.shape[1]:
            u, s, _ = np.linalg.svd(jx, full_matrices=False)
            u = u[:, s > rank_tol * max(float(s[0]) if s.size else 0.0, 1e-300)]
            jp = jp - u @ (u.T @ jp)
        yield jp


def window_information(Jx: np.ndarray, Jp: np.ndarray, rank_tol: float = RANK_TOL) -> np.ndarray:
    """(P, P) Fisher information of the parameters from whitened residuals with Jacobians ``Jx``
    (W, m, nx) in each window's own nuisances and ``Jp`` (W, m, P) in the shared parameters:
    ``Σ_w Jpᵀ (I - P_w) Jp`` (the module docstring).  Rank-deficient ``Jx`` is fine."""
    F = np.zeros((np.shape(Jp)[-1],) * 2)
    for jp in _nuisance_free(Jx, Jp, rank_tol):
        F += jp.T @ jp
    return 0.5 * (F + F.T)


def window_gradient(Jx: np.ndarray, Jp: np.ndarray, r: np.ndarray, rank_tol: float = RANK_TOL) -> np.ndarray:
    """(P,) half the gradient of the cost ``Σ r²`` in the parameters with every window's nuisances
    re-fitted to first order: ``Σ_w Jpᵀ (I - P_w) r_w`` (``r`` (W, m), whitened).  With
    :func:`window_information` ``F`` it gives the Gauss-Newton step of the parameters to the minimum
    of the cost's quadratic model, ``-F⁻¹ g`` (nuisances and parameters stepped together)."""
    r = np.asarray(r, dtype=float)
    g = np.zeros(np.shape(Jp)[-1])
    for jp, rw in zip(_nuisance_free(Jx, Jp, rank_tol), r):
        g += jp.T @ rw
    return g


@dataclass
class CramerRao:
    """The bound on the log-parameters ``names`` at ``values``: ``cov`` (P, P), and which
    parameters have one (``finite``: false where the parameter moves along a direction the data
    carries no information about)."""

    names: list[str]
    values: np.ndarray
    cov: np.ndarray
    finite: np.ndarray

    @property
    def rel_se(self) -> np.ndarray:
        """(P,) relative standard error each parameter cannot beat (inf: no bound, not identifiable)."""
        return np.where(self.finite, np.sqrt(np.clip(np.diag(self.cov), 0.0, None)), np.inf)

    def identifiable(self, max_rel: float = NOT_IDENTIFIABLE) -> np.ndarray:
        """(P,) bool: the bound is finite and at most ``max_rel`` (relative)."""
        return self.rel_se <= max_rel

    def describe(self, i: int, max_rel: float = NOT_IDENTIFIABLE) -> str:
        """One phrase for parameter ``i``: its bound, or why it is not identifiable."""
        r = self.rel_se[i]
        if not np.isfinite(r):
            return f"{self.names[i]}: not identifiable (no information in the markers)"
        if r > max_rel:
            return f"{self.names[i]}: not identifiable at this rate/noise (Cramer-Rao bound {100 * r:.3g} %)"
        return f"{self.names[i]}: Cramer-Rao bound {100 * r:.3g} %"


def constraint_basis(constraints: np.ndarray | None, P: int) -> np.ndarray:
    """(P, P - k) an orthonormal basis of the steps in ``P`` unknowns that keep the linear(ised)
    equality constraints ``constraints`` (k, P) (rows: their gradients); the identity without any."""
    if constraints is None or np.size(constraints) == 0:
        return np.eye(P)
    return sla.null_space(np.atleast_2d(constraints))


def informative(lam: np.ndarray, null_tol: float = NULL_TOL) -> np.ndarray:
    """(n,) bool: which eigenvalues ``lam`` of an information matrix carry information, those above
    ``null_tol`` times the largest (the others: directions the data say nothing about)."""
    return lam > null_tol * max(float(lam.max()) if lam.size else 0.0, 1e-300)


def constrained_bound(F: np.ndarray, names: list[str], values: np.ndarray,
                      constraints: np.ndarray | None = None, null_tol: float = NULL_TOL) -> CramerRao:
    """The Cramér-Rao bound of log-parameters with Fisher information ``F`` (P, P) under linear(ised)
    equality constraints ``constraints`` (k, P) (rows: gradients of the constraints in the
    log-parameters): ``U (Uᵀ F U)⁺ Uᵀ``; the parameters with a component along a direction of
    (numerically) zero information within the constraints are marked not ``finite``."""
    F = np.asarray(F, dtype=float)
    P = F.shape[0]
    if F.shape != (P, P) or len(names) != P or np.shape(values) != (P,):
        raise ValueError(f"information {F.shape}, {len(names)} names, values {np.shape(values)}: sizes differ")
    U = constraint_basis(constraints, P)
    lam, V = np.linalg.eigh(U.T @ F @ U)
    good = informative(lam, null_tol)
    W = U @ V
    cov = (W[:, good] / lam[good]) @ W[:, good].T
    blind = W[:, ~good]
    finite = ~(np.abs(blind) > 1e-6 * max(1.0, float(np.abs(W).max()))).any(axis=1)
    return CramerRao(list(names), np.asarray(values, dtype=float), cov, finite)
