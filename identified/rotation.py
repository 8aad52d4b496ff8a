"""Quaternion helpers in torch, w-x-y-z, batched over any leading dimensions.

All functions are differentiable (including through the small-angle limit of the exponential map)
and keep the dtype and device of their inputs.  Conventions match MuJoCo:

* a quaternion ``q = (w, x, y, z)`` rotates a body-frame vector into the world frame,
  ``v_world = R(q) v_body``;
* the product is Hamilton's, ``R(q1 ⊗ q2) = R(q1) R(q2)`` (MuJoCo ``mju_mulQuat``);
* integrating a BODY-frame angular velocity ``w_b`` over ``dt`` is
  ``q⁺ = normalise(q ⊗ exp(dt·w_b))`` (MuJoCo ``mju_quatIntegrate`` followed by
  ``mju_normalize4``), where ``exp`` of a rotation vector ``θ`` is
  ``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)``.

Shapes: quaternions ``(..., 4)``, vectors ``(..., 3)``, matrices ``(..., 3, 3)``; leading
dimensions broadcast.
"""

from __future__ import annotations

import torch

__all__ = [
    "matrix_apply",
    "matrix_apply_transpose",
    "quat_conjugate",
    "quat_exp",
    "quat_integrate",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_inverse",
    "quat_to_matrix",
]

# Below this squared angle the exponential map uses its Taylor series (relative error ~ |θ|^4/400,
# i.e. < 1e-26 here), which keeps every derivative finite at θ = 0.
_SMALL_ANGLE_SQ = 1e-12


def quat_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 ⊗ q2``: (..., 4), (..., 4) -> (..., 4).

    Computed as one bilinear map of the outer product ``q1 q2ᵀ`` (few kernels, fast on small batches).
    """
    q1, q2 = torch.broadcast_tensors(q1, q2)
    outer = (q1.unsqueeze(-1) * q2.unsqueeze(-2)).flatten(-2)  # (..., 16)
    return outer @ _constant("mul", q1)


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """``(w, -x, -y, -z)``, the inverse of a unit quaternion: (..., 4) -> (..., 4)."""
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """``q / |q|``: (..., 4) -> (..., 4).  A zero quaternion gives NaN (not an exception)."""
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of ``q`` (..., 4) -> (..., 3, 3), columns = body axes in the world frame.

    The quaternion need not be exactly unit: the matrix is that of ``q/|q|`` (the homogeneous form
    ``R = Q(q) / |q|²`` with ``Q`` quadratic), so noisy recorded quaternions still give a rotation.
    """
    outer = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)  # (..., 16)
    m = (outer @ _constant("mat", q)) / (q * q).sum(-1, keepdim=True)
    return m.unflatten(-1, (3, 3))


