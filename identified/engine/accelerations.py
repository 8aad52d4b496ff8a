"""Acceleration generation module (paper, Sec. "Acceleration Generation Module", eqs. 3-4).

The spring forces on the end points of each rod are aggregated (the paper's ``f_1``, ``f_2``, the
*aggregate* force on each end when several springs share it) into a force and a world torque about
the rod's centre of mass; gravity ``M g``, the control force and any plug-in effects are added, and
the rod's linear and angular accelerations follow (eq. 3 and its 3D form eq. 4):

* ``F = Σ_e f_e + M g + h f_u + F_fx``,           ``a = F / M``;
* ``τ = Σ_e (R o_e) × f_e + (R r_u) × (h f_u) + τ_fx`` (world frame);
* in the ROD frame with the diagonal inertia ``I = diag(Ixx, Iyy, Izz)``:
  ``w_b = Rᵀ w``, ``τ_b = Rᵀ τ``, ``α_b = I⁻¹ (τ_b - w_b × (I w_b))``.

A rod's state is its body frame (the free joint's frame), which need not be its centre of mass.
With the centre of mass at ``c`` in the rod frame and the full inertia tensor ``J`` about it (rod
frame: the diagonal ``I`` and the products ``(Jxy, Jxz, Jyz)``), the torque ``τ`` about the frame's
origin and the origin's acceleration follow from Newton-Euler about the centre of mass:

* ``τ_c = Rᵀ τ - c × Rᵀ F`` (the torque about the centre of mass, rod frame; gravity has none);
* ``α_b = J⁻¹ (τ_c - w_b × J w_b)``;
* ``a = F / M + g - R (α_b × c + w_b × (w_b × c))`` (the origin's acceleration, world).

With ``c = 0`` and no products this is the diagonal model above, term by term.

The paper's eq. 4 writes ``α = R I⁻¹ Rᵀ τ``; the gyroscopic term ``w_b × (I w_b)`` (Euler's
equations) is added here because it is exact physics and MuJoCo includes it.  ``h`` is the paper's
control force scalar (it scales the applied push ``f_u``, acting at the rod-frame point ``r_u``).

Shapes: ``R`` rods, ``S`` springs, ``...`` leading batch dimensions.  Aggregation is a gather and
a short sum: each rod sums the ends it holds (``SpringGraph.rod_ends``), no scatter.  Every formula
is written once in component form (``*_components``, :mod:`identified.engine.smallmat`); the
tensor-form functions unbind into it and stack back.
"""

from __future__ import annotations

import torch

from identified.engine.forces import SpringGraph, as_graph
from identified.engine.smallmat import Mat, Vec, mat, minverse, mtv, mv, unvec, vadd, vcross, vec, vsub
from identified.topology import Topology

__all__ = ["inertia_matrix", "inertial_wrench", "push_wrench", "push_wrench_components", "rod_accelerations",
           "rod_accelerations_components", "rod_wrench", "rod_wrench_components"]


