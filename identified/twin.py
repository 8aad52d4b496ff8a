"""The identified twin assembled from its model: an :class:`~identified.model.IdentifiedModel` (the
identified JSON) as a running :class:`~identified.engine.SpringRodEngine`.

The model file gives the topology, the physical parameters, ``dt``, the integrator and the fitted
effects by name (:data:`identified.effects.EFFECTS`); this module puts them together. It sits above
the engine, the effects' laws and the model file, and below everything that runs a model (the
evaluation, ``predict``, the fit's effect search, the diagnosis, the Gymnasium twin backend).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from identified.effects import Effect, effect_from_json
from identified.engine import SpringRodEngine, SpringRodParams
from identified.model import IdentifiedModel

__all__ = ["effects_from_model", "engine_from_model", "params_from_model"]


def params_from_model(model: IdentifiedModel, dtype: torch.dtype = torch.float64,
                      device: torch.device | str = "cpu") -> SpringRodParams:
    """The model's stiffness, damping, mass, inertia, control scale and gravity as engine
    parameters; a model with centres of mass off the rod frames' origins or turned principal axes
    gives the engine its ``com`` and the inertia tensor about the centre of mass (diagonal and
    ``inertia_products``, rod frame)."""
    topo = model.topology
    inertia, com, products = model.inertia, None, None
    if model.full_inertia:
        inertia, products = model.inertia_about_com()
        com = np.zeros((topo.n_rods, 3)) if model.com is None else model.com
    return SpringRodParams.from_values(
        model.stiffness, model.damping, model.mass, inertia, model.control_scale, model.gravity,
        com=com, inertia_products=products,
        n_rods=topo.n_rods, n_springs=topo.n_springs, dtype=dtype, device=device,
    )


def effects_from_model(model: IdentifiedModel) -> list[Effect]:
    """The fitted effects the model file lists, ready for the engine."""
    topo = model.topology
    return [effect_from_json(e, topo.n_rods, topo.n_springs) for e in model.effects]


def engine_from_model(model: IdentifiedModel, effects: Sequence[Effect] = (), dtype: torch.dtype = torch.float64,
                      device: torch.device | str = "cpu") -> SpringRodEngine:
    """The engine of a model: its topology, parameters, dt, integrator and every effect its file
    lists, then ``effects`` (extra plug-ins, any callable :class:`~identified.engine.Effect`) after them."""
    return SpringRodEngine(model.topology, params_from_model(model, dtype, device), model.dt,
                           effects=[*effects_from_model(model), *effects], dtype=dtype, device=device,
                           integrator=model.integrator)
