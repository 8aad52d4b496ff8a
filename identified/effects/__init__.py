"""The effect library: forces the spring-rod model lacks, one file each (:mod:`.base`).

========================  ===========================================================
name                      what it adds
========================  ===========================================================
``ground_contact``        rod capsules on a ground plane (normal force, friction)
``linear_drag``           viscous drag per rod (translation and rotation)
``quadratic_drag``        drag quadratic in speed per rod-frame axis
``cable_friction``        dry friction along each cable: it sticks, slips at F
``cable_slack``           a spring declared two-sided that only pulls
``constant_force``        a constant force per rod (gravity mismatch, tilt, wind)
``actuator_lag``          (not implemented: the dataset records the actual rest lengths)
========================  ===========================================================
"""

from __future__ import annotations

from typing import Any

from identified.effects.base import Effect, ParamBlock
from identified.effects.cable_friction import CableFriction
from identified.effects.cable_slack import CableSlack
from identified.effects.constant_force import ConstantForce
from identified.effects.ground_contact import GeometryError, GroundContact, read_contact_geometry
from identified.effects.linear_drag import LinearDrag
from identified.effects.quadratic_drag import QuadraticDrag

__all__ = [
    "EFFECTS",
    "Effect",
    "GeometryError",
    "ParamBlock",
    "effect_from_json",
    "effects_from_model",
    "make_effect",
    "read_contact_geometry",
]

#: every effect by its JSON name
EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (GroundContact, LinearDrag, QuadraticDrag, CableFriction, CableSlack, ConstantForce)
}
#: names the model file may use (DESIGN.md), in this order; actuator_lag is reserved
KNOWN_NAMES = tuple(EFFECTS) + ("actuator_lag",)


def make_effect(name: str, topology: Any, mjcf: str | None = None) -> Effect:
    """An unfitted effect by name for a system (ValueError naming the known ones otherwise)."""
    if name == "actuator_lag":
        raise ValueError("effect 'actuator_lag' is not available: the dataset records the cables' actual "
                         "rest lengths, so a lag of the motors is already in the data")
    if name not in EFFECTS:
        raise ValueError(f"unknown effect '{name}' (known: {', '.join(EFFECTS)})")
    return EFFECTS[name].for_system(topology, mjcf)


def effect_from_json(obj: dict[str, Any], n_rods: int, n_springs: int) -> Effect:
    """A fitted effect from its model-file entry ``{name, parameters, stderr, options}``."""
    name = obj.get("name")
    if name not in EFFECTS:
        raise ValueError(f"unknown effect '{name}' (known: {', '.join(EFFECTS)})")
    cls = EFFECTS[name]
    eff = cls(n_rods, n_springs, options=obj.get("options") or {})
    eff.values = eff.flatten(obj.get("parameters") or {})
    se = obj.get("stderr")
    if se:
        try:
            eff.stderr = _flatten_loose(eff, se)
        except (ValueError, KeyError, TypeError):
            eff.stderr = None
    return eff


def _flatten_loose(eff: Effect, obj: dict[str, Any]):
    import numpy as np

    parts = []
    for b in eff.blocks:
        v = np.asarray(obj[b.name], dtype=float)
        parts.append(v.reshape(-1, b.width) if eff.kind != "global" else v.reshape(1, b.width))
    return np.concatenate(parts, axis=1).reshape(-1)


def effects_from_model(model: Any) -> list[Effect]:
    """The fitted effects an :class:`~identified.model.IdentifiedModel` lists, ready for the engine."""
    topo = model.topology
    return [effect_from_json(e, topo.n_rods, topo.n_springs) for e in model.effects]
