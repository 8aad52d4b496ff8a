"""Whether a recording's frame rate resolves the robot's motion between its frames.

The fit reconstructs rod states at every engine step from markers sampled at ``rate`` Hz
(:mod:`identified.fit.markers`): smoothing splines between the frames.  A motion that oscillates
faster than half the rate (the Nyquist frequency) is not in the samples at all, and the splines
replace it by a smooth curve: a bias in the reconstructed velocities and, more, accelerations,
common to every take, which neither the errors-in-variables replicas (noise) nor the jackknife over
runs (spread) can see.  The dampings (fitted from velocities) and the masses and moments of inertia
(from accelerations) then come out biased beyond their standard errors -- measured on the robot at
10 Hz, clean markers: a damping 35 % off at z = 21, a mass 7 % off at z = 4.5 -- while the stiffnesses
(from positions, which the frames do hold) stay calibrated (1 %, |z| <= 2).

:func:`fastest_oscillation` asks the identified model itself how fast it oscillates: the
oscillating modes of its engine step linearised at the first reconstructed state of a few takes
(:func:`identified.engine.stability.oscillation_frequencies`); the robot's cable modes reach about
10 Hz.  :func:`withhold_unresolved` then withholds the standard errors of what the frames cannot
carry, says so in ``metrics.not_identifiable`` and warns: a number without an error bar, never one
with an error bar that does not cover the truth.
"""

from __future__ import annotations

import numpy as np

from identified.dataset import Dataset
from identified.engine.integration import RodState
from identified.engine.stability import oscillation_frequencies
from identified.model import IdentifiedModel
from identified.twin import engine_from_model

__all__ = ["fastest_oscillation", "withhold_unresolved"]

#: takes whose first state the model is linearised at
TAKES = 3


def fastest_oscillation(model: IdentifiedModel, data: Dataset, takes: int = TAKES) -> float:
    """The highest frequency (Hz) of the model's oscillating modes at the first state of each of
    the first ``takes`` takes of ``data`` (0 where nothing oscillates or the step is not finite)."""
    engine = engine_from_model(model)
    best = 0.0
    for e in range(min(int(takes), data.n_episodes)):
        state = RodState(*(np.asarray(x[e, 0], dtype=np.float64) for x in (data.pos, data.quat, data.vel, data.angvel)))
        f = oscillation_frequencies(engine, state, data.rest_length[e, 0])
        best = max(best, float(f.max()) if f.size else 0.0)
    return best


def withhold_unresolved(model: IdentifiedModel, rate_hz: float, fastest_hz: float) -> bool:
    """Where ``fastest_hz`` (the model's fastest oscillation) is above half of ``rate_hz`` (the
    recording's frame rate): the standard errors of the dampings, masses and moments of inertia set
    to NaN (``null`` in the file), one line in ``metrics.not_identifiable`` and one warning in
    ``metrics.warnings``; True where it did so.  The stiffnesses keep theirs."""
    nyquist = 0.5 * float(rate_hz)
    if not fastest_hz > nyquist:
        return False
    why = (f"the robot oscillates at up to {fastest_hz:.3g} Hz, above half the recording's {rate_hz:.3g} Hz: "
           "the frames do not hold that motion")
    for key in ("damping", "mass", "inertia"):
        if key in model.stderr:
            model.stderr[key] = np.full_like(np.asarray(model.stderr[key], dtype=float), np.nan)
    names = model.metrics.setdefault("not_identifiable", [])
    names.append(f"every damping, mass and moment of inertia ({why}; standard errors withheld)")
    model.metrics.setdefault("warnings", []).append(
        f"{why}, so the dampings, masses and moments of inertia are biased by the reconstruction between frames "
        f"beyond any error bar (standard errors withheld; the stiffnesses keep theirs); record at "
        f"{2 * fastest_hz:.3g} Hz or more to identify them")
    return True
