"""MuJoCo tendon actuators: activation dynamics and the force each puts on its tendon.

An actuator's force on its tendon is ``F = g act + b`` (MuJoCo's fixed gain times gear, ``g``;
its constant affine bias times gear, ``b``; MuJoCo's sign: positive ``F`` lengthens the tendon, so
the tendon's tension changes by ``-F``).  The activation ``act`` follows the commands ``ctrl`` as
MuJoCo's Euler integrator steps it (``mj_Euler`` -> ``mj_advance``), from ``act_0 = 0``
(``mj_resetData``), the force of step ``t`` acting on ``act_t``:

* ``none``: ``act_t = ctrl_t``;
* ``filter``: ``act_{t+1} = act_t + dt (ctrl_t - act_t) / tau``;
* ``filterexact``: ``act_{t+1} = act_t + (ctrl_t - act_t) (1 - exp(-dt / tau))``;
* ``integrator``: ``act_{t+1} = act_t + dt ctrl_t``.

:func:`activations` also returns ``d act / d tau`` (the fit's Gauss-Newton column for the time
constant, :mod:`identified.fit.actuation`); :func:`tendon_forces` gives every tendon's actuator
force over a record, which the engine takes as an input of each step (``tendon_force``);
:class:`ActuatorBank` steps the same law on torch tensors, one physics step at a time (the twin).
The activation's rate ``k`` is :func:`filter_rates`' for both.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["DYNAMICS", "FILTERS", "ActuatorBank", "activations", "filter_rates", "tendon_force_parts", "tendon_forces"]

DYNAMICS = ("none", "filter", "filterexact", "integrator")
#: activation dynamics with a time constant
FILTERS = ("filter", "filterexact")


def activations(ctrl: np.ndarray, dt: float, dynamics: Sequence[str], tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``act`` (E, T, U) of step ``t`` and ``d act / d tau`` (E, T, U) from the commands ``ctrl``
    (E, T, U) (module docstring); ``tau`` (U,) s, read for the filters only."""
    E, T, U = ctrl.shape
    act, dact = np.zeros_like(ctrl), np.zeros_like(ctrl)
    a, s = np.zeros((E, U)), np.zeros((E, U))
    kinds = np.array(list(dynamics), dtype=object)
    none, integ = kinds == "none", kinds == "integrator"
    k, dk = filter_rates(dynamics, tau, dt)
    for t in range(T):
        c = ctrl[:, t]
        act[:, t] = np.where(none, c, a)
        dact[:, t] = np.where(none | integ, 0.0, s)
        s = s * (1.0 - k) + dk * (c - a)
        a = np.where(integ, a + dt * c, a + k * (c - a))
    return act, dact


