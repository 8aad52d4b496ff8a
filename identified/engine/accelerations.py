"""Acceleration generation module (paper, Sec. "Acceleration Generation Module", eqs. 3-4).

The spring forces on the end points of each rod are aggregated (the paper's ``f_1``, ``f_2``, the
*aggregate* force on each end when several springs share it) into a force and a world torque about
the rod's centre of mass; gravity ``M g``, the control force and any plug-in effects are added, and
the rod's linear and angular accelerations follow (eq. 3 and its 3D form eq. 4):

* ``F = Σ_e f_e + M g + h f_u + F_fx``,           ``a = F / M``;
* ``τ = Σ_e (R o_e) × f_e + (R r_u) × (h f_u) + τ_fx`` (world frame);
* in the ROD frame with the diagonal inertia ``I = diag(Ixx, Iyy, Izz)``:
  ``w_b = Rᵀ w``, ``τ_b = Rᵀ τ``, ``α_b = I⁻¹ (τ_b - w_b × (I w_b))``.

The paper's eq. 4 writes ``α = R I⁻¹ Rᵀ τ``; the gyroscopic term ``w_b × (I w_b)`` (Euler's
equations) is added here because it is exact physics and MuJoCo includes it.  ``h`` is the paper's
control force scalar (it scales the applied push ``f_u``, acting at the rod-frame point ``r_u``).

Shapes: ``R`` rods, ``S`` springs, ``...`` leading batch dimensions.  Aggregation uses
``index_add`` over index tensors from :class:`~identified.engine.forces.SpringGraph`.
"""

from __future__ import annotations

import torch

from identified.engine.forces import SpringGraph, as_graph
from identified.rotation import matrix_apply, matrix_apply_transpose
from identified.topology import Topology

__all__ = ["push_wrench", "rod_accelerations", "rod_wrench"]


def rod_wrench(
    graph: SpringGraph | Topology,
    end_forces: torch.Tensor,
    lever: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Aggregate spring-end forces on the rods: force and WORLD torque about each rod's COM.

    ``end_forces`` (..., S, 2, 3), ``lever`` (..., S, 2, 3) world lever arms ``R o_e`` -> force
    (..., R, 3), torque (..., R, 3).  Ends on fixed anchors are ignored.
    """
    g = as_graph(graph, end_forces)
    batch = end_forces.shape[:-3]
    f = end_forces.reshape(batch + (-1, 3)).index_select(-2, g.end_index)  # (..., E, 3)
    r = lever.reshape(batch + (-1, 3)).index_select(-2, g.end_index)
    tau = torch.cross(r, f, dim=-1)
    zeros = end_forces.new_zeros(batch + (g.n_rods, 3))
    force = zeros.index_add(-2, g.end_rod, f)
    torque = zeros.index_add(-2, g.end_rod, tau)
    return force, torque


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
    force = h.unsqueeze(-1).unsqueeze(-1) * push_force
    if push_point is None:
        return force, torch.zeros_like(force)
    return force, torch.cross(matrix_apply(rot, push_point), force, dim=-1)


def rod_accelerations(
    force: torch.Tensor,
    torque: torch.Tensor,
    rot: torch.Tensor,
    angvel_body: torch.Tensor,
    mass: torch.Tensor,
    inertia: torch.Tensor,
    gravity: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eqs. 3-4: linear acceleration (world) and angular acceleration (ROD frame) of every rod.

    ``force`` (..., R, 3) and ``torque`` (..., R, 3): everything but gravity, world frame; ``rot``
    (..., R, 3, 3); ``angvel_body`` (..., R, 3) = ``Rᵀ w``; ``mass`` (R,) or (..., R);
    ``inertia`` (R, 3) or (..., R, 3) rod-frame diagonal; ``gravity`` (3,) or (..., 3).
    Returns ``a = (F + M g) / M`` (..., R, 3) and ``α_b = I⁻¹ (Rᵀ τ - w_b × I w_b)`` (..., R, 3).
    """
    m = mass.unsqueeze(-1)
    lin_acc = (force + m * gravity.unsqueeze(-2)) / m
    tau_b = matrix_apply_transpose(rot, torque)
    gyro = torch.cross(angvel_body, inertia * angvel_body, dim=-1)
    ang_acc_body = (tau_b - gyro) / inertia
    return lin_acc, ang_acc_body
