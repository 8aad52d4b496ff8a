"""Integration module (paper, Sec. "Integration Module and Method Implementation").

Semi-implicit (symplectic) Euler, exactly as MuJoCo's ``mj_Euler`` integrates a free joint
(``qvel += dt·qacc``, then ``mj_integratePos`` with the NEW velocity):

* ``v⁺ = v + dt a``,            ``w_b⁺ = w_b + dt α_b``            (velocity first),
* ``p⁺ = p + dt v⁺``,           ``q⁺ = normalise(q ⊗ exp(dt w_b⁺))``  (then position),

where ``exp`` maps the body-frame rotation vector ``θ = dt w_b⁺`` to the quaternion
``(cos(|θ|/2), sin(|θ|/2) θ/|θ|)`` (MuJoCo ``mju_quatIntegrate``, then ``mju_normalize4``).  The
returned angular velocity is in the WORLD frame, ``w⁺ = R(q⁺) w_b⁺``, as the dataset stores it.

Shapes: ``R`` rods, ``...`` leading batch dimensions.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from identified.rotation import matrix_apply, quat_integrate, quat_to_matrix

__all__ = ["RodState", "semi_implicit_euler"]


class RodState(NamedTuple):
    """The state of every rod: ``pos`` (..., R, 3) COM world, ``quat`` (..., R, 4) w-x-y-z,
    ``vel`` (..., R, 3) world, ``angvel`` (..., R, 3) WORLD frame."""

    pos: torch.Tensor
    quat: torch.Tensor
    vel: torch.Tensor
    angvel: torch.Tensor


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
    vel_next = vel + dt * lin_acc
    w_next = angvel_body + dt * ang_acc_body
    pos_next = pos + dt * vel_next
    quat_next = quat_integrate(quat, w_next, dt)
    angvel_next = matrix_apply(quat_to_matrix(quat_next), w_next)
    return RodState(pos_next, quat_next, vel_next, angvel_next)
