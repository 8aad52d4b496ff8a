"""The classification strategy of the fit: effects whose columns depend on a classification of
every instant made from their own values (``fit_strategy = "classification"``: cable friction,
whose cables stick or slip).

Given the classification the effect's columns are linear in its parameters and join the main
regression (:func:`identified.fit.identify.identify`); the classification follows from the
parameters, so the fit iterates (:func:`iterate_classification`): a first classification is searched
among the starts read off the data (:func:`starts`), every later pass classifies with the previous
pass's values, until they stop moving.  Before each pass :func:`prepare` counts what the data show
of every element under the classification (cables never seen sticking or slipping have the
parameters the data cannot tell held, :meth:`~identified.effects.cable_friction.CableFriction.pinned`).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch

from identified.dataset import Dataset
from identified.effects.base import Effect
from identified.fit.checks import ROUNDING, relative_residual
from identified.fit.features import chunk_context
from identified.fit.regression import IdentifiabilityError
from identified.model import IdentifiedModel
from identified.samples import iter_chunks
from identified.topology import Topology

__all__ = ["MAX_CLASSIFICATION_PASSES", "MAX_FULL_PASSES", "SEARCH_STEPS", "iterate_classification", "prepare",
           "starts"]

#: fits of an iterative effect's classification (cable friction) per start of the search on a part
#: of the data: it settles in 2-4 on clean data; where it does not (little or no sticking) the
#: passes wander and the best one is kept
MAX_CLASSIFICATION_PASSES = 5
#: passes on all the data from a settled classification -- the search's on a part, or one given as
#: the effect's values (a refit, or the effect search's next round) -- measured: 1-2 where the law
#: is there; where it is not (F ~ 0) the classification of the rows near |m L̈ + d L̇| ~ F flickers
#: and the passes stop at this cap
MAX_FULL_PASSES = 3
#: steps of the part of the data the first classification is searched on
SEARCH_STEPS = 4000


def starts(effect: Effect, data: Dataset, topology: Topology) -> list[dict[str, float]]:
    """Initial classifications of a stick / slip effect to try (the fit keeps the one whose passes
    leave the smallest equation residual): stick within ``|L̈ + b L̇| < θ`` (the effect's options
    ``start_rate`` b, ``start_band`` θ).  ``b``: the decay rate of a sticking cable's length rate
    (``-L̈ / L̇ -> b`` while ``|b L̇|`` dominates the stick force), read off the data as the sharp
    mode of ``-L̈ / L̇`` on a log scale (the slipping cables spread over a broad range); ``θ``: 0.1,
    0.3, 1 and 3 times the median ``|L̈ + b L̇|`` -- only 1 when the mode is not sharp (no sticking
    in the data)."""
    ch, _ = next(iter(iter_chunks(data, 20_000)))
    acc, rate = effect.length_motion(chunk_context(topology, ch), ch.acc, ch.alpha_body)
    acc, rate = acc.reshape(-1).numpy(), rate.reshape(-1).numpy()
    sel = np.abs(rate) > 1e-3 * np.percentile(np.abs(rate), 90)  # not the cables at rest
    ratio = -acc[sel] / rate[sel]
    ratio = ratio[ratio > 0]
    if ratio.size < 10:
        return [{"start_rate": 0.0, "start_band": float(np.median(np.abs(acc)))}]
    h, edges = np.histogram(np.log10(ratio), bins=80, range=(-1.0, 5.0))
    # sticking cables make a sharp peak: a bin far above the bins a few away on both sides
    # (measured: 2-7x, where the broad mode of the slipping cables is 1.2-1.4x; with little
    # sticking, 0.7 N, the peak is lower than the broad mode but still 6x its surroundings);
    # the sharpest bin among those of at least a fifth of the highest count is taken
    sharpness = np.zeros(h.size)
    for k in np.flatnonzero(h >= 0.2 * h.max()):
        near = np.concatenate([h[max(0, k - 6): max(0, k - 2)], h[k + 3: k + 7]])
        sharpness[k] = h[k] / max(float(np.median(near)) if near.size else 0.0, 1.0)
    k = int(np.argmax(sharpness))
    # the peak's place to a fiftieth of a bin: a fine histogram over the bins around it
    fine, fe = np.histogram(np.log10(ratio), bins=250, range=(edges[max(k - 2, 0)], edges[min(k + 3, 80)]))
    j = int(np.argmax(fine))
    b = float(10 ** (0.5 * (fe[j] + fe[j + 1])))
    scale = float(np.median(np.abs(acc + b * rate)))
    # without that signature one start is enough to show F ~ 0
    sharp = sharpness[k] > 1.5
    return [{"start_rate": b, "start_band": scale * g} for g in ((0.1, 0.3, 1.0, 3.0) if sharp else (1.0,))]


def prepare(effect: Effect, data: Dataset, topology: Topology, min_rows: int = 100,
            motion: dict | None = None) -> None:
    """Before a pass of the fit: count each element's sticking instants under the effect's current
    classification and the largest stick force seen, and give them to the effect
    (:meth:`~identified.effects.cable_friction.CableFriction.observe`).  ``motion``: where the
    passes on the same data keep what the classification reads (:meth:`length_motion`, which the
    effect's values do not change)."""
    stuck = np.zeros(effect.n_springs)
    rows = 0
    qmax = np.zeros(effect.n_springs)
    with torch.no_grad():
        for acc, rate in _length_motion(effect, data, topology, motion):
            stuck += effect.classify(acc, rate)[0].sum(0).numpy()
            rows += acc.shape[0]
            if effect.values is not None:
                qmax = np.maximum(qmax, effect.stick_force(acc, rate).amax(0).numpy())
    effect.observe(stuck, rows, qmax, min_rows)


def _length_motion(effect: Effect, data: Dataset, topology: Topology, motion: dict | None
                   ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The effect's :meth:`length_motion` of ``data`` per chunk, kept in ``motion`` for the same data."""
    if motion is not None and motion.get(effect.name, (None,))[0] is data:
        return motion[effect.name][1]
    out = [effect.length_motion(chunk_context(topology, ch), ch.acc, ch.alpha_body) for ch, _ in iter_chunks(data, 8192)]
    if motion is not None:
        motion[effect.name] = (data, out)
    return out


def iterate_classification(dataset: Dataset, topology: Topology, iterative: Sequence[Effect],
                            fit_once: Any, progress: bool) -> IdentifiedModel:
    """Fit with effects whose columns depend on a classification made from their own values (the
    cable friction's stick / slip): fit, reclassify with the new values, until they stop moving.

    The first classification is searched on a part of the data (:func:`starts` of each effect;
    the one whose passes leave the smallest equation residual is kept); what a pass finds
    unidentifiable of such an effect is held at the effect's pinned values and the pass redone.
    """

    motion: dict = {}  # what the classification reads, for the data of the latest passes

    def fit_holding(data: Dataset, residual_stage: bool = False, bar: bool = False) -> IdentifiedModel | None:
        for e in iterative:
            prepare(e, data, topology, motion=motion)
        try:  # what the pass finds unidentifiable of these effects it holds (identify's solve_holding)
            return fit_once(data, residual_stage, bar)
        except IdentifiabilityError:
            return None

    def passes_from_here(data: Dataset, most: int) -> tuple[int, float, float]:
        """Passes until the values settle: how many, the equation residual, and the smallest
        relative residual of a pass (:func:`relative_residual`: whether the law settled).  The
        passes are a fixed-point iteration that need not contract (little sticking: a cable that drops below
        the stick rows it needs loses its stick law, and the next classification is worse); if
        they end above the best pass's residual, the values that classified the best pass are
        restored."""
        res = np.inf
        best: tuple[float, list | None] = (np.inf, None)
        settled = np.inf
        for n in range(1, most + 1):
            previous = [None if e.values is None else e.values.copy() for e in iterative]
            try:
                fit = fit_holding(data)
            except ValueError:
                fit = None
            if fit is None:
                return n, np.inf, np.inf
            rms = fit.metrics["equation_residual_rms"]
            res = (rms["translation"] or 0.0) + (rms["rotation"] or 0.0)
            settled = min(settled, relative_residual(fit) or np.inf)
            if all(p is not None for p in previous) and res < best[0]:
                best = (res, previous)  # the values whose classification gave this pass's fit
            if not any(e.reclassify(p) for e, p in zip(iterative, previous)):
                break
        if best[1] is not None and best[0] < res:  # the passes wandered off: back to the best one
            for e, v in zip(iterative, best[1]):
                e.values = v
            res = best[0]
        return n, res, settled

    warm = [None if e.values is None else e.values.copy() for e in iterative]
    searched = any(v is None for v in warm) or any(e.search_too for e in iterative)
    inert = False
    if searched:  # search the initial classification (given values, if any, are one more start)
        best: tuple[float, list | None] = (np.inf, None)
        tried: list[Any] = list(itertools.product(*[starts(e, dataset, topology) for e in iterative]))
        if all(v is not None for v in warm):
            tried.append(None)
        kept: list | None = None  # a smaller part's best, for a larger part none of whose starts fits
        for part in _search_parts(dataset):
            best, spread, rel = (np.inf, None), [], np.inf
            for start in tried:
                for k, e in enumerate(iterative):
                    if start is not None:
                        e.options.update(start[k])
                    e.values = None if start is not None else warm[k].copy()
                    e.release()
                _, res, settled = passes_from_here(part, MAX_CLASSIFICATION_PASSES)
                if start is not None:  # the effect's own starts (a given classification may be wrong)
                    spread.append(res)
                if res < best[0]:
                    best, rel = (res, [e.values.copy() for e in iterative]), settled
            if best[1] is None:
                continue  # no start could be fitted on this part: a larger one
            kept = best[1]
            if not _part_too_small(iterative, best[1], part, topology, spread, rel, motion):
                break
        best = (best[0], best[1] or kept)
        for e, v in zip(iterative, best[1] or [None] * len(iterative)):
            e.values = v
            e.release()
            prepare(e, part, topology, motion=motion)
        # nothing to classify (no cable ever sticks): no more passes, one final fit
        inert = all(e.inert() for e in iterative)
    passes = 0
    if not inert:
        passes, _, _ = passes_from_here(dataset, MAX_FULL_PASSES)
    model = fit_holding(dataset, residual_stage=True, bar=progress)
    if model is None:  # let the regression say what it cannot identify
        model = fit_once(dataset, True, progress)
    model.metrics["classification"] = {"passes": passes + 1, **{e.name: e.unseen() for e in iterative}}
    return model


def _part_too_small(iterative: Sequence[Effect], values: list, part: Dataset, topology: Topology,
                    residuals: Sequence[float], relative: float, motion: dict | None = None) -> bool:
    """Whether the classification search should go on to a larger part of the data than ``part``:
    the classification matters there (the effect's own starts' equation ``residuals`` differ by 2x
    or more, or there was one), the best one, ``values``, leaves a ``relative`` residual above rounding
    (:data:`ROUNDING`: not settled), and it sees some of an effect's elements and not others (a
    cable with too few sticking rows to tell its stick law).  The part then holds too few rows of a
    rare state: the robot's cables stick ~2 % of the time under 10 N of friction, ~60 rows per cable
    in a 3 s episode, and the search settled a wrong classification on one or two such episodes
    (F 3.9 N for 10, K 783 N/m for 2000) and the exact one on four; under 30 N (4 %, and no sharp
    signature: one start) it needed all six.  Where several starts agree (the law is not what the
    data lack: friction without the ground contact, round 1 on the robot) or the residual is
    rounding, a larger part cannot do better."""
    finite = [r for r in residuals if np.isfinite(r)]
    if relative < ROUNDING or (len(finite) > 1 and max(finite) < 2.0 * min(finite)):
        return False
    for e, v in zip(iterative, values):
        e.values = v.copy()
        prepare(e, part, topology, motion=motion)
        if e.partly_unseen():
            return True
    return False


def _search_parts(dataset: Dataset) -> Iterator[Dataset]:
    """The parts of the data the first classification is searched on, smallest first:
    ``SEARCH_STEPS`` steps (whole episodes where they are shorter), then twice the episodes, up to
    all of them.  A larger part is tried only when no start could be fitted on the smaller one
    (the robot on 3 s episodes: in one episode a rod that stays on the ground has no equation
    outside the contact's rows, so its mass is unidentifiable there), or when the best start's
    classification there sees some elements and not others (:func:`_part_too_small`)."""
    E, T = dataset.n_episodes, dataset.n_steps
    k = max(1, min(E, SEARCH_STEPS // T))
    while True:
        yield dataset.select(episodes=slice(0, k), steps=min(T, SEARCH_STEPS)) if k < E or T > SEARCH_STEPS \
            else dataset
        if k >= E:
            return
        k = min(E, 2 * k)