def matrix_apply(rot: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``R v`` for (..., 3, 3) and (..., 3) -> (..., 3) (body -> world)."""
    return torch.matmul(rot, v.unsqueeze(-1)).squeeze(-1)


def matrix_apply_transpose(rot: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``Rᵀ v`` for (..., 3, 3) and (..., 3) -> (..., 3) (world -> body)."""
    return torch.matmul(v.unsqueeze(-2), rot).squeeze(-2)


# ---------------------------------------------------------------------- constant bilinear maps
def _mul_table() -> list[list[float]]:
    """(16, 4): (q1 ⊗ q2)_k = Σ_ij q1_i q2_j T[4 i + j, k] (Hamilton, w-x-y-z)."""
    # e_i e_j = sign * e_k for the basis (1, i, j, k)
    prod = {(0, 0): (1, 0), (0, 1): (1, 1), (0, 2): (1, 2), (0, 3): (1, 3),
            (1, 0): (1, 1), (1, 1): (-1, 0), (1, 2): (1, 3), (1, 3): (-1, 2),
            (2, 0): (1, 2), (2, 1): (-1, 3), (2, 2): (-1, 0), (2, 3): (1, 1),
            (3, 0): (1, 3), (3, 1): (1, 2), (3, 2): (-1, 1), (3, 3): (-1, 0)}
    table = [[0.0] * 4 for _ in range(16)]
    for (i, j), (sign, k) in prod.items():
        table[4 * i + j][k] = float(sign)
    return table


def _mat_table() -> list[list[float]]:
    """(16, 9): R_ab |q|² = Σ_ij q_i q_j T[4 i + j, 3 a + b] (homogeneous rotation matrix)."""
    w, x, y, z = range(4)
    entries = {  # (a, b): [(coefficient, i, j), ...]
        (0, 0): [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)],
        (0, 1): [(2, x, y), (-2, w, z)],
        (0, 2): [(2, x, z), (2, w, y)],
        (1, 0): [(2, x, y), (2, w, z)],
        (1, 1): [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)],
        (1, 2): [(2, y, z), (-2, w, x)],
        (2, 0): [(2, x, z), (-2, w, y)],
        (2, 1): [(2, y, z), (2, w, x)],
        (2, 2): [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)],
    }
    table = [[0.0] * 9 for _ in range(16)]
    for (a, b), terms in entries.items():
        for coef, i, j in terms:
            table[4 * i + j][3 * a + b] += float(coef)
    return table


_TABLES = {"mul": _mul_table(), "mat": _mat_table()}
_CACHE: dict[tuple[str, torch.dtype, torch.device], torch.Tensor] = {}


def _constant(name: str, like: torch.Tensor) -> torch.Tensor:
    key = (name, like.dtype, like.device)
    t = _CACHE.get(key)
    if t is None:
        t = _CACHE[key] = torch.tensor(_TABLES[name], dtype=like.dtype, device=like.device)
    return t


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate a body-frame vector into the world frame, ``R(q) v``: (..., 4), (..., 3) -> (..., 3)."""
    return matrix_apply(quat_to_matrix(q), v)


def quat_rotate_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate a world-frame vector into the body frame, ``R(q)ᵀ v``: (..., 4), (..., 3) -> (..., 3)."""
    return matrix_apply_transpose(quat_to_matrix(q), v)


def quat_exp(theta: torch.Tensor) -> torch.Tensor:
    """Unit quaternion of a rotation vector ``θ`` (..., 3) -> (..., 4).

    ``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)``.  For tiny angles (``|θ| < 1e-6``) the Taylor series
    ``cos(a/2) ≈ 1 - a²/8`` and ``sin(a/2)/a ≈ 1/2 - a²/48`` is used behind a
    "double where", so the value and all derivatives stay finite and exact at ``θ = 0``.
    """
    a2 = (theta * theta).sum(-1)
    small = a2 < _SMALL_ANGLE_SQ
    a = torch.sqrt(torch.where(small, torch.ones_like(a2), a2))  # never sqrt(0): finite gradient
    half = 0.5 * a
    c_big = torch.cos(half)
    s_big = torch.sin(half) / a
    c_small = 1.0 - a2 / 8.0
    s_small = 0.5 - a2 / 48.0
    c = torch.where(small, c_small, c_big)
    s = torch.where(small, s_small, s_big)
    return torch.cat((c.unsqueeze(-1), s.unsqueeze(-1) * theta), dim=-1)


def quat_integrate(q: torch.Tensor, angvel_body: torch.Tensor, dt: float | torch.Tensor) -> torch.Tensor:
    """Rotate ``q`` by a body-frame angular velocity held for ``dt``: ``normalise(q ⊗ exp(dt·w_b))``.

    (..., 4), (..., 3) -> (..., 4).  This is MuJoCo's ``mju_quatIntegrate(q, w_b, dt)`` followed by
    ``mju_normalize4`` (``mj_integratePos`` for a ball or free joint).
    """
    return quat_normalize(quat_multiply(q, quat_exp(angvel_body * dt)))
