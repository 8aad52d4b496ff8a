"""Integration module (paper, Sec. "Integration Module and Method Implementation").

Semi-implicit (symplectic) Euler, exactly as MuJoCo's ``mj_Euler`` integrates a free joint
(``qvel += dt·qacc``, then ``mj_integratePos`` with the NEW velocity):

* ``v⁺ = v + dt a``,            ``w_b⁺ = w_b + dt α_b``            (velocity first),
* ``p⁺ = p + dt v⁺``,           ``q⁺ = normalise(q ⊗ exp(dt w_b⁺))``  (then position),

where ``exp`` maps the body-frame rotation vector ``θ = dt w_b⁺`` to the quaternion
``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)`` (MuJoCo ``mju_quatIntegrate``, then ``mju_normalize4``).  The
returned angular velocity is in the WORLD frame, ``w⁺ = R(q⁺) w_b⁺``, as the dataset stores it.

MuJoCo's ``implicit`` and ``implicitfast`` integrators (``mj_implicit``) step the same way but take
the velocity update from ``(M - dt D) qacc = f`` instead of ``M qacc = f``, where ``D`` is the
velocity derivative of the smooth forces.  For rods on free joints MuJoCo keeps only each rod's own
6x6 block of ``D`` (its sparsity is tree-local, ``nD = 36 R``): the damping of every spring end on
the rod, ``-c J_eᵀ J_e``, and the derivative of the gyroscopic term (MuJoCo 4.0 adds it for free
bodies in both integrators).  With the rod's generalised acceleration ``qacc = (a, α_b)`` (world
linear, rod-frame angular) and ``M_b = diag(M, M, M, Ixx, Iyy, Izz)``:

* ``(M_b + dt Σ_e c_e J_eᵀ J_e + dt G_b) qacc = M_b qacc_explicit``,
* ``J_e = s_e (u, Rᵀ(r_e × u))`` the rate of the spring's length per unit velocity of this rod
  (``s_e = -1`` for end 0, ``+1`` for end 1), ``G_b α = w_b × (I α) + α × (I w_b)``.

Equivalently each end feels the tension ``K s + c (L̇ + dt ρ_e)`` with ``ρ_e = J_e qacc`` of its own
rod only, and the rotation gains ``dt G_b α``: both linear in the parameters, which is what lets the
regression identify an implicit plant exactly (:mod:`identified.fit.features`).  Verified against
MuJoCo 4.0's ``mj_implicit`` to ~1e-15 (tests/test_engine.py).

MuJoCo's ``RK4`` (``mj_RungeKutta`` with N = 4) evaluates the accelerations at four stage states
``X_i = X_0 ⊕ dt Σ_j A_ij (v_j, acc_j)`` and advances ``X_0 ⊕ dt Σ_j B_j (v_j, acc_j)``, where
``⊕`` integrates positions with the velocity given (``mj_integratePos``) and every velocity —
the angular ones included — is summed in MuJoCo's generalised coordinates (world linear,
rod-frame angular), as :func:`runge_kutta4` does.

Shapes: ``R`` rods, ``S`` springs, ``...`` leading batch dimensions.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from identified.engine.forces import SpringGraph, as_graph
from identified.engine.smallmat import Vec, inverse3, mv, unvec, vec
from identified.rotation import (
    matrix_apply,
    matrix_apply_transpose,
    quat_integrate,
    quat_integrate_components,
    quat_to_matrix,
    quat_to_matrix_components,
)
from identified.state import RodState  # the one state type (re-exported here for the engine)

__all__ = [
    "INTEGRATORS",
    "RodState",
    "gyroscopic_derivative",
    "implicit_accelerations",
    "implicit_rate_correction",
    "runge_kutta4",
    "semi_implicit_euler",
    "semi_implicit_euler_components",
    "spring_rate_rows",
]

INTEGRATORS = ("euler", "implicit", "rk4")


def semi_implicit_euler(
    pos: torch.Tensor,
    quat: torch.Tensor,
    vel: torch.Tensor,
    angvel_body: torch.Tensor,
    lin_acc: torch.Tensor,
    ang_acc_body: torch.Tensor,
    dt: float | torch.Tensor,
) -> RodState:
    """One semi-implicit Euler step of every rod.

    ``pos``, ``vel``, ``lin_acc`` (..., R, 3) world; ``quat`` (..., R, 4); ``angvel_body``,
    ``ang_acc_body`` (..., R, 3) ROD frame; ``dt`` s.  Returns the new :class:`RodState` with the
    angular velocity in the WORLD frame.
    """
    out = semi_implicit_euler_components(vec(pos), tuple(quat.unbind(-1)), vec(vel), vec(angvel_body),
                                         vec(lin_acc), vec(ang_acc_body), dt)
    return RodState(*(unvec(x) for x in out))


def semi_implicit_euler_components(pos: Vec, quat: tuple, vel: Vec, angvel_body: Vec, lin_acc: Vec,
                                   ang_acc_body: Vec, dt: float | torch.Tensor) -> tuple[Vec, tuple, Vec, Vec]:
    """Component form of :func:`semi_implicit_euler`: every argument's components (..., R);
    returns the components of the new position, quaternion, velocity and WORLD angular velocity."""
    vel_next = tuple(v + dt * a for v, a in zip(vel, lin_acc))
    w_next = tuple(w + dt * a for w, a in zip(angvel_body, ang_acc_body))
    pos_next = tuple(p + dt * v for p, v in zip(pos, vel_next))
    quat_next = quat_integrate_components(quat, w_next, dt)
    return pos_next, quat_next, vel_next, mv(quat_to_matrix_components(quat_next), w_next)


Accelerations = Callable[[RodState, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]

_RK4_A = ((0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
_RK4_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)


def runge_kutta4(accelerations: Accelerations, state: RodState, angvel_body: torch.Tensor, dt: float) -> RodState:
    """One step of MuJoCo's RK4 (``mj_RungeKutta``, N = 4) for every rod.

    ``accelerations(stage_state, stage_angvel_body) -> (a, α_b)`` evaluates the dynamics at a
    stage (its state with WORLD angular velocity, and the same in the rod frame); ``state`` and
    ``angvel_body`` (..., R, 3) are the start.  Returns the new :class:`RodState`.
    """
    pos0, quat0, vel0, _ = state
    vels, ws = [vel0], [angvel_body]
    accs = [accelerations(state, angvel_body)]
    for coeffs in _RK4_A:
        dv = sum(c * v for c, v in zip(coeffs, vels))
        dw = sum(c * w for c, w in zip(coeffs, ws))
        da = sum(c * a for c, (a, _) in zip(coeffs, accs))
        dal = sum(c * al for c, (_, al) in zip(coeffs, accs))
        quat = quat_integrate(quat0, dw, dt)
        vel, w_b = vel0 + dt * da, angvel_body + dt * dal
        stage = RodState(pos0 + dt * dv, quat, vel, matrix_apply(quat_to_matrix(quat), w_b))
        vels.append(vel)
        ws.append(w_b)
        accs.append(accelerations(stage, w_b))
    dv = sum(b * v for b, v in zip(_RK4_B, vels))
    dw = sum(b * w for b, w in zip(_RK4_B, ws))
    vel_next = vel0 + dt * sum(b * a for b, (a, _) in zip(_RK4_B, accs))
    w_next = angvel_body + dt * sum(b * al for b, (_, al) in zip(_RK4_B, accs))
    quat_next = quat_integrate(quat0, dw, dt)
    return RodState(pos0 + dt * dv, quat_next, vel_next, matrix_apply(quat_to_matrix(quat_next), w_next))


def spring_rate_rows(
    graph: SpringGraph, unit: torch.Tensor, lever: torch.Tensor, rot: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``J_e``: how fast each spring's length changes per unit generalised velocity of the rod at
    end ``e`` — (..., S, 2, 6), world linear then rod-frame angular part — and the weight of each
    end in that rod's implicit matrix, (S, 2).

    ``unit`` (..., S, 3), ``lever`` (..., S, 2, 3) world, ``rot`` (..., R, 3, 3).  Anchored ends
    get zero rows; a spring with both ends on one rod gets the summed row at both ends, each with
    weight 1/2 (so the rod counts it once).
    """
    g = as_graph(graph, unit)
    sign = unit.new_tensor([-1.0, 1.0]).view(2, 1)
    u = sign * unit.unsqueeze(-2)  # (..., S, 2, 3)
    rot_e = rot.index_select(-3, g.endpoint_rods.reshape(-1)).reshape(*u.shape, 3)
    ang = matrix_apply_transpose(rot_e, torch.cross(lever, u, dim=-1))
    rows = torch.where(g.on_rod.unsqueeze(-1), torch.cat([u, ang], dim=-1), 0.0)
    same = g.on_rod.all(-1) & (g.endpoint_rods[:, 0] == g.endpoint_rods[:, 1])  # (S,)
    if bool(same.any()):
        both = rows.sum(-2, keepdim=True).expand_as(rows)
        rows = torch.where(same.view(-1, 1, 1), both, rows)
    weight = torch.where(same.unsqueeze(-1), 0.5, 1.0).to(unit.dtype) * g.on_rod.to(unit.dtype)
    return rows, weight