def rod_wrench(
    graph: SpringGraph | Topology,
    end_forces: torch.Tensor,
    lever: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Aggregate spring-end forces on the rods: force and WORLD torque about each rod's COM.

    ``end_forces`` (..., S, 2, 3), ``lever`` (..., S, 2, 3) world lever arms ``R o_e`` -> force
    (..., R, 3), torque (..., R, 3).  Ends on fixed anchors are ignored.  The formulas are
    :func:`rod_wrench_components`.
    """
    g = as_graph(graph, end_forces)

    def end_major(x: torch.Tensor) -> Vec:  # (..., S, 2, 3) -> components (..., 2S), end-major
        return vec(x.transpose(-3, -2).flatten(-3, -2))

    force, torque = rod_wrench_components(g, end_major(end_forces), end_major(lever))
    return unvec(force), unvec(torque)


def rod_wrench_components(g: SpringGraph, end_forces: Vec, lever: Vec) -> tuple[Vec, Vec]:
    """Component form of :func:`rod_wrench`: forces and levers of the spring ends, components
    (..., 2S) end-major -> force and WORLD torque per rod, components (..., R).  Each rod sums the
    ends it holds (``graph.rod_ends``: a gather and a short sum, no scatter)."""
    torque = vcross(lever, end_forces)
    R, K = g.rod_ends.shape

    def per_rod(x: torch.Tensor) -> torch.Tensor:
        return (x.index_select(-1, g.rod_ends.reshape(-1)).unflatten(-1, (R, K)) * g.rod_ends_weight).sum(-1)

    return tuple(per_rod(x) for x in end_forces), tuple(per_rod(x) for x in torque)


def push_wrench(
    rot: torch.Tensor,
    push_force: torch.Tensor,
    push_point: torch.Tensor | None = None,
    control_scale: torch.Tensor | float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The control force ``h f_u`` at the rod-frame point ``r_u``: force and WORLD torque.

    ``rot`` (..., R, 3, 3); ``push_force`` (..., R, 3) world; ``push_point`` (..., R, 3) in the rod
    frame, ``None`` = at the centre of mass; ``control_scale`` ``h``: scalar or (...) -> force
    ``h f_u`` (..., R, 3), torque ``(R r_u) × (h f_u)`` (..., R, 3).
    """
    h = torch.as_tensor(control_scale, dtype=push_force.dtype, device=push_force.device)
    force, torque = push_wrench_components(mat(rot), vec(push_force), None if push_point is None else vec(push_point),
                                           h.unsqueeze(-1))
    force_t = unvec(force)
    return force_t, torch.zeros_like(force_t) if torque is None else unvec(torque)


def inertial_wrench(mass: torch.Tensor, inertia: torch.Tensor, gravity: torch.Tensor, lin_acc: torch.Tensor,
                    ang_acc_body: torch.Tensor, angvel_body: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eqs. 3-4 read backwards: the wrench every force but gravity must add for the given motion,
    ``M (a - g)`` (..., R, 3) world and ``I α_b + w_b × I w_b`` (..., R, 3) ROD frame (shapes as
    :func:`rod_accelerations`).  The residual-stage fit, the effect search's one-step error and
    ``diagnose`` compare a model's forces with it."""
    return mass.unsqueeze(-1) * (lin_acc - gravity), inertia * ang_acc_body + torch.cross(
        angvel_body, inertia * angvel_body, dim=-1)


def rod_accelerations(
    force: torch.Tensor,
    torque: torch.Tensor,
    rot: torch.Tensor,
    angvel_body: torch.Tensor,
    mass: torch.Tensor,
    inertia: torch.Tensor,
    gravity: torch.Tensor,
    com: torch.Tensor | None = None,
    products: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eqs. 3-4: linear acceleration (world) and angular acceleration (ROD frame) of every rod.

    ``force`` (..., R, 3) and ``torque`` (..., R, 3): everything but gravity, world frame, the
    torque about the rod frame's origin; ``rot`` (..., R, 3, 3); ``angvel_body`` (..., R, 3) =
    ``Rᵀ w``; ``mass`` (R,) or (..., R); ``inertia`` (R, 3) or (..., R, 3) the rod-frame diagonal
    of the inertia about the centre of mass; ``gravity`` (3,) or (..., 3); ``com`` (R, 3) or
    (..., R, 3) the centre of mass in the rod frame and ``products`` (R, 3) or (..., R, 3) the
    inertia's off-diagonal entries ``(Jxy, Jxz, Jyz)`` (rod frame), ``None``: 0 (module docstring).
    Returns the origin's ``a`` (..., R, 3) and ``α_b`` (..., R, 3); the formulas are
    :func:`rod_accelerations_components`.
    """
    lin, ang = rod_accelerations_components(vec(force), vec(torque), mat(rot), vec(angvel_body), mass,
                                            vec(inertia), tuple(gravity.unsqueeze(-2).unbind(-1)),
                                            None if com is None else vec(com),
                                            None if products is None else vec(products))
    return unvec(lin), unvec(ang)


def inertia_matrix(inertia: Vec, products: Vec | None) -> Mat:
    """The symmetric inertia tensor (rod frame) from its diagonal and products ``(Jxy, Jxz, Jyz)``
    (``None``: a diagonal tensor), component form."""
    ixx, iyy, izz = inertia
    if products is None:
        z = torch.zeros_like(ixx)
        return (ixx, z, z, z, iyy, z, z, z, izz)
    jxy, jxz, jyz = products
    return (ixx, jxy, jxz, jxy, iyy, jyz, jxz, jyz, izz)


def rod_accelerations_components(force: Vec, torque: Vec, rot: Mat, angvel_body: Vec, mass: torch.Tensor,
                                 inertia: Vec, gravity: Vec, com: Vec | None = None,
                                 products: Vec | None = None) -> tuple[Vec, Vec]:
    """Component form of :func:`rod_accelerations`: every argument's components (..., R) (or
    broadcastable: ``gravity`` (..., 1), ``mass``, ``inertia``, ``com`` and ``products`` (R,)).
    Without ``com`` and ``products`` the diagonal model's short form (the same numbers)."""
    lin = tuple((f + mass * g) / mass for f, g in zip(force, gravity))
    tau_b = mtv(rot, torque)
    if com is None and products is None:
        gyro = vcross(angvel_body, tuple(i * w for i, w in zip(inertia, angvel_body)))
        return lin, tuple((t - gy) / i for t, gy, i in zip(tau_b, gyro, inertia))
    w = angvel_body
    if com is not None:  # the torque about the centre of mass
        tau_b = vsub(tau_b, vcross(com, mtv(rot, force)))
    J = inertia_matrix(inertia, products)
    alpha = mv(minverse(J), vsub(tau_b, vcross(w, mv(J, w))))
    if com is not None:  # the origin's acceleration from the centre of mass's
        lin = vsub(lin, mv(rot, vadd(vcross(alpha, com), vcross(w, vcross(w, com)))))
    return lin, alpha


def push_wrench_components(rot: Mat, push_force: Vec, push_point: Vec | None,
                           control_scale: torch.Tensor) -> tuple[Vec, Vec | None]:
    """Component form of :func:`push_wrench` (``control_scale`` a scalar tensor); the torque is
    ``None`` for a push at the centre of mass."""
    force = tuple(control_scale * f for f in push_force)
    if push_point is None:
        return force, None
    return force, vcross(mv(rot, push_point), force)
