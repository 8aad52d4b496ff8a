"""``cable_friction``: dry (Coulomb) friction along each cable, smoothed.

A cable running through a guide or a motor's gearbox resists changes of its length with a force
of nearly constant size: tension ``F_j tanh(L̇_j / v_s)`` (positive resists lengthening), with the
smoothing speed ``v_s`` an option (default 0.01 m/s).  Linear in ``F_j`` per cable.
"""

from __future__ import annotations

from typing import Any

import torch

from identified.effects.base import Effect, ParamBlock

__all__ = ["CableFriction"]


class CableFriction(Effect):
    name = "cable_friction"
    description = "dry friction along each cable, tension F tanh(rate / v_s)"
    blocks = (ParamBlock("force", "spring", unit="N"),)

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> CableFriction:
        return cls(topology.n_rods, topology.n_springs, options={"smoothing_speed": 0.01})

    def end_features(self, state: Any, ctx: Any) -> torch.Tensor:
        vs = float(self.options.get("smoothing_speed", 0.01))
        t = torch.tanh(ctx.geometry.rate / vs).unsqueeze(-1) * ctx.geometry.unit  # (..., S, 3)
        return torch.stack((t, -t), dim=-2)
