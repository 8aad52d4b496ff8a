"""The project's one rotation vocabulary: quaternions w-x-y-z, in torch and in numpy side by side.

Every function takes torch tensors or numpy arrays and answers in kind (a tensor keeps its dtype
and device; an array comes back float64), batched over any leading dimensions.  The torch path is
differentiable (including through the small-angle limit of the exponential map); the engine, the
fit and the twin use it.  The numpy path is what the plant, the env, data collection, the MJCF
builder and the topology reader use: the same formulas, so there is one definition of each
rotation in the project.  Conventions match MuJoCo:

* a quaternion ``q = (w, x, y, z)`` rotates a body-frame vector into the world frame,
  ``v_world = R(q) v_body``;
* the product is Hamilton's, ``R(q1 ⊗ q2) = R(q1) R(q2)`` (MuJoCo ``mju_mulQuat``);
* integrating a BODY-frame angular velocity ``w_b`` over ``dt`` is
  ``q⁺ = normalise(q ⊗ exp(dt·w_b))`` (MuJoCo ``mju_quatIntegrate`` followed by
  ``mju_normalize4``), where ``exp`` of a rotation vector ``θ`` is
  ``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)``.

Shapes: quaternions ``(..., 4)``, vectors ``(..., 3)``, matrices ``(..., 3, 3)``; leading
dimensions broadcast.

Speed: in eager torch, :func:`quat_multiply` and :func:`quat_to_matrix` are one bilinear map of the
outer product (a small matrix product: few kernel launches, fast on small batches); under
``torch.compile`` they are written out component by component instead, so the compiler fuses them
with their neighbours into one loop (a matrix product would stay a separate library call).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np
import torch

Array = TypeVar("Array", torch.Tensor, np.ndarray)

__all__ = [
    "matrix_apply",
    "matrix_apply_transpose",
    "matrix_to_quat",
    "quat_conjugate",
    "quat_exp",
    "quat_integrate",
    "quat_integrate_components",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_inverse",
    "quat_to_matrix",
    "quat_to_matrix_components",
]

# Below this squared angle the exponential map uses its Taylor series (relative error ~ |θ|^4/400,
# i.e. < 1e-26 here), which keeps every derivative finite at θ = 0.
_SMALL_ANGLE_SQ = 1e-12


def _np(x: object) -> bool:
    """True for anything that is not a torch tensor (numpy arrays, lists): the numpy path."""
    return not isinstance(x, torch.Tensor)


def _unrolled() -> bool:
    """Inside ``torch.compile``: write products out component by component (they fuse)."""
    return torch.compiler.is_compiling()


def quat_multiply(q1: Array, q2: Array) -> Array:
    """Hamilton product ``q1 ⊗ q2``: (..., 4), (..., 4) -> (..., 4)."""
    if _np(q1) or _np(q2):
        q1, q2 = np.asarray(q1, dtype=float), np.asarray(q2, dtype=float)
        return np.stack(_hamilton(np.moveaxis(q1, -1, 0), np.moveaxis(q2, -1, 0)), axis=-1)
    if _unrolled():
        return torch.stack(_hamilton(q1.unbind(-1), q2.unbind(-1)), dim=-1)
    q1, q2 = torch.broadcast_tensors(q1, q2)
    outer = (q1.unsqueeze(-1) * q2.unsqueeze(-2)).flatten(-2)  # (..., 16)
    return outer @ _constant("mul", q1)


def _hamilton(a: Sequence[Any], b: Sequence[Any]) -> tuple[Any, Any, Any, Any]:
    """The four components of the Hamilton product from the components of each factor."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def quat_conjugate(q: Array) -> Array:
    """``(w, -x, -y, -z)``, the inverse of a unit quaternion: (..., 4) -> (..., 4)."""
    if _np(q):
        q = np.asarray(q, dtype=float)
        return np.concatenate((q[..., :1], -q[..., 1:]), axis=-1)
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def quat_normalize(q: Array) -> Array:
    """``q / |q|``: (..., 4) -> (..., 4).  A zero quaternion gives NaN (not an exception)."""
    if _np(q):
        q = np.asarray(q, dtype=float)
        with np.errstate(invalid="ignore", divide="ignore"):
            return q / np.sqrt(np.einsum("...i,...i->...", q, q))[..., None]
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def quat_to_matrix(q: Array) -> Array:
    """Rotation matrix of ``q`` (..., 4) -> (..., 3, 3), columns = body axes in the world frame.

    The quaternion need not be exactly unit: the matrix is that of ``q/|q|`` (the homogeneous form
    ``R = Q(q) / |q|²`` with ``Q`` quadratic), so noisy recorded quaternions still give a rotation.
    """
    if _np(q):
        q = np.asarray(q, dtype=float)
        outer = (q[..., :, None] * q[..., None, :]).reshape(q.shape[:-1] + (16,))
        m = (outer @ _NP_TABLES["mat"]) / np.einsum("...i,...i->...", q, q)[..., None]
        return m.reshape(q.shape[:-1] + (3, 3))
    if _unrolled():
        return torch.stack(quat_to_matrix_components(q.unbind(-1)), dim=-1).unflatten(-1, (3, 3))
    outer = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)  # (..., 16)
    m = (outer @ _constant("mat", q)) / (q * q).sum(-1, keepdim=True)
    return m.unflatten(-1, (3, 3))


