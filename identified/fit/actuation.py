"""MuJoCo tendon actuators in the regression: activations from the recorded commands, and the
Gauss-Newton search of a filter's time constant.

An actuator's force on its tendon is ``F = g act + b`` (:mod:`identified.engine.actuators`, which
also steps the activation ``act`` from the commands as MuJoCo does), linear in ``(g, b)`` once
``act`` is known.  The time constant enters nonlinearly;
:func:`~identified.engine.actuators.activations` also returns ``d act / d tau``, whose column
(parameter ``g dtau``) turns one least-squares solve into one Gauss-Newton step of ``tau``
(variable projection): ``tau <- tau + (g dtau) / g``, exact at the fixed point on clean data.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from identified.dataset import Dataset
from identified.engine.actuators import FILTERS, activations

__all__ = ["FILTERS", "activation_dataset", "activations", "step_time_constant"]


def activation_dataset(dataset: Dataset, names: Sequence[str], dynamics: Sequence[str],
                       tau: np.ndarray) -> Dataset:
    """The dataset with ``ctrl`` replaced by the activations of the actuators ``names`` (in that
    order, each looked up in ``dataset.actuator_names``), then their ``d act / d tau``: what
    :func:`identified.fit.features.equation_rows` reads."""
    idx = [dataset.actuator_names.index(n) for n in names]
    act, dact = activations(dataset.ctrl[..., idx], dataset.dt, dynamics, tau)
    return replace(dataset, ctrl=np.concatenate([act, dact], axis=-1),
                   actuator_names=tuple(names) + tuple(f"{n}/dtau" for n in names),
                   replicas=tuple(activation_dataset(r, names, dynamics, tau) for r in dataset.replicas))


def step_time_constant(tau: np.ndarray, gain: np.ndarray, gain_dtau: np.ndarray, dynamics: Sequence[str],
                       dt: float) -> np.ndarray:
    """One Gauss-Newton step of the filters' time constants, ``tau + (g dtau) / g``, kept within
    a factor 3 of the current value and above ``dt / 10`` (others unchanged)."""
    filt = np.isin(np.array(list(dynamics)), FILTERS)
    with np.errstate(divide="ignore", invalid="ignore"):
        new = tau + np.where(gain != 0, gain_dtau / np.where(gain != 0, gain, 1.0), 0.0)
    new = np.clip(np.nan_to_num(new, nan=tau), tau / 3.0, tau * 3.0)
    return np.where(filt, np.maximum(new, dt / 10.0), tau)
