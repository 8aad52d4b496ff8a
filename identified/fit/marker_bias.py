"""The marker fit's second-order bias: what fitting every window's own states costs the parameters.

The marker fit (:mod:`identified.fit.marker_fit`) estimates the shared parameters ``θ`` together
with each window's own initial states ``x_w`` (incidental parameters: every window brings its
own).  Least squares is unbiased only where the residuals are linear in what it fits over the
range the noise moves it.  At coarse noise (30 Hz, 1 cm) a window's states are known only to the
noise's order, and over that range the markers of rods that make and break contact with the
ground are far from linear in them (``benchmarks/bench_state_steps.py --roughness``).  Then the
fitted states' residuals are shifted on average by

    d_i = tr(C_w H_i),     C_w = (J_xwᵀ J_xw)⁻¹ the window's state covariance,
                           H_i the Hessian of residual i in the window's states,

and the parameters take up the part of that shift the states cannot (Box 1971, *J. R. Stat. Soc.
B* 33, "Bias in nonlinear estimation", with the states eliminated as in
:func:`identified.fit.bound.window_gradient`):

    b = E[θ̂ - θ] ≈ -½ F⁻¹ Σ_w J_θwᵀ (I - P_w) d_w,    F = Σ_w J_θwᵀ (I - P_w) J_θw.

Every window adds its own ``d_w``, so the bias does not shrink as windows are added while the
standard errors do (the incidental-parameter problem of Neyman and Scott 1948, *Econometrica*
16): a fit of all the windows of a recording can stand several of its own standard errors from
the truth.  The terms of ``C`` in the shared parameters are left out; they shrink as ``1/W``.

``d_w`` is taken with sigma points, ``Σ_j [r(x + l_j) + r(x - l_j) - 2 r(x)]`` over the columns
``l_j`` of a square root of ``C_w`` (Julier and Uhlmann 2004, *Proc. IEEE* 92(3)): exact for
residuals quadratic in the states, and where contacts put kinks into the markers microns apart
(a Hessian at a point says nothing about the next centimetre) it is the curvature averaged over
the states' spread, which is what the bias needs.

The expansion holds where ``d`` is small against the noise.  In the test's windows ``d`` is 0.06
of the noise (RMS per window), and a fit of 20000 of them stands where it predicts, within one
standard error.  At 30 Hz and 1 cm on the robot it does not hold (``benchmarks/bench_marker_bias.py``,
all 330 windows of two recordings at the truth): ``d`` is 8-9 times the noise (RMS per window,
median), and the bias it predicts, every K 2 % (seed 7) or 4 % (seed 8) low at 6-14 standard
errors, is not where the marker fits of those recordings stop (every K within 0.6 and 1.2 %).  So
the marker fit does not apply it; it measures how far from linear the windows are.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from identified.fit.bound import window_gradient

__all__ = ["second_order_bias", "state_curvature", "state_sigma_points"]

#: eigenvalues of a window's state information below this fraction of its largest are directions
#: no marker sees (a rod's spin about the axis its end caps lie on): no sigma point along them
SIGMA_RANK_TOL = 1e-10


def state_sigma_points(Jx: torch.Tensor, noise_var: float = 1.0) -> torch.Tensor:
    """(W, n, n) the columns ``l_j`` of a square root of each window's state covariance
    ``noise_var (J_xᵀ J_x)⁺`` (``Jx`` (W, m, n), whitened residuals): its principal axes, each
    scaled to one standard deviation; a direction no residual sees has a zero column."""
    A = Jx.transpose(1, 2) @ Jx
    lam, V = torch.linalg.eigh(0.5 * (A + A.transpose(1, 2)))
    seen = lam > SIGMA_RANK_TOL * lam[:, -1:].clamp(min=1e-300)
    scale = torch.where(seen, (noise_var / lam.clamp(min=1e-300)).sqrt(), torch.zeros_like(lam))
    return V * scale.unsqueeze(1)


def state_curvature(residuals: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                    sigma_points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``d`` (W, m): each window's residuals' mean shift ``tr(C_w H_i)`` from the spread of its states,
    by sigma points (the module docstring), and ``ok`` (W,) bool: the windows whose every sigma
    point gave finite residuals.  ``residuals(x)`` (W, m) for the states ``x`` (W, n) of all the
    windows at once; ``sigma_points`` (W, n, n) from :func:`state_sigma_points`."""
    r0 = residuals(x)
    d = torch.zeros_like(r0)
    ok = torch.isfinite(r0).all(1)
    for j in range(sigma_points.shape[-1]):
        lj = sigma_points[..., j]
        if not bool((lj != 0).any()):
            continue
        plus, minus = residuals(x + lj), residuals(x - lj)
        step = plus + minus - 2.0 * r0
        ok &= torch.isfinite(step).all(1)
        d = d + torch.where(torch.isfinite(step), step, torch.zeros_like(step))
    return d, ok


def second_order_bias(Jx: np.ndarray, Jp: np.ndarray, d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(P,) the estimate's bias ``-½ C Σ_w J_θwᵀ (I - P_w) d_w`` (the module docstring): ``Jx`` (W, m,
    n) and ``Jp`` (W, m, P) the whitened residuals' Jacobians, ``d`` (W, m) from
    :func:`state_curvature`, ``cov`` (P, P) the parameters' covariance ``F⁻¹`` in the same
    whitened units (within any constraints: its rows then keep them)."""
    return -0.5 * np.asarray(cov, dtype=float) @ window_gradient(Jx, Jp, np.asarray(d, dtype=float))
