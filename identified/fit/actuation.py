"""MuJoCo tendon actuators in the regression: activations from the recorded commands, and the
Gauss-Newton search of a filter's time constant.

An actuator's force on its tendon is ``F = g act + b`` (MuJoCo ``mju_muscleGain``-free fixed gain
times gear, ``g``; its constant affine bias times gear, ``b``), linear in ``(g, b)`` once the
activation ``act`` is known.  ``act`` follows from the commands ``ctrl`` and the activation
dynamics, stepped as MuJoCo's Euler integrator steps ``act`` (``mj_Euler`` -> ``mj_advance``):

* ``none``: ``act_t = ctrl_t``;
* ``filter``: ``act_{t+1} = act_t + dt (ctrl_t - act_t) / tau``;
* ``filterexact``: ``act_{t+1} = act_t + (ctrl_t - act_t) (1 - exp(-dt / tau))``;
* ``integrator``: ``act_{t+1} = act_t + dt ctrl_t``;

from ``act_0 = 0`` (MuJoCo's reset), the force of step ``t`` acting on ``act_t``.  The time
constant enters nonlinearly; :func:`activations` also returns ``d act / d tau``, whose column
(parameter ``g dtau``) turns one least-squares solve into one Gauss-Newton step of ``tau``
(variable projection): ``tau <- tau + (g dtau) / g``, exact at the fixed point on clean data.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from identified.dataset import Dataset

__all__ = ["FILTERS", "activation_dataset", "activations", "step_time_constant"]

#: activation dynamics with a time constant
FILTERS = ("filter", "filterexact")


def activations(ctrl: np.ndarray, dt: float, dynamics: Sequence[str], tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``act`` (E, T, U) of step ``t`` and ``d act / d tau`` (E, T, U) from the commands ``ctrl``
    (E, T, U) (module docstring); ``tau`` (U,) s, read for the filters only."""
    E, T, U = ctrl.shape
    act, dact = np.zeros_like(ctrl), np.zeros_like(ctrl)
    a, s = np.zeros((E, U)), np.zeros((E, U))
    tau = np.asarray(tau, dtype=float)
    kinds = np.array(list(dynamics))
    none, integ = kinds == "none", kinds == "integrator"
    filt, exact = kinds == "filter", kinds == "filterexact"
    with np.errstate(divide="ignore", invalid="ignore"):
        k_f = np.where(filt, dt / tau, 0.0)  # filter: act += k (ctrl - act)
        k_e = np.where(exact, 1.0 - np.exp(-dt / tau), 0.0)
        dk_f = np.where(filt, -dt / tau**2, 0.0)  # d k / d tau
        dk_e = np.where(exact, -np.exp(-dt / tau) * dt / tau**2, 0.0)
    k, dk = k_f + k_e, dk_f + dk_e
    for t in range(T):
        c = ctrl[:, t]
        act[:, t] = np.where(none, c, a)
        dact[:, t] = np.where(none | integ, 0.0, s)
        s = s * (1.0 - k) + dk * (c - a)
        a = np.where(integ, a + dt * c, a + k * (c - a))
    return act, dact


def activation_dataset(dataset: Dataset, names: Sequence[str], dynamics: Sequence[str],
                       tau: np.ndarray) -> Dataset:
    """The dataset with ``ctrl`` replaced by the activations of the actuators ``names`` (in that
    order, each looked up in ``dataset.actuator_names``), then their ``d act / d tau``: what
    :func:`identified.fit.features.equation_rows` reads."""
    idx = [dataset.actuator_names.index(n) for n in names]
    act, dact = activations(dataset.ctrl[..., idx], dataset.dt, dynamics, tau)
    return replace(dataset, ctrl=np.concatenate([act, dact], axis=-1),
                   actuator_names=tuple(names) + tuple(f"{n}/dtau" for n in names))


def step_time_constant(tau: np.ndarray, gain: np.ndarray, gain_dtau: np.ndarray, dynamics: Sequence[str],
                       dt: float) -> np.ndarray:
    """One Gauss-Newton step of the filters' time constants, ``tau + (g dtau) / g``, kept within
    a factor 3 of the current value and above ``dt / 10`` (others unchanged)."""
    filt = np.isin(np.array(list(dynamics)), FILTERS)
    with np.errstate(divide="ignore", invalid="ignore"):
        new = tau + np.where(gain != 0, gain_dtau / np.where(gain != 0, gain, 1.0), 0.0)
    new = np.clip(np.nan_to_num(new, nan=tau), tau / 3.0, tau * 3.0)
    return np.where(filt, np.maximum(new, dt / 10.0), tau)
