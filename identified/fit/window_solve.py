"""The windows' Gauss-Newton system with each window's nuisances eliminated (the Schur complement).

Windows ``w`` have their own nuisances ``x_w`` and share the parameters ``p``; the normal equations

    [ A_w   B_w ] [dx_w]     [g_x,w]
    [ B_wᵀ  C_w ] [dp  ] = - [g_p,w]      (summed over w in the parameters' rows)

with ``A_w = J_xᵀ J_x`` (plus whatever diagonal the caller adds), ``B_w = J_xᵀ J_p``, ``C_w = J_pᵀ J_p``
are block-arrow: eliminating each ``dx_w`` leaves the reduced system in ``p`` alone,

    S dp = - g_s,   S = Σ_w (C_w - B_wᵀ A_w⁻¹ B_w),   g_s = Σ_w (g_p,w - B_wᵀ A_w⁻¹ g_x,w),

and back-substitution gives each window's step ``dx_w = -(A_w⁻¹ g_x,w + A_w⁻¹ B_w dp)``
(Triggs et al. 2000, *Bundle Adjustment -- A Modern Synthesis*, sec. 6.1; Nocedal and Wright 2006,
*Numerical Optimization*, sec. 16.2).  The parameter step itself (its damping, its gauge) is the
caller's: :func:`identified.fit.output_error.refine_markers`, :func:`identified.fit.marker_fit.fit_markers`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["WindowSchur", "window_schur"]


@dataclass
class WindowSchur:
    """The windows' factorised normal matrices and the reduced parameter system: ``chol`` (W, nx, nx)
    the Cholesky factor of each ``A_w``, ``B`` (W, nx, P) ``= J_xᵀ J_p``, ``AiB`` (W, nx, P)
    ``= A_w⁻¹ B_w``, ``S`` (P, P) the Schur complement ``Σ_w C_w - B_wᵀ A_w⁻¹ B_w`` (symmetrised)."""

    chol: torch.Tensor
    B: torch.Tensor
    AiB: torch.Tensor
    S: torch.Tensor

    def reduce(self, gx: torch.Tensor, gp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(A⁻¹ g_x, g_s)`` for the windows' gradients ``gx`` (W, nx, 1) and the parameters' ``gp``
        (P, 1) summed over the windows: ``g_s = gp - Σ_w B_wᵀ A_w⁻¹ g_x,w``, the reduced gradient."""
        Aig = torch.cholesky_solve(gx, self.chol)
        return Aig, gp - (self.B.transpose(1, 2) @ Aig).sum(0)

    def back_substitute(self, Aig: torch.Tensor, dp: torch.Tensor) -> torch.Tensor:
        """(W, nx, 1) each window's nuisance step at the parameter step ``dp`` (P, 1):
        ``-(A_w⁻¹ g_x,w + A_w⁻¹ B_w dp)``, ``Aig`` from :meth:`reduce`."""
        return -(Aig + self.AiB @ dp)


def window_schur(A: torch.Tensor, B: torch.Tensor, C: torch.Tensor) -> WindowSchur:
    """The reduced system of the windows' normal matrices ``A`` (W, nx, nx, positive definite),
    their cross blocks ``B`` (W, nx, P) ``= J_xᵀ J_p`` and the parameters' block ``C`` (P, P)
    ``= Σ_w J_pᵀ J_p``: ``S = C - Σ_w B_wᵀ A_w⁻¹ B_w`` (the module docstring)."""
    chol = torch.linalg.cholesky(A)
    AiB = torch.cholesky_solve(B, chol)
    S = C - (B.transpose(1, 2) @ AiB).sum(0)
    return WindowSchur(chol, B, AiB, 0.5 * (S + S.T))