def filter_rates(dynamics: Sequence[str], tau: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Each actuator's rate ``k`` in ``act += k (ctrl - act)`` (U,) and ``dk / dtau`` (U,): ``dt /
    tau`` (filter), ``1 - exp(-dt / tau)`` (filterexact), 0 without a filter. ValueError naming an
    unknown kind of dynamics."""
    tau = np.asarray(tau, dtype=float)
    kinds = np.array(list(dynamics), dtype=object)
    unknown = [k for k in kinds if k not in DYNAMICS]
    if unknown:
        raise ValueError(f"activation dynamics '{unknown[0]}' is not one of {', '.join(DYNAMICS)}")
    filt, exact = kinds == "filter", kinds == "filterexact"
    safe = np.where(filt | exact, tau, 1.0)
    k = np.where(filt, dt / safe, 0.0) + np.where(exact, 1.0 - np.exp(-dt / safe), 0.0)
    dk = np.where(filt, -dt / safe**2, 0.0) + np.where(exact, -np.exp(-dt / safe) * dt / safe**2, 0.0)
    return k, dk


@dataclass(frozen=True)
class ActuatorBank:
    """Identified tendon actuators as tensors: their force on the tendons and their activation,
    one physics step at a time, as :func:`activations` and :func:`tendon_forces` (module docstring).

    Build with :meth:`from_json` from the model's ``actuators`` (layout order: ``names``). States
    and commands are (..., U) tensors; the force of a step acts on the activation at its start.
    """

    names: tuple[str, ...]
    spread: torch.Tensor  # (U, S): actuator u's gain in its tendon's column
    bias: torch.Tensor  # (S,): the constant biases, summed per tendon
    rate: torch.Tensor  # (U,) k of a filter, 0 otherwise
    direct: torch.Tensor  # (U,) bool: no dynamics (the force acts on the command itself)
    integrator: torch.Tensor  # (U,) bool
    dt: float

    @classmethod
    def from_json(cls, actuators: Sequence[Mapping[str, Any]], tendon_names: Sequence[str], dt: float,
                  dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> ActuatorBank:
        """From identified actuators ``{name, tendon, dynamics, gain, bias, time_constant}``;
        ValueError naming an actuator on a tendon that is not in ``tendon_names``."""
        U, S = len(actuators), len(tendon_names)
        spread, bias = np.zeros((U, S)), np.zeros(S)
        for u, a in enumerate(actuators):
            if a["tendon"] not in tendon_names:
                raise ValueError(f"actuator '{a['name']}' acts on tendon '{a['tendon']}', which the model does not have")
            j = list(tendon_names).index(a["tendon"])
            spread[u, j] = float(a["gain"])
            bias[j] += float(a.get("bias") or 0.0)
        dyn = [a.get("dynamics", "none") for a in actuators]
        k, _ = filter_rates(dyn, np.array([a.get("time_constant") or 0.0 for a in actuators], dtype=float), dt)
        t = lambda x, dt_=dtype: torch.as_tensor(x, dtype=dt_, device=device)
        return cls(tuple(a["name"] for a in actuators), t(spread), t(bias), t(k),
                   t(np.array([d == "none" for d in dyn], dtype=bool), torch.bool),
                   t(np.array([d == "integrator" for d in dyn], dtype=bool), torch.bool), float(dt))

    @property
    def n(self) -> int:
        return len(self.names)

    def force(self, ctrl: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """(..., S) every tendon's actuator force ``Σ (g act + b)`` (positive lengthens it)."""
        return torch.where(self.direct, ctrl, act) @ self.spread + self.bias

    def step(self, ctrl: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """The activations after one step under the commands ``ctrl`` (..., U)."""
        return torch.where(self.integrator, act + self.dt * ctrl,
                           torch.where(self.direct, ctrl, act + self.rate * (ctrl - act)))


def tendon_forces(ctrl: np.ndarray, dt: float, ctrl_names: Sequence[str], actuators: Sequence[Mapping[str, Any]],
                  tendon_names: Sequence[str]) -> np.ndarray:
    """(E, T, S) every tendon's actuator force ``Σ (g act + b)`` over a record of commands ``ctrl``
    (E, T, U) named ``ctrl_names``; ``actuators``: identified actuators ``{name, tendon, dynamics,
    gain, bias, time_constant}``.  ValueError naming an actuator the record has no command for."""
    gained, spread, bias = tendon_force_parts(ctrl, dt, ctrl_names, actuators, tendon_names)
    return bias + gained @ spread


def tendon_force_parts(ctrl: np.ndarray, dt: float, ctrl_names: Sequence[str], actuators: Sequence[Mapping[str, Any]],
                       tendon_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`tendon_forces` in the parts a fit of the gains needs: each actuator's ``g act`` (E, T,
    U), the tendon each pulls on (U, S, one 1 a row) and the biases' sum on each tendon (E, T, S);
    ``tendon_forces = bias + gained @ spread``, and a gain scaled by ``x`` scales its column alone."""
    E, T = ctrl.shape[:2]
    U, S = len(actuators), len(tendon_names)
    gained, spread, bias = np.zeros((E, T, U)), np.zeros((U, S)), np.zeros((E, T, S))
    if not actuators:
        return gained, spread, bias
    missing = [a["name"] for a in actuators if a["name"] not in ctrl_names]
    if missing:
        raise ValueError(f"the record has no command ('ctrl') for actuator '{missing[0]}'")
    idx = [list(ctrl_names).index(a["name"]) for a in actuators]
    dyn = [a.get("dynamics", "none") for a in actuators]
    tau = np.array([a.get("time_constant") or 0.0 for a in actuators], dtype=float)
    act, _ = activations(np.asarray(ctrl, dtype=float)[..., idx], dt, dyn, tau)
    for u, a in enumerate(actuators):
        j = list(tendon_names).index(a["tendon"])
        gained[..., u] = a["gain"] * act[..., u]
        spread[u, j] = 1.0
        bias[..., j] += a.get("bias", 0.0)
    return gained, spread, bias
