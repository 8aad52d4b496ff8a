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
force over a record, which the engine takes as an input of each step (``tendon_force``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["DYNAMICS", "FILTERS", "activations", "tendon_forces"]

DYNAMICS = ("none", "filter", "filterexact", "integrator")
#: activation dynamics with a time constant
FILTERS = ("filter", "filterexact")


def activations(ctrl: np.ndarray, dt: float, dynamics: Sequence[str], tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``act`` (E, T, U) of step ``t`` and ``d act / d tau`` (E, T, U) from the commands ``ctrl``
    (E, T, U) (module docstring); ``tau`` (U,) s, read for the filters only."""
    E, T, U = ctrl.shape
    act, dact = np.zeros_like(ctrl), np.zeros_like(ctrl)
    a, s = np.zeros((E, U)), np.zeros((E, U))
    tau = np.asarray(tau, dtype=float)
    kinds = np.array(list(dynamics), dtype=object)
    unknown = [k for k in kinds if k not in DYNAMICS]
    if unknown:
        raise ValueError(f"activation dynamics '{unknown[0]}' is not one of {', '.join(DYNAMICS)}")
    none, integ = kinds == "none", kinds == "integrator"
    filt, exact = kinds == "filter", kinds == "filterexact"
    safe = np.where(filt | exact, tau, 1.0)
    k = np.where(filt, dt / safe, 0.0) + np.where(exact, 1.0 - np.exp(-dt / safe), 0.0)  # act += k (ctrl - act)
    dk = np.where(filt, -dt / safe**2, 0.0) + np.where(exact, -np.exp(-dt / safe) * dt / safe**2, 0.0)  # dk/dtau
    for t in range(T):
        c = ctrl[:, t]
        act[:, t] = np.where(none, c, a)
        dact[:, t] = np.where(none | integ, 0.0, s)
        s = s * (1.0 - k) + dk * (c - a)
        a = np.where(integ, a + dt * c, a + k * (c - a))
    return act, dact


def tendon_forces(ctrl: np.ndarray, dt: float, ctrl_names: Sequence[str], actuators: Sequence[Mapping[str, Any]],
                  tendon_names: Sequence[str]) -> np.ndarray:
    """(E, T, S) every tendon's actuator force ``Σ (g act + b)`` over a record of commands ``ctrl``
    (E, T, U) named ``ctrl_names``; ``actuators``: identified actuators ``{name, tendon, dynamics,
    gain, bias, time_constant}``.  ValueError naming an actuator the record has no command for."""
    E, T = ctrl.shape[:2]
    out = np.zeros((E, T, len(tendon_names)))
    if not actuators:
        return out
    missing = [a["name"] for a in actuators if a["name"] not in ctrl_names]
    if missing:
        raise ValueError(f"the record has no command ('ctrl') for actuator '{missing[0]}'")
    idx = [list(ctrl_names).index(a["name"]) for a in actuators]
    dyn = [a.get("dynamics", "none") for a in actuators]
    tau = np.array([a.get("time_constant") or 0.0 for a in actuators], dtype=float)
    act, _ = activations(np.asarray(ctrl, dtype=float)[..., idx], dt, dyn, tau)
    for u, a in enumerate(actuators):
        out[..., list(tendon_names).index(a["tendon"])] += a["gain"] * act[..., u] + a.get("bias", 0.0)
    return out
