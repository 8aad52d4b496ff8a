"""Products and inverses of small matrices (3x3, 6x6) written as elementwise torch work.

The engine and its effects work on many tiny matrices: a 3x3 rotation per rod, a 6x6 contact
matrix per rod.  ``torch.matmul`` and ``torch.linalg.inv`` on them are library calls (batched
GEMM, LAPACK's LU) whose fixed cost per call dwarfs the arithmetic: measured on the robot twin,
one compiled substep spent half its time in two ``linalg.inv`` calls on six 6x6 matrices.
Written out as broadcasts and sums, the same work is a handful of elementwise loops that
``torch.compile`` fuses with the code around them (and, eagerly, a few small kernels).

* :func:`mm` ``a @ b`` for small matrices (..., n, k) @ (..., k, m), by a broadcast product and a sum;
* :func:`inverse3` (..., 3, 3) by the adjugate (rows' cross products over the determinant);
* :func:`inverse6` (..., 6, 6) by 3x3 blocks (the Schur complement of the upper-left block), for
  matrices whose upper-left 3x3 block and its Schur complement are invertible (positive-definite
  matrices always are).

Accuracy: these are the textbook formulas; for the well-conditioned matrices they are used on
(regularised positive-definite contact matrices, the implicit integrator's mass matrices) they
agree with LAPACK to a few units of rounding of the dtype.
"""

from __future__ import annotations

import torch

__all__ = ["inverse3", "inverse6", "mm"]


def mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for small matrices, (..., n, k) @ (..., k, m) -> (..., n, m), as a broadcast
    product summed over ``k`` (fuses under ``torch.compile``; no GEMM call)."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def inverse3(m: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 3, 3) matrices by the adjugate (rows' cross products over the determinant).

    A singular matrix gives inf/NaN entries (no exception)."""
    r0, r1, r2 = m.unbind(-2)
    cols = torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], -1)
    det = (r0 * cols[..., 0]).sum(-1)
    return cols / det[..., None, None]


def inverse6(m: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 6, 6) matrices ``[[P, Q], [U, W]]`` by 3x3 blocks:
    ``S = W - U P⁻¹ Q``, ``M⁻¹ = [[P⁻¹ + P⁻¹Q S⁻¹ U P⁻¹, -P⁻¹Q S⁻¹], [-S⁻¹ U P⁻¹, S⁻¹]]``."""
    P, Q = m[..., :3, :3], m[..., :3, 3:]
    U, W = m[..., 3:, :3], m[..., 3:, 3:]
    Pi = inverse3(P)
    X = mm(Pi, Q)  # P⁻¹ Q
    Y = mm(U, Pi)  # U P⁻¹
    Si = inverse3(W - mm(U, X))
    tr = -mm(X, Si)
    bl = -mm(Si, Y)
    tl = Pi - mm(tr, Y)
    return torch.cat((torch.cat((tl, tr), -1), torch.cat((bl, Si), -1)), -2)