def implicit_rate_correction(
    graph: SpringGraph, rows: torch.Tensor, lin_acc: torch.Tensor, ang_acc_body: torch.Tensor, dt: float
) -> torch.Tensor:
    """``dt ρ_e = dt J_e qacc`` of every spring end (..., S, 2): the implicit step's addition to
    the stretch rate that the damper of end ``e`` sees (``qacc`` of the end's own rod only)."""
    g = as_graph(graph, rows)
    qacc = torch.cat([lin_acc, ang_acc_body], dim=-1)  # (..., R, 6)
    q_e = qacc.index_select(-2, g.endpoint_rods.reshape(-1)).reshape(rows.shape)
    return dt * (rows * q_e).sum(-1)


def gyroscopic_derivative(angvel_body: torch.Tensor, ang_acc_body: torch.Tensor, inertia: torch.Tensor) -> torch.Tensor:
    """``G α = w_b × (I α) + α × (I w_b)``: the derivative of the gyroscopic term ``w_b × I w_b``
    with respect to ``w_b``, applied to ``α``; all (..., R, 3) rod frame, ``inertia`` diagonal."""
    return torch.cross(angvel_body, inertia * ang_acc_body, dim=-1) + torch.cross(
        ang_acc_body, inertia * angvel_body, dim=-1
    )


