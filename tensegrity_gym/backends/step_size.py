"""The twin's integration step for training: the coarsest whole multiple of the model's ``dt``
that divides the control period and at which the identified engine is stable with a factor of
safety (``physics_dt="auto"``, ``tensegrity train``'s default).

The identified parameters are continuous-time quantities, so the twin may integrate them at
``k dt`` (:class:`~tensegrity_gym.backends.identified_backend.IdentifiedBackend`'s ``physics_dt``)
and run ``k`` times fewer engine steps; how coarse is each robot's own matter (its stiffest cable,
its contact), found here by linearising the model's engine at the robot's standing pose
(:mod:`identified.engine.stability`) rather than by a fixed number.  The robot preset's shipped
model is stable up to a step of about 11.1 ms (benchmarks/bench_physics_dt.py), so the default
factor of safety of 2.5 picks 4 ms (README, "Training on the twin": what it costs in transfer).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Sequence

import torch

from identified.engine import Effect, SpringRodEngine
from identified.engine.stability import StepChoice, coarsest_stable_step
from identified.model import IdentifiedModel
from identified.twin import engine_from_model

#: the factor of safety: a step is taken only if the engine is stable at 2.5 times it.  Measured
#: (README, "The twin's step"): at 2 (5 ms for the robot preset) policies matched the plant less
#: well than at 4 ms on the same models and seeds (seeds under 90 % of their twin 3 / 2 / 2 against
#: 1 / 0 / 0, the unrandomized twin exploited); 2.5 takes 4 ms.
STABILITY_MARGIN = 2.5


def whole_divisors(n: int) -> list[int]:
    """The whole numbers ``k >= 1`` that divide ``n`` (the coarsenings a control period of ``n``
    physics steps allows), ascending."""
    if int(n) != n or n < 1:
        raise ValueError(f"a control period of {n!r} physics steps: must be a whole number >= 1")
    return [k for k in range(1, int(n) + 1) if n % k == 0]


def stable_physics_dt(model: str | os.PathLike | IdentifiedModel | None, period_steps: int,
                      mjcf: str | os.PathLike | None = None, effects: Sequence[Effect] = (),
                      margin: float = STABILITY_MARGIN) -> StepChoice:
    """The coarsest ``k dt`` (``k`` dividing ``period_steps``) at which ``model``'s engine, with its
    effects and ``effects``, linearised at the robot's standing pose (the backend's nominal state
    and rest lengths), is stable at ``margin`` times the step, and every first-order actuator
    filter of the model too (:func:`identified.engine.stability.coarsest_stable_step`).  ``model``:
    as :class:`IdentifiedBackend` takes it (``None``: the shipped model); ``mjcf``: its source
    MJCF where not the model's own.  Stable means no faster growth than the model's own at its
    ``dt`` (a twin not at rest at that pose tips over at any step); a model not stable at its own
    ``dt``, or blowing up there, gets ``dt`` (``StepChoice.stable_at_finest`` False).  A model
    file's answer is kept for the process (by path, size and modification time)."""
    if isinstance(model, (str, os.PathLike)) and not effects:
        path = os.path.realpath(model)
        st = os.stat(path)
        return _stable_from_file(path, st.st_size, st.st_mtime_ns, int(period_steps),
                                 None if mjcf is None else os.fspath(mjcf), float(margin))
    return _stable(model, period_steps, mjcf, effects, margin)


@functools.lru_cache(maxsize=16)
def _stable_from_file(path: str, size: int, mtime_ns: int, period_steps: int, mjcf: str | None,
                      margin: float) -> StepChoice:
    """:func:`_stable` of a model file, remembered by its path, size and modification time."""
    return _stable(path, period_steps, mjcf, (), margin)


def _stable(model: str | os.PathLike | IdentifiedModel | None, period_steps: int, mjcf: str | os.PathLike | None,
            effects: Sequence[Effect], margin: float) -> StepChoice:
    """:func:`stable_physics_dt`, computed."""
    from tensegrity_gym.backends.identified_backend import IdentifiedBackend

    backend = IdentifiedBackend(model, dtype=torch.float64, effects=effects, mjcf=mjcf, compile=False)
    m = backend.model
    taus = [float(a.get("time_constant") or 0.0) for a in m.actuators if a.get("dynamics") == "filter"]

    def engine_at(h: float) -> SpringRodEngine:
        return engine_from_model(dataclasses.replace(m, dt=h), effects=effects)

    return coarsest_stable_step(engine_at, backend.nominal_states(), backend.nominal_rest_lengths(),
                                [k * m.dt for k in whole_divisors(period_steps)], margin=margin,
                                filter_time_constants=taus)

