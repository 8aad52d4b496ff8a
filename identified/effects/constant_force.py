"""``constant_force``: a constant force on every rod (world frame), one vector per rod.

A uniform force field the spring-rod model does not declare: a gravity that differs from the
dataset's (``M_i Δg`` on rod i), a tilted floor's pull, a steady wind.  Linear and signed.
"""

from __future__ import annotations

from typing import Any

import torch

from identified.effects.base import Effect, ParamBlock

__all__ = ["ConstantForce"]


class ConstantForce(Effect):
    name = "constant_force"
    description = "a constant world-frame force on each rod (gravity mismatch, tilt, wind)"
    blocks = (ParamBlock("force", "rod", width=3, signed=True, unit="N"),)

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> ConstantForce:
        return cls(topology.n_rods, topology.n_springs)

    def features(self, state: Any, ctx: Any) -> torch.Tensor:
        eye = torch.eye(3, dtype=state.pos.dtype, device=state.pos.device)
        force = eye.expand(state.pos.shape[:-1] + (3, 3))
        return force, torch.zeros_like(force)