def implicit_accelerations(
    graph: SpringGraph,
    unit: torch.Tensor,
    lever: torch.Tensor,
    rot: torch.Tensor,
    angvel_body: torch.Tensor,
    lin_acc: torch.Tensor,
    ang_acc_body: torch.Tensor,
    mass: torch.Tensor,
    inertia: torch.Tensor,
    damping: torch.Tensor,
    dt: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The accelerations of MuJoCo's implicit integrators from the explicit ones (module docstring).

    Solves ``(M_b + dt Σ_e c_e J_eᵀ J_e + dt G_b) qacc = M_b qacc_explicit`` rod by rod (a batched
    6x6 solve).  ``unit`` (..., S, 3), ``lever`` (..., S, 2, 3), ``rot`` (..., R, 3, 3),
    ``angvel_body``, ``lin_acc``, ``ang_acc_body`` (..., R, 3), ``mass`` (..., R), ``inertia``
    (..., R, 3), ``damping`` (..., S).  Returns ``(a, α_b)``, (..., R, 3) each.
    """
    g = as_graph(graph, unit)
    rows, weight = spring_rate_rows(g, unit, lever, rot)
    scale = (dt * damping).unsqueeze(-1) * weight  # (..., S, 2)
    outer = scale[..., None, None] * rows.unsqueeze(-1) * rows.unsqueeze(-2)  # (..., S, 2, 6, 6)
    batch = outer.shape[:-4]
    flat = outer.reshape(batch + (-1, 36)).index_select(-2, g.end_index)
    A = outer.new_zeros(batch + (g.n_rods, 36)).index_add(-2, g.end_rod, flat).reshape(batch + (g.n_rods, 6, 6))
    eye = torch.eye(3, dtype=unit.dtype, device=unit.device)
    w, basis, inert = torch.broadcast_tensors(angvel_body.unsqueeze(-2), eye, inertia.unsqueeze(-2))
    gyro = gyroscopic_derivative(w, basis, inert)  # (..., R, 3, 3): row k is G e_k
    m = mass.unsqueeze(-1)
    diag = torch.cat([m.expand_as(lin_acc), inertia.expand_as(ang_acc_body)], dim=-1)  # (..., R, 6)
    A = A + torch.diag_embed(diag) + torch.nn.functional.pad(dt * gyro.transpose(-1, -2), (3, 0, 3, 0))
    rhs = diag * torch.cat([lin_acc, ang_acc_body], dim=-1)
    return _solve_blocks(A, rhs)


def _solve_blocks(A: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve (..., 6, 6) ``A x = b`` by 3x3 blocks (Schur complement of the translational block).

    Elementwise torch work only: for the small batches of a single environment this is ~100x
    faster than a batched LAPACK call, whose threading overhead dominates 6x6 systems.  Returns
    ``x[..., :3]``, ``x[..., 3:]``.
    """
    P, Q = A[..., :3, :3], A[..., :3, 3:]
    U, W = A[..., 3:, :3], A[..., 3:, 3:]
    bl, ba = b[..., :3].unsqueeze(-1), b[..., 3:].unsqueeze(-1)
    Pinv = inverse3(P)
    UPinv = U @ Pinv
    xa = inverse3(W - UPinv @ Q) @ (ba - UPinv @ bl)
    xl = Pinv @ (bl - Q @ xa)
    return xl.squeeze(-1), xa.squeeze(-1)
