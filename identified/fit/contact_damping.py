"""The ground contact law's friction damping from a recording's short free runs.

Fitted by least squares on rod states splined from markers, the contact law's friction damping
``β_a``, ``β_p`` (:mod:`identified.effects.ground_contact`) comes out several times too small: its
regressor, the contact point's tangential velocity, is a noisy, smoothed measurement, and least
squares on a noisy regressor pulls its coefficient towards zero (on the robot at 100 Hz and 1 mm,
3.9 and 3.0 1/s against 18.6 and 14.9 1/s from the full states of the same runs; the twin's 1 s
free run 0.307 m against 0.070 m, and 0.088 m with the full states' two values).  The short free
runs of the identified engine from the reconstructed states see that damping directly: a common
factor on both is chosen from :data:`FACTORS` by the mean position error of free runs of
:data:`WINDOW_STEPS` steps against the reconstructed states (:func:`identified.evaluate.window_error`).
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Any

import numpy as np

from identified.dataset import Dataset
from identified.evaluate import window_error
from identified.fit.workers import TaskPool
from identified.model import IdentifiedModel

__all__ = ["FACTORS", "WINDOW_STEPS", "refine_friction_damping"]

#: the factors on the fitted ``β_a``, ``β_p`` scanned (the profile's grid)
FACTORS = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0)
#: steps of each free run the factor is judged by (0.3 s at 1 kHz)
WINDOW_STEPS = 300
#: the takes and the steps of each the free runs start from (the first ones)
MAX_TAKES, MAX_STEPS = 8, 3000
KEYS = ("beta_a", "beta_p")


def _scaled_error(ctx: tuple[IdentifiedModel, Dataset, int, dict[str, float]], f: float) -> float:
    """The windows' error of ``ctx``'s model with its contact law's ``β_a``, ``β_p`` times ``f``."""
    model, part, k, fitted = ctx
    effects = copy.deepcopy(model.effects)
    effects[k]["parameters"].update({key: f * v for key, v in fitted.items()})
    return window_error(replace(model, effects=effects), part, WINDOW_STEPS)


def refine_friction_damping(model: IdentifiedModel, data: Dataset, jobs: int | str | None = 1
                            ) -> dict[str, Any] | None:
    """Scale the ground contact law's ``β_a``, ``β_p`` of ``model`` (in place) by the factor of
    :data:`FACTORS` whose free runs of :data:`WINDOW_STEPS` steps from the reconstructed states
    ``data`` (its first takes and steps) stay nearest them.  Their standard errors become ``NaN``
    (a profile scan's value).  Returns ``{"factor", "window_steps", "errors": {factor: m}}``, or
    ``None`` without a ground contact law or takes too short for one window.  The factors' free
    runs run side by side in ``jobs`` processes (:mod:`identified.fit.workers`; the same result)."""
    k = next((i for i, e in enumerate(model.effects) if e["name"] == "ground_contact"), None)
    if k is None or data.n_steps <= WINDOW_STEPS:
        return None
    part = data.select(episodes=slice(0, min(MAX_TAKES, data.n_episodes)), steps=min(MAX_STEPS, data.n_steps))
    part = replace(part, replicas=())
    fitted = {key: float(model.effects[k]["parameters"][key]) for key in KEYS}
    with TaskPool(_scaled_error, (model, part, k, fitted), jobs) as pool:
        errors = dict(zip(FACTORS, pool.map(FACTORS)))
    best = min(FACTORS, key=lambda f: errors[f] if np.isfinite(errors[f]) else np.inf)
    model.effects[k]["parameters"].update({key: best * v for key, v in fitted.items()})
    stderr = model.effects[k].get("stderr")
    if isinstance(stderr, dict) and best != 1.0:
        stderr.update({key: None for key in KEYS})
    return {"factor": best, "window_steps": WINDOW_STEPS,
            "errors": {str(f): (float(e) if np.isfinite(e) else None) for f, e in errors.items()}}
