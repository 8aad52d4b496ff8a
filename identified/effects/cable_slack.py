"""``cable_slack``: a spring declared two-sided (push-pull) that only pulls.

The true tension is ``K max(s, 0)``; the declared spring gives ``K s``.  The correction is the
tension ``κ min(s, 0)`` (stretch ``s = L - L0``): ``κ = -K`` for a cable that goes slack, ``0`` for a
true two-sided spring.  Linear in ``κ`` per spring; springs already declared pull-only are pinned
at 0 (their stretch is already dead-banded).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from identified.effects.base import Effect, ParamBlock

__all__ = ["CableSlack"]


class CableSlack(Effect):
    name = "cable_slack"
    description = "compression correction kappa min(L - L0, 0): kappa = -K for a spring that only pulls"
    blocks = (ParamBlock("kappa", "spring", signed=True, unit="N/m"),)
    reads_rest_length = True

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> CableSlack:
        return cls(topology.n_rods, topology.n_springs,
                   options={"pull_only": np.asarray(topology.pull_only, dtype=bool).tolist()})

    def pinned(self) -> np.ndarray:
        """(P,) bool: parameters held at 0 (springs declared pull-only already)."""
        return np.asarray(self.options.get("pull_only", [False] * self.n_springs), dtype=bool)

    def end_features(self, state: Any, ctx: Any) -> torch.Tensor:
        comp = (ctx.geometry.length - ctx.rest_length).clamp_max(0.0)
        pinned = torch.as_tensor(self.pinned(), device=comp.device)
        t = torch.where(pinned, 0.0, comp).unsqueeze(-1) * ctx.geometry.unit
        return torch.stack((t, -t), dim=-2)