def quat_to_matrix_components(q: Sequence[torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """:func:`quat_to_matrix` in component form: the four components ``(w, x, y, z)``, each
    (...,), -> the nine entries of ``R`` row-major, each (...,) (the engine's fused step,
    :mod:`identified.engine.smallmat`)."""
    w, x, y, z = q
    inv = 1.0 / (w * w + x * x + y * y + z * z)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return ((ww + xx - yy - zz) * inv, 2 * (xy - wz) * inv, 2 * (xz + wy) * inv,
            2 * (xy + wz) * inv, (ww - xx + yy - zz) * inv, 2 * (yz - wx) * inv,
            2 * (xz - wy) * inv, 2 * (yz + wx) * inv, (ww - xx - yy + zz) * inv)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternion w-x-y-z (w >= 0) of one rotation matrix (3, 3) -> (4,), Shepperd's method
    (numpy only: the MJCF builder writes body orientations with it)."""
    m = np.asarray(m, dtype=float)
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return out if out[0] >= 0 else -out


def matrix_apply(rot: Array, v: Array) -> Array:
    """``R v`` for (..., 3, 3) and (..., 3) -> (..., 3) (body -> world)."""
    if _np(rot) or _np(v):
        return (np.asarray(rot, dtype=float) @ np.asarray(v, dtype=float)[..., None])[..., 0]
    if _unrolled():
        return (rot * v.unsqueeze(-2)).sum(-1)
    return torch.matmul(rot, v.unsqueeze(-1)).squeeze(-1)


def matrix_apply_transpose(rot: Array, v: Array) -> Array:
    """``Rᵀ v`` for (..., 3, 3) and (..., 3) -> (..., 3) (world -> body)."""
    if _np(rot) or _np(v):
        return (np.asarray(v, dtype=float)[..., None, :] @ np.asarray(rot, dtype=float))[..., 0, :]
    if _unrolled():
        return (rot * v.unsqueeze(-1)).sum(-2)
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
_NP_TABLES = {k: np.array(v) for k, v in _TABLES.items()}
_CACHE: dict[tuple[str, torch.dtype, torch.device], torch.Tensor] = {}


def _constant(name: str, like: torch.Tensor) -> torch.Tensor:
    key = (name, like.dtype, like.device)
    t = _CACHE.get(key)
    if t is None:
        t = _CACHE[key] = torch.tensor(_TABLES[name], dtype=like.dtype, device=like.device)
    return t


def quat_rotate(q: Array, v: Array) -> Array:
    """Rotate a body-frame vector into the world frame, ``R(q) v``: (..., 4), (..., 3) -> (..., 3)."""
    return matrix_apply(quat_to_matrix(q), v)


def quat_rotate_inverse(q: Array, v: Array) -> Array:
    """Rotate a world-frame vector into the body frame, ``R(q)ᵀ v``: (..., 4), (..., 3) -> (..., 3)."""
    return matrix_apply_transpose(quat_to_matrix(q), v)


def quat_exp(theta: Array) -> Array:
    """Unit quaternion of a rotation vector ``θ`` (..., 3) -> (..., 4).

    ``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)``.  For tiny angles (``|θ| < 1e-6``) the Taylor series
    ``cos(a/2) ≈ 1 - a²/8`` and ``sin(a/2)/a ≈ 1/2 - a²/48`` is used behind a
    "double where", so the value and all derivatives stay finite and exact at ``θ = 0``.
    """
    if _np(theta):
        th = np.asarray(theta, dtype=float)
        a2 = np.einsum("...i,...i->...", th, th)
        small = a2 < _SMALL_ANGLE_SQ
        a = np.sqrt(np.where(small, 1.0, a2))
        c = np.where(small, 1.0 - a2 / 8.0, np.cos(0.5 * a))
        s = np.where(small, 0.5 - a2 / 48.0, np.sin(0.5 * a) / a)
        return np.concatenate((c[..., None], s[..., None] * th), axis=-1)
    c, s = _exp_coefficients((theta * theta).sum(-1))
    return torch.cat((c.unsqueeze(-1), s.unsqueeze(-1) * theta), dim=-1)


def _exp_coefficients(a2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``cos(|θ|/2)`` and ``sin(|θ|/2)/|θ|`` from ``|θ|²`` (torch), Taylor series for tiny angles."""
    small = a2 < _SMALL_ANGLE_SQ
    a = torch.sqrt(torch.where(small, torch.ones_like(a2), a2))  # never sqrt(0): finite gradient
    half = 0.5 * a
    c = torch.where(small, 1.0 - a2 / 8.0, torch.cos(half))
    s = torch.where(small, 0.5 - a2 / 48.0, torch.sin(half) / a)
    return c, s


def quat_integrate(q: Array, angvel_body: Array, dt: float | torch.Tensor) -> Array:
    """Rotate ``q`` by a body-frame angular velocity held for ``dt``: ``normalise(q ⊗ exp(dt·w_b))``.

    (..., 4), (..., 3) -> (..., 4).  This is MuJoCo's ``mju_quatIntegrate(q, w_b, dt)`` followed by
    ``mju_normalize4`` (``mj_integratePos`` for a ball or free joint).
    """
    return quat_normalize(quat_multiply(q, quat_exp(angvel_body * dt)))


def quat_integrate_components(q: Sequence[torch.Tensor], angvel_body: Sequence[torch.Tensor],
                              dt: float | torch.Tensor) -> tuple[torch.Tensor, ...]:
    """:func:`quat_integrate` in component form (torch): ``q`` four components, ``angvel_body``
    three, each (...,) -> the four components of ``normalise(q ⊗ exp(dt·w_b))``."""
    theta = tuple(w * dt for w in angvel_body)
    c, s = _exp_coefficients(theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2])
    out = _hamilton(tuple(q), (c, s * theta[0], s * theta[1], s * theta[2]))
    norm = torch.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2] + out[3] * out[3])
    return tuple(x / norm for x in out)
