"""``quadratic_drag``: fluid drag quadratic in speed, per axis of the rod frame.

A rod is not a sphere: its drag along its axis is far weaker than across it.  In the rod frame,
``f_k = -d_k |v_k| v_k`` and ``τ_k = -e_k |ω_k| ω_k`` for k = x, y, z (MuJoCo's inertia-box fluid
model with ``density``: ``d_k = ρ A_k / 2`` with ``A_k`` the box's face area across axis k), then
rotated to the world.  Linear in the six coefficients per rod.
"""

from __future__ import annotations

from typing import Any

import torch

from identified.effects.base import Effect, ParamBlock
from identified.rotation import matrix_apply_transpose

__all__ = ["QuadraticDrag"]


class QuadraticDrag(Effect):
    name = "quadratic_drag"
    description = "drag quadratic in speed per rod-frame axis: f_k = -d_k |v_k| v_k, tau_k = -e_k |w_k| w_k"
    blocks = (ParamBlock("d", "rod", width=3, unit="kg/m"), ParamBlock("e", "rod", width=3, unit="kg m^2"))

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> QuadraticDrag:
        return cls(topology.n_rods, topology.n_springs)

    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        rot = ctx.rot  # (..., R, 3, 3); column k is the rod's axis k in the world
        v_b = matrix_apply_transpose(rot, state.vel)
        w_b = ctx.angvel_body
        axes = rot.transpose(-1, -2)  # (..., R, 3 axes, 3)
        f = -(v_b.abs() * v_b).unsqueeze(-1) * axes  # (..., R, 3, 3): force per unit d_k
        t = -(w_b.abs() * w_b).unsqueeze(-1) * axes
        zero = torch.zeros_like(f)
        return torch.cat((f, zero), dim=-2), torch.cat((zero, t), dim=-2)
