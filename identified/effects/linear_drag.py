"""``linear_drag``: viscous drag on every rod, ``f = -b_lin v``, ``τ = -b_rot ω`` (world frame).

The low-Reynolds limit of fluid drag (MuJoCo's ``viscosity``: ``-3πμd v`` and ``-πμd³ ω`` on the
equivalent sphere) and the damping of a free joint.  Linear in ``(b_lin, b_rot)`` per rod.
"""

from __future__ import annotations

from typing import Any

import torch

from identified.effects.base import Effect, ParamBlock

__all__ = ["LinearDrag"]


class LinearDrag(Effect):
    name = "linear_drag"
    description = "viscous drag per rod: force -b_lin v, torque -b_rot w"
    blocks = (ParamBlock("b_lin", "rod", unit="N s/m"), ParamBlock("b_rot", "rod", unit="N m s"))

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> LinearDrag:
        return cls(topology.n_rods, topology.n_springs)

    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        zero = torch.zeros_like(state.vel)
        force = torch.stack((-state.vel, zero), dim=-2)  # (..., R, 2, 3)
        torque = torch.stack((zero, -state.angvel), dim=-2)
        return force, torque
