"""The marker fit in interleaved blocks of windows, combined by their information.

One fit of all of a recording's windows is one Levenberg-Marquardt problem over every window's
states and the shared parameters; where it stops, it cannot say whether that is the minimum.  At
30 Hz / 1 cm (a varied robot, seed 7) all 330 windows stopped at a cost per residual of 0.858, and
the 64 of them that a fit of their own brought to 0.815 stood at 0.860 there; fits of four other
64-window subsets stalled at 0.825-0.885 (measured; the README's recordings section).  Fitted in
blocks, the windows check each other: they share nothing but the parameters, so the blocks'
estimates are independent measurements of them, combined by their Fisher information:

    θ̄ = θ₀ + C Σ_b I_b (θ_b − θ₀),    C = U (Uᵀ (Σ_b I_b) U)⁺ Uᵀ

(``θ_b`` block ``b``'s unknowns -- logarithms, logits of the contact law's impedances --, ``I_b``
their information with the windows' states eliminated, ``U`` a basis of the steps that keep the
known total mass, ``θ₀`` the blocks' mean).  For a model linear in ``θ`` this is the estimate of
all the windows fitted together, and ``C`` its covariance (``tests/test_marker_blocks.py``).
Whether the blocks agree is a chi-square of their scatter about it,
``Σ_b (θ_b − θ̄)ᵀ I_b (θ_b − θ̄)`` over ``Σ_b rank_b − rank`` degrees of freedom (the ranks of the
blocks' and the sum's information within the total mass): blocks that disagree by more than their
error bars say that some block stopped short of its minimum or is biased.  Each block is also a
smaller problem (its memory, its own checkpoint).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.special import expit, logsumexp
from scipy.stats import chi2 as chi2_dist

from identified.fit.bound import constrained_bound, constraint_basis, informative
from identified.fit.marker_fit import Agreement, MarkerFit
from identified.fit.output_error import _impedances

__all__ = ["combine", "combine_fits"]


def combine(thetas: Sequence[np.ndarray], informations: Sequence[np.ndarray],
            constraint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Agreement]:
    """Blocks' estimates ``thetas`` (each (P,)) with their information ``informations`` (each
    (P, P)) combined: ``(θ̄, C, agreement)`` as the module docstring gives them, within the
    linear(ised) equality constraints ``constraint`` (k, P) that every block's estimate already
    meets.  A direction no block has information about keeps the blocks' mean."""
    T = np.asarray(thetas, dtype=float)
    if T.ndim != 2 or len(informations) != len(T):
        raise ValueError(f"{len(T)} estimates for {len(informations)} information matrices")
    U = constraint_basis(constraint, T.shape[1])
    Ib = [U.T @ np.asarray(I, dtype=float) @ U for I in informations]
    lam, V = np.linalg.eigh(sum(Ib))
    good = informative(lam)  # the directions some block has information about, as constrained_bound takes them
    C_u = (V[:, good] / lam[good]) @ V[:, good].T
    t0 = T.mean(0)
    rhs = sum(I @ (U.T @ (t - t0)) for I, t in zip(Ib, T))
    theta = t0 + U @ (C_u @ rhs)
    chi2 = float(sum((U.T @ (t - theta)) @ I @ (U.T @ (t - theta)) for I, t in zip(Ib, T)))
    dof = sum(int(informative(np.linalg.eigvalsh(I)).sum()) for I in Ib) - int(good.sum())
    p = float(chi2_dist.sf(chi2, dof)) if dof > 0 else float("nan")
    return theta, U @ C_u @ U.T, Agreement(chi2, int(dof), p)


def _natural(names: list[str], theta: np.ndarray, like: MarkerFit) -> np.ndarray:
    """The unknowns ``theta`` in their own units: the contact law's impedances (``law[imp_*]``) from
    their logits, every other parameter from its logarithm, relative to its unit in the fit ``like``
    (1, but an actuator's gain is its start's times the exponential of its unknown)."""
    logit = _impedances([n[4:-1] if n.startswith("law[") else n for n in names])
    unit = np.where(logit, 1.0, like.cov.values / np.exp(np.where(logit, 0.0, like.theta)))
    return np.where(logit, expit(theta), unit * np.exp(np.where(logit, 0.0, theta)))


def combine_fits(fits: Sequence[MarkerFit]) -> MarkerFit:
    """The marker fits of blocks of one recording's windows (:func:`~identified.fit.marker_fit.fit_markers`
    with ``block``) as one fit: the estimate and its covariance by :func:`combine` (then scaled to
    the blocks' exact total mass), its Cramer-Rao parameters not identifiable where no block's
    information reaches, the step left to the minimum the blocks' steps combined the same way, the
    residual's variance pooled over their degrees of freedom; ``blocks`` the fits, ``agreement``
    their :class:`Agreement`.  Its ``history`` is the block's whose last step lowered its cost the
    most (what says whether the combined fit is still moving)."""
    if not fits:
        raise ValueError("no fits to combine")
    names = fits[0].cov.names
    if any(f.cov.names != names or f.theta is None or f.information is None for f in fits):
        raise ValueError("the fits to combine must be of the same parameters, each with its unknowns and information")
    msl = fits[0].constraint > 0  # the masses' places in the unknowns (the total mass's row)
    log_total = float(logsumexp(fits[0].theta[msl]))
    theta, _, agreement = combine([f.theta for f in fits], [f.information for f in fits], fits[0].constraint)
    scaled = np.array([not n.startswith("law[") for n in names])  # the scale moves K, c, M, I, not the law
    theta = theta + scaled * (log_total - float(logsumexp(theta[msl])))
    mass = np.exp(theta[msl])
    row = np.zeros_like(theta)
    row[msl] = mass / mass.sum()
    information = sum(f.information for f in fits)
    cov = constrained_bound(information, names, _natural(names, theta, fits[0]), constraints=row[None])
    # each block's step left to its minimum, in its unknowns, combined like the estimates
    steps = [np.nan_to_num(f.to_minimum * f.cov.rel_se, posinf=0.0, neginf=0.0) if f.to_minimum is not None
             else np.zeros_like(theta) for f in fits]
    step = cov.cov @ sum(f.information @ s for f, s in zip(fits, steps))
    with np.errstate(divide="ignore", invalid="ignore"):
        to_minimum = np.where(cov.finite, step / cov.rel_se, np.nan)
    dof = float(sum(f.dof for f in fits))
    s2 = sum((f.residual_rms ** 2) * f.dof for f in fits) / max(dof, 1.0)
    moving = max(fits, key=lambda f: (f.history[-2] - f.history[-1]) / f.history[-1] if len(f.history) > 1 else 0.0)
    return MarkerFit(cov, sum(f.windows for f in fits), fits[0].available, float(np.sqrt(s2)), list(moving.history),
                     float(sum(f.seconds for f in fits)), all(f.converged for f in fits), to_minimum, dof, theta,
                     information, row, blocks=list(fits), agreement=agreement)
