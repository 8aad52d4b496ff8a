"""Small vectors and matrices (3-vectors, 3x3) as elementwise torch work: the *component form*.

The engine and its effects work on many tiny matrices: a 3x3 rotation per rod, a 6x6 contact
matrix per rod.  ``torch.matmul`` and ``torch.linalg.inv`` on them are library calls (batched
GEMM, LAPACK's LU) whose fixed cost per call dwarfs the arithmetic: measured on the robot twin,
one compiled substep spent half its time in two ``linalg.inv`` calls on six 6x6 matrices.
Written out as products and sums of components, the same work is a handful of elementwise loops
that ``torch.compile`` fuses with the code around them.

A 3-vector is a tuple of three tensors (..., n), a 3x3 matrix a tuple of nine, with their sums,
products, cross products (:func:`vcross`), ``M v`` (:func:`mv`), ``Mᵀ v`` (:func:`mtv`), products
(:func:`mmul`), inverses (:func:`minverse`, by the adjugate; :func:`inverse3` the same on (..., 3, 3)
tensors, for the implicit integrator's block solve) and gathers (:func:`gather`); :func:`vec`/:func:`unvec`
convert from and to the tensor form.  A 6x6 contact matrix is solved by
its 3x3 blocks (the Schur complement of the upper-left block:
``identified.effects.ground_contact._masked_block_solve``).

Accuracy: these are the textbook formulas; for the well-conditioned matrices they are used on
(regularised positive-definite contact matrices, the implicit integrator's mass matrices) they agree with LAPACK to a few units of
rounding of the dtype (tests/test_twin_speed.py).
"""

from __future__ import annotations

import torch

__all__ = ["Mat", "Vec", "gather", "inverse3", "mat", "minverse", "mmul", "mtranspose", "mtv", "mv", "unvec", "vadd",
           "vcross", "vdot", "vec", "vscale", "vsub"]


# ---------------------------------------------------------------------- component form
# The twin's fused step keeps every 3-vector as a tuple of three tensors (x, y, z) and every 3x3
# matrix as a tuple of nine (row-major), each of shape (..., n): "struct of arrays". Every
# operation is then elementwise over the batch and the rods, with no trailing dimension of 3, so
# that ``torch.compile`` turns a whole substep into a few long loops it vectorises across envs and
# rods (a trailing dimension of 3 became a masked 16-lane vector op for 3 numbers, or a scalar
# loop). The tensor form (``(..., 3)``, ``(..., 3, 3)``) of the engine's public functions unbinds
# into these and stacks back: each formula is written once, here or in the function that uses it.
Vec = tuple  # (x, y, z), each (..., n)
Mat = tuple  # (m00, m01, m02, m10, ..., m22), each (..., n)


def vec(x: torch.Tensor) -> Vec:
    """(..., 3) -> the tuple of its three components (views)."""
    return tuple(x.unbind(-1))


def unvec(v: Vec) -> torch.Tensor:
    """A tuple of components -> (..., k) (stacked on a new last dimension)."""
    return torch.stack(tuple(v), -1)


def mat(m: torch.Tensor) -> Mat:
    """(..., 3, 3) -> its nine entries, row-major (views)."""
    return tuple(m.flatten(-2).unbind(-1))


def vadd(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def vsub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def vscale(a: Vec, s: torch.Tensor | float) -> Vec:
    return (a[0] * s, a[1] * s, a[2] * s)


def vdot(a: Vec, b: Vec) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def vcross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def mv(m: Mat, v: Vec) -> Vec:
    """``M v``."""
    return (m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
            m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
            m[6] * v[0] + m[7] * v[1] + m[8] * v[2])


def mtv(m: Mat, v: Vec) -> Vec:
    """``Mᵀ v``."""
    return (m[0] * v[0] + m[3] * v[1] + m[6] * v[2],
            m[1] * v[0] + m[4] * v[1] + m[7] * v[2],
            m[2] * v[0] + m[5] * v[1] + m[8] * v[2])


def mmul(a: Mat, b: Mat) -> Mat:
    """``A B``."""
    return tuple(a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]
                 for i in range(3) for j in range(3))


def mtranspose(a: Mat) -> Mat:
    return (a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8])


def minverse(m: Mat) -> Mat:
    """The inverse by the adjugate (rows' cross products over the determinant); a singular matrix
    gives inf/NaN entries (no exception)."""
    r0, r1, r2 = m[0:3], m[3:6], m[6:9]
    c0, c1, c2 = vcross(r1, r2), vcross(r2, r0), vcross(r0, r1)
    d = 1.0 / vdot(r0, c0)
    return (c0[0] * d, c1[0] * d, c2[0] * d, c0[1] * d, c1[1] * d, c2[1] * d, c0[2] * d, c1[2] * d, c2[2] * d)


def gather(v: tuple, index: torch.Tensor) -> tuple:
    """Every component of ``v`` indexed along its last dimension (rods -> spring ends)."""
    return tuple(c.index_select(-1, index) for c in v)


def inverse3(m: torch.Tensor) -> torch.Tensor:
    """:func:`minverse` on (..., 3, 3) tensors."""
    return torch.stack(minverse(mat(m)), -1).unflatten(-1, (3, 3))
