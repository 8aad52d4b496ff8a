"""The effect library: forces the spring-rod model lacks, one file per effect on one base class
(:mod:`.base`: its law, its regression columns, its JSON, its fit strategy), and one line each in
:data:`LIBRARY`.

Everything else reads the library from here: the names a model file may hold, the candidates of
the fit's effect search (:func:`search_labels`), the command line's help, the documentation's
table (``scripts/architecture.py``). A plug-in effect is one more class given to
:func:`register_effect`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from identified.effects.base import Effect, ParamBlock
from identified.effects.cable_friction import CableFriction
from identified.effects.cable_slack import CableSlack
from identified.effects.constant_force import ConstantForce
from identified.effects.ground_contact import GeometryError, GroundContact, read_contact_geometry
from identified.effects.linear_drag import LinearDrag
from identified.effects.pyramid_contact import PyramidContact
from identified.effects.quadratic_drag import QuadraticDrag

__all__ = [
    "EFFECTS",
    "LIBRARY",
    "RESERVED",
    "Effect",
    "GeometryError",
    "ParamBlock",
    "effect_from_json",
    "known_names",
    "make_effect",
    "read_contact_geometry",
    "register_effect",
    "rival",
    "search_labels",
    "split_label",
]

#: the library, in the order the effect search tries it
LIBRARY: tuple[type[Effect], ...] = (GroundContact, PyramidContact, LinearDrag, QuadraticDrag, CableFriction,
                                     CableSlack, ConstantForce)
#: every effect by its JSON name (the library and registered plug-ins)
EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in LIBRARY}
#: names the model file format reserves without an effect behind them, and why
RESERVED: dict[str, str] = {
    "actuator_lag": "the dataset records the cables' actual rest lengths, so a motor lag is already in the data",
}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Add an effect class to :data:`EFFECTS` (usable as a decorator); ValueError on a taken name,
    TypeError for what is not an :class:`Effect` class."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise TypeError(f"{cls!r} is not an Effect class")
    if cls.name in EFFECTS and EFFECTS[cls.name] is not cls or cls.name in RESERVED:
        raise ValueError(f"effect name '{cls.name}' is taken")
    EFFECTS[cls.name] = cls
    return cls


def known_names() -> tuple[str, ...]:
    """Names a model file may use: every effect's, then the reserved ones."""
    return (*EFFECTS, *RESERVED)


def search_labels(markers: bool = False) -> tuple[str, ...]:
    """The effect search's candidates: every effect the class lets the search try (``searched``;
    with ``markers``, on states reconstructed from markers: ``searched_on_markers`` too), each
    followed by its variants as ``name:variant`` (``variants``)."""
    return tuple(label for cls in EFFECTS.values() if cls.searched and (cls.searched_on_markers or not markers)
                 for label in (cls.name, *(f"{cls.name}:{v}" for v in cls.variants)))


def rival(name: str, present: Sequence[str]) -> str | None:
    """The effect of ``present`` (names or ``name:variant`` labels) that models what ``name`` models
    (the same :attr:`Effect.phenomenon`: two ground-contact laws), else None."""
    kind = EFFECTS[name.split(":")[0]].phenomenon
    if kind is None:
        return None
    return next((p for p in present if p.split(":")[0] != name.split(":")[0]
                 and EFFECTS[p.split(":")[0]].phenomenon == kind), None)


def split_label(label: str) -> tuple[str, dict[str, Any]]:
    """``"name"`` or ``"name:variant"`` -> the effect's name and the options of the variant
    (ValueError naming the known ones otherwise)."""
    name, _, variant = label.partition(":")
    if name in RESERVED:
        raise ValueError(f"effect '{name}' is not available: {RESERVED[name]}")
    if name not in EFFECTS:
        raise ValueError(f"unknown effect '{name}' (known: {', '.join(EFFECTS)})")
    if not variant:
        return name, {}
    variants = EFFECTS[name].variants
    if variant not in variants:
        known = ", ".join(f"{name}:{v}" for v in variants) or "none"
        raise ValueError(f"unknown variant '{label}' (variants of {name}: {known})")
    return name, dict(variants[variant])


def make_effect(name: str, topology: Any, mjcf: str | None = None) -> Effect:
    """An unfitted effect by name or ``name:variant`` for a system (ValueError naming the known ones)."""
    base, options = split_label(name)
    eff = EFFECTS[base].for_system(topology, mjcf)
    eff.options.update(options)
    return eff


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


def _flatten_loose(eff: Effect, obj: dict[str, Any]) -> np.ndarray:
    parts = []
    for b in eff.blocks:
        # a block the file does not hold (a parameter added to the effect later): no standard error
        v = np.asarray(obj[b.name] if b.name in obj else np.full(b.size(eff.n_rods, eff.n_springs), np.nan), dtype=float)
        parts.append(v.reshape(-1, b.width) if eff.kind != "global" else v.reshape(1, b.width))
    return np.concatenate(parts, axis=1).reshape(-1)
