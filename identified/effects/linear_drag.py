"""``linear_drag``: viscous drag on every rod, ``f = -b_lin v``, ``τ = -b_rot ω`` (world frame).

The low-Reynolds limit of fluid drag (MuJoCo's ``viscosity``: ``-3πμd v`` and ``-πμd³ ω`` on the
equivalent sphere) and the damping of a free joint.  Linear in ``(b_lin, b_rot)`` per rod.

Option ``implicit`` (default False): the integrator takes the drag implicitly, as MuJoCo's Euler
does with joint damping, ``(M + dt b) a = F - b v``: the force acts on the step's *end* velocity
``v + dt a`` (in the fit: the recorded one), and the engine scales the accelerations by
``M / (M + dt b)`` (:meth:`implicit_damping`, the drag's velocity derivative).  The rotational
drag then acts in the rod frame (MuJoCo's free-joint angular velocity is the body's).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from identified.effects.base import Effect, ParamBlock
from identified.rotation import matrix_apply

__all__ = ["LinearDrag"]


class LinearDrag(Effect):
    name = "linear_drag"
    description = "viscous drag per rod: force -b_lin v, torque -b_rot w"
    blocks = (ParamBlock("b_lin", "rod", unit="N s/m"), ParamBlock("b_rot", "rod", unit="N m s"))
    #: linear_drag:implicit, as MuJoCo's Euler takes joint damping
    variants: ClassVar[dict[str, dict[str, Any]]] = {"implicit": {"implicit": True}}

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> LinearDrag:
        return cls(topology.n_rods, topology.n_springs, options={"implicit": False})

    @property
    def implicit(self) -> bool:
        return bool(self.options.get("implicit", False))

    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        vel, angvel = state.vel, state.angvel
        if self.implicit and ctx.recorded_lin_acc is not None:  # the fit: the recorded end velocity
            vel = vel + ctx.dt * ctx.recorded_lin_acc
            angvel = matrix_apply(ctx.rot, ctx.angvel_body + ctx.dt * ctx.recorded_ang_acc_body)
        zero = torch.zeros_like(vel)
        force = torch.stack((-vel, zero), dim=-2)  # (..., R, 2, 3)
        torque = torch.stack((zero, -angvel), dim=-2)
        return force, torque

    def implicit_damping(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(b_lin (R,), b_rot (R,))`` when the integrator takes this drag implicitly, else None."""
        if not self.implicit:
            return None
        th = self.theta(like).view(self.n_rods, 2)
        return th[:, 0], th[:, 1]
