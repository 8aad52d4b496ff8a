"""The whole ``tensegrity fit``: integrator choice, the fit with effects, the effect search,
refinement, metrics and the source model -- one function, :func:`fit_model`, for the CLI and Python.

Effect search (``effects="auto"``), forward selection on held-out data:

1. split the episodes: the last quarter (at least one) is *held out*, never fitted;
2. fit the model with the effects chosen so far on the rest; its held-out error is the free-run
   position error (m, mean over rods and steps) over ``horizon_s`` seconds from every held-out
   episode's recorded states (:func:`identified.evaluate.rollout_errors`);
3. refit with each remaining candidate of the library added, one at a time, and screen each by
   its held-out error over short windows (a tenth of the horizon, from many recorded states: one
   cheap batched rollout); the screen ranks candidates apart by more than ``min_gain``, and those
   within it of the best screen are ranked by their full held-out free-run error (:func:`_judge`).
   The best is added if it lowers the full held-out free-run error by at least the factor
   ``min_gain`` (default 2: the effect must halve the error; a candidate whose parameters the data
   cannot identify is skipped), from above ``FREE_RUN_FLOOR`` (rounding).  Failing that, the candidate with the lowest
   held-out one-step error (:func:`identified.evaluate.relative_one_step_errors`: the residual wrench relative to the recorded
   one, on the rods no candidate's residual-stage effect touches) is added if it cuts that error
   by ``min_gain`` from above ``ONE_STEP_FLOOR`` without making the free run worse by ``min_gain``
   or more (on the robot with free-joint damping the exact drag, one-step error 0.022 -> 6e-14, K
   1933 -> 2000 N/m, made the contact law's free run 0.0185 -> 0.026 m: the law's own error).  The second
   test finds an effect exact where it acts whose gain the free run hides under another effect's
   inexact law (air drag on the robot: its ground contact law leaves ~3 cm over 1 s);
4. repeat until no candidate passes, or until the model with the effects chosen so far (before
   the first round: the model without effects, fitted alone first, so clean data cost one fit) leaves
   nothing to find: its equation residual on the fitted episodes is rounding relative to the forces
   (:func:`identified.fit.checks.relative_residual` below ``ROUNDING``) and its held-out one-step error
   is below ``ONE_STEP_FLOOR``.  Both are taken on the rows the joint fit uses (a residual-stage
   law's rows, the rods on the ground, aside): every candidate that is not a rival of a chosen law
   acts on those rows too, so none has a signature left there, and a further round could only add
   one by a chance halving of a rounding-level free run.  A classification candidate (the cable friction's stick / slip
   classification) left out has the classification it settled this round as one more start of
   its next round's search (a settled classification alone is not enough: the effect just added
   can change it -- on the robot, ground contact takes the rods on the ground out of the joint
   fit, and friction's classification without contact is wrong).  Each step goes into the model's ``loop`` section: the
   effect added and the held-out error before and after.

A round's fits are independent: they run side by side in ``jobs`` processes
(:mod:`identified.fit.workers`), each with its screen and its share of the one-step errors, and
the result does not depend on ``jobs``.  With more than one process, a round after one that added
an effect also makes the final fit (all the data, the effects chosen so far) beside its
candidates: if the round adds nothing, that fit is the model.

The evidence is out-of-sample: an effect absent from the plant fits to near zero on the fitted
episodes and changes the held-out error by far less than 2x, so clean data get nothing added
(measured on clean plants in tests/test_effects.py).  After the search, ``explained`` says whether
what is left is at the level of the model's own rounding or noise (one-step residual relative to
the forces below ``1e-6``, or the held-out error fell at least 5x); otherwise the residual stays
structured and no effect of the library explains it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from identified.dataset import Dataset, DatasetError
from identified.effects import (
    EFFECTS,
    Effect,
    GeometryError,
    effect_from_json,
    make_effect,
    rival,
    search_labels,
    split_label,
)
from identified.evaluate import (
    OneStepParts,
    one_step_data,
    one_step_parts,
    relative_errors_from_parts,
    rollout_errors,
    window_error,
)
from identified.fit.checks import ROUNDING, relative_residual
from identified.fit.identify import ScaleSpec, identify
from identified.fit.regression import IdentifiabilityError
from identified.fit.workers import TaskPool, resolve_jobs
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel
from identified.threads import torch_threads
from identified.topology import Topology

__all__ = ["fit_model", "one_step_evidence", "parse_effects", "search_explained", "select_effects"]
#: a held-out one-step error (relative) below this is rounding or noise-free exactness: no effect
#: is added on the evidence of the one-step error alone (the free run must then show it)
ONE_STEP_FLOOR = 1e-6
#: a held-out free-run error (m) below this is rounding (float64 states of rods a metre across,
#: run for a second): no effect is added on the evidence of a free run this good, whatever the
#: ratio (measured: exact models leave 3e-16 to 1e-15 m, and among several candidates judged by
#: their free run one could halve it by chance: cable_slack's exact model got quadratic_drag)
FREE_RUN_FLOOR = 1e-10
#: the effect search on a recording (rod states reconstructed from markers, with noise replicas)
#: fits its candidates on at most this many steps of the training takes, the middle of each take,
#: and without the replicas (no errors-in-variables correction: it moves K by a fraction of a
#: percent, far below the factor the search asks of an effect); the final fit uses all of it
RECORDING_SEARCH_STEPS = 8_000


def parse_effects(spec: str | Sequence[str]) -> str | list[str]:
    """``"none"``, ``"auto"`` or a list of effect names (from ``"a,b"``); ValueError naming a bad one."""
    if isinstance(spec, str):
        s = spec.strip()
        if s in ("none", "auto"):
            return s
        names = [x.strip() for x in s.split(",") if x.strip()]
    else:
        names = list(spec)
    if not names:
        raise ValueError("--effects: give none, auto or effect names separated by commas")
    for n in names:
        try:
            split_label(n)
        except ValueError as err:
            raise ValueError(f"--effects: {err}") from None
    if len(set(names)) != len(names):
        raise ValueError("--effects names an effect twice")
    for i, n in enumerate(names):
        other = rival(n, names[:i])
        if other is not None:
            raise ValueError(f"--effects: {other} and {n} are two laws of one thing ({EFFECTS[n.split(':')[0]].phenomenon}); "
                             "name one")
    return names


@torch_threads(1)
def fit_model(
    data: Dataset,
    mjcf: str | os.PathLike,
    effects: str | Sequence[str] = "none",
    regressors: str = "multiple",
    scale: ScaleSpec = ScaleSpec(),
    solver: str = "lstsq",
    weak_window: int | str | None = "auto",
    integrator: str | None = None,
    scheme: str | None = None,
    refine: bool = False,
    progress: bool = False,
    horizon_s: float = 1.0,
    min_gain: float = 2.0,
    jobs: int | str | None = "auto",
    hold_inertia: Sequence[tuple[int, int]] = (),
    contact_margin: int = 0,
    inertia: str = "auto",
    before_metrics: Callable[[IdentifiedModel], None] | None = None,
) -> IdentifiedModel:
    """Identify a model from ``data`` for the system of ``mjcf`` (topology and geometry only).

    ``effects``: ``"none"``, ``"auto"`` (the search of the module docstring) or effect names.
    ``integrator``: as :func:`identified.fit.identify.identify` (default ``"euler"``, ``"auto"``
    with ``refine``); MuJoCo's ``"implicitfast"`` is the engine's ``"implicit"``.
    ``jobs``: processes the effect search fits its candidates in (``"auto"``: the cores this
    process may use; :mod:`identified.fit.workers`); the model does not depend on it.
    ``inertia``: ``"auto"``, ``"full"`` (each rod's ten inertial parameters) or ``"diagonal"``,
    as :func:`identified.fit.identify.identify`.  ``before_metrics``: called with the fitted model
    before its metrics are computed (a recording's contact damping, chosen after the fit).

    Torch runs on one intra-op thread here (:mod:`identified.threads`): the fit's tensors are small
    and its parallel work runs in processes; with another process busy on a core, torch's idle
    threads spinning made ``--effects auto`` twice as slow.
    """
    mjcf = os.fspath(mjcf)
    topo = Topology.from_mjcf(mjcf)
    spec = parse_effects(effects)
    resolve_jobs(jobs)  # a bad value fails before any work
    if refine:
        from identified.fit.refine import check_refinable

        check_refinable(data)
    integ = integrator or ("auto" if refine else "euler")
    integ = "implicit" if integ == "implicitfast" else integ
    if integ == "auto":
        from identified.fit.identify import select_integrator

        integ, selection = select_integrator(data, topo, regressors, scale, weak_window)
    else:
        selection = None
    kw = {"regressors": regressors, "scale": scale, "solver": solver, "weak_window": weak_window,
          "integrator": integ, "scheme": scheme, "hold_inertia": tuple(hold_inertia),
          "contact_margin": contact_margin, "inertia": inertia}
    loop: list[dict[str, Any]] = []
    explained = None
    fixed: dict[str, dict[str, Any]] = {}
    early = None
    if spec == "auto":
        names, loop, explained, fixed, early, part = _select_effects(data, topo, mjcf, kw, horizon_s, min_gain,
                                                                     progress, jobs)
    else:
        names = [] if spec == "none" else spec
    if early is not None and early.names == names and early.fixed == fixed and early.model is not None:
        model, seconds = early.model, early.seconds  # fitted during the search's last round
    else:
        t0 = time.perf_counter()
        try:
            model = identify(data, topo, effects=_build(names, topo, mjcf, fixed), progress=progress, **kw)
        except IdentifiabilityError as err:
            if spec != "auto" or names:
                raise
            # the search added nothing and the spring-rod model alone is not identified: that is the
            # news (a robot on the ground with no contact law), not the rank error's parameter list
            raise IdentifiabilityError(
                f"--effects auto added no effect (none of its candidates ran on the held-out episodes "
                f"well enough) and without one {err}; name the effects instead, e.g. --effects ground_contact",
                err.names) from err
        seconds = time.perf_counter() - t0
    model.metrics["fit_seconds"] = round(seconds, 4)
    if selection is not None:
        model.metrics["integrator_selection"] = selection
    model.source_model = os.path.abspath(mjcf)
    model.loop = loop
    if spec == "auto":
        model.metrics["effect_search"] = {"explained": explained,
                                          "candidates": list(search_labels(markers=part is not None)),
                                          "metric": _metric(horizon_s), "min_gain": min_gain}
        if part is not None:
            model.metrics["effect_search"]["fitted_on"] = (
                f"the middle {part.n_steps * data.dt:g} s of each of {part.n_episodes} training takes, "
                "without noise replicas")
    if refine:
        from identified.fit.refine import refine as refine_model

        model = refine_model(model, data, progress=progress)
    from identified.fit.checks import refresh_physics, residual_check
    from identified.predict import attach_metrics

    refresh_physics(model)  # the checks of the final parameters (refinement moves them)
    if before_metrics is not None:
        before_metrics(model)
    attach_metrics(model, data)
    residual_check(model, data)  # a fit that does not describe its own data says so
    return model


def _metric(horizon_s: float) -> str:
    return (f"held-out free-run position error, m: mean over rods and steps of the first {horizon_s:g} s "
            "from every held-out episode's recorded initial state")


def _build(names: Sequence[str], topo: Topology, mjcf: str,
           fixed: dict[str, dict[str, Any]] | None = None) -> list[Effect]:
    """Unfitted effects by label (``name`` or ``name:variant``), with options ``fixed`` per label."""
    out = []
    for label in names:
        eff = make_effect(label, topo, mjcf)
        opts = dict((fixed or {}).get(label, {}))
        start = opts.pop("start_values", None)
        opts.pop("final_values", None)  # the final fit's start (:func:`_final_options`)
        eff.search_too = bool(opts.pop("search_too", False))
        eff.options.update(opts)
        if start is not None:  # start from a settled classification, or from fitted values
            eff.values = np.asarray(start, dtype=float)
        out.append(eff)
    return out


@dataclass(frozen=True)
class _Search:
    """What every fit of the effect search shares (a worker process inherits it)."""

    train: Dataset
    held: Dataset
    topo: Topology
    mjcf: str
    fit_kwargs: dict[str, Any]
    horizon: int  # steps of the held-out free run
    one_step: Dataset  # the held-out instants of the one-step errors (:func:`one_step_data`)
    data: Dataset  # all of it, for the final fit
    final_kwargs: dict[str, Any]  # the final fit's options
    on_part: bool  # the candidates are fitted on a part of a recording (:func:`search_part`)


@dataclass(frozen=True)
class _Final:
    """The final fit with the effects ``names`` and options ``fixed``, made during a round of the
    search beside its candidates (``None``: the data cannot identify it; fitted again, to raise)."""

    names: list[str]
    fixed: dict[str, dict[str, Any]]
    model: IdentifiedModel | None
    seconds: float


@dataclass(frozen=True)
class _Fitted:
    """One fit of the search: the model (``None``: the data cannot identify it), its screen error,
    its full free-run error (the base model's only, else NaN), its share of the held-out one-step
    errors, and the seconds it took."""

    model: IdentifiedModel | None
    screen: float
    free_run: float
    one_step: OneStepParts | None
    seconds: float


def _task(ctx: _Search, task: tuple[Any, ...]) -> _Fitted | float:
    """A task of the search's pool: ``("fit", names, fixed, base)`` -> :class:`_Fitted`;
    ``("free run", model)`` -> its held-out free-run error (:func:`_free_run`); ``("final", names,
    fixed)`` -> the final fit on all the data (:class:`_Final`)."""
    if task[0] == "free run":
        return _free_run(task[1], ctx)
    if task[0] == "final":
        t0 = time.perf_counter()
        try:
            m = identify(ctx.data, ctx.topo, effects=_build(task[1], ctx.topo, ctx.mjcf, task[2]), **ctx.final_kwargs)
        except (IdentifiabilityError, ValueError, np.linalg.LinAlgError):
            m = None
        return _Final(task[1], task[2], m, time.perf_counter() - t0)
    _, names, fixed, base = task
    t0 = time.perf_counter()
    try:
        m = identify(ctx.train, ctx.topo, effects=_build(names, ctx.topo, ctx.mjcf, fixed), **ctx.fit_kwargs)
    except (IdentifiabilityError, ValueError, np.linalg.LinAlgError):
        return _Fitted(None, float("inf"), float("inf"), None, time.perf_counter() - t0)
    screen = window_error(m, ctx.held, max(1, ctx.horizon // 10))
    free = _free_run(m, ctx) if base else float("nan")
    return _Fitted(m, screen, free, one_step_parts(m, ctx.one_step), time.perf_counter() - t0)


def _one_step_errors(ctx: _Search, parts: list[OneStepParts | None], models: list[IdentifiedModel | None]
                     ) -> list[float]:
    """The held-out relative one-step errors of ``models`` from their fits' ``parts``
    (:func:`identified.evaluate.relative_one_step_errors`: every model's accelerations formed by
    the first model's scheme; a part formed by another is formed again here)."""
    scheme = next((p.scheme for p in parts if p is not None), None)
    parts = [p if p is None or p.scheme == scheme else one_step_parts(m, ctx.one_step, scheme)
             for p, m in zip(parts, models)]
    return relative_errors_from_parts(parts)


def _free_run(m: IdentifiedModel | None, ctx: _Search) -> float:
    """The held-out free-run error (the search's metric); ``inf`` for no model or a diverged run."""
    if m is None:
        return float("inf")
    with np.errstate(over="ignore", invalid="ignore"):  # a candidate whose free run diverges
        err = float(rollout_errors(m, ctx.held, horizon=ctx.horizon)["pos_mean"])
    return err if np.isfinite(err) else float("inf")


def select_effects(
    data: Dataset,
    topo: Topology,
    mjcf: str,
    fit_kwargs: dict[str, Any],
    horizon_s: float = 1.0,
    min_gain: float = 2.0,
    progress: bool = False,
    jobs: int | str | None = "auto",
) -> tuple[list[str], list[dict[str, Any]], bool, dict[str, dict[str, Any]]]:
    """Forward selection of effects on held-out episodes (module docstring).

    Returns the chosen names, the loop record (one entry per step: ``added``, ``error_before``,
    ``error_after``, ``candidates`` with each one's held-out error), ``explained``, and the options
    a chosen effect's own search settled (the contact regulariser; the cable friction's values,
    from which its later refits start their classification), for the final fit.  A round's fits
    run side by side in ``jobs`` processes (:mod:`identified.fit.workers`; the same result).
    """
    return _select_effects(data, topo, mjcf, fit_kwargs, horizon_s, min_gain, progress, jobs)[:4]


def _select_effects(data: Dataset, topo: Topology, mjcf: str, fit_kwargs: dict[str, Any], horizon_s: float,
                    min_gain: float, progress: bool, jobs: int | str | None
                    ) -> tuple[list[str], list[dict[str, Any]], bool, dict[str, dict[str, Any]], _Final | None,
                               Dataset | None]:
    """:func:`select_effects`, the final fit made beside the last round's candidates
    (:func:`_search`), if any, and the part of a recording the candidates were fitted on.  On a
    recording whose part no candidate's fit runs on the held-out takes (each not identified, or its
    twin diverged: the robot lying still, or slowed by a drag, leaves few rows off the ground
    there), the search runs again on a part twice as long, up to all of the training takes."""
    E = data.n_episodes
    if E < 2:
        raise DatasetError("--effects auto needs at least 2 episodes (one is held out to judge each effect)")
    n_hold = max(1, E // 4)
    train = data.select(episodes=slice(0, E - n_hold))
    held = data.select(episodes=slice(E - n_hold, E))
    H = max(1, min(held.n_steps, round(horizon_s / data.dt)))
    recording = bool(train.replicas)  # rod states reconstructed from markers: fitted on a part (search_part)
    kwargs = {**fit_kwargs, "noise_copies": 0} if recording else fit_kwargs  # the part without replicas
    candidates = []
    for name in search_labels(markers=recording):
        try:
            make_effect(name.split(":")[0], topo, mjcf)
        except GeometryError:
            continue  # e.g. no ground plane: ground contact cannot be there
        candidates.append(name)
    held_instants = one_step_data(held)
    n_jobs = min(resolve_jobs(jobs), len(candidates) + 1)  # a round has at most this many fits
    total = RECORDING_SEARCH_STEPS
    while True:
        part = search_part(train, total)
        ctx = _Search(train if part is None else part, held, topo, mjcf, kwargs, H, held_instants, data,
                      fit_kwargs, recording)
        with TaskPool(_task, ctx, n_jobs) as pool:
            names, loop, explained, fixed, final, starved = _search(ctx, pool, candidates, min_gain, progress)
        if part is None or not starved or part.n_steps >= train.n_steps:
            return names, loop, explained, _final_options(ctx, fixed), final, part
        total *= 2


def _final_options(ctx: _Search, fixed: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The options the search settled that the final fit takes: on a part of a recording, what a
    profile scan settled there is scanned again on all the data; an effect that ``warm_starts``
    starts from the values of the fit that chose the model (``final_values``)."""
    out = {label: {k: v for k, v in opts.items() if not ctx.on_part or k not in EFFECTS[label.split(":")[0]].profiled}
           for label, opts in fixed.items()}
    for opts in out.values():
        if "final_values" in opts:
            opts["start_values"] = opts.pop("final_values")
    return {label: opts for label, opts in out.items() if opts}


def search_part(train: Dataset, total: int | None = None) -> Dataset | None:
    """The part of a recording's training takes the effect search fits its candidates on: the
    middle steps of each take, ``total`` in all (default :data:`RECORDING_SEARCH_STEPS`; at least
    1000 a take), without the noise replicas; ``None`` for rod states that are not reconstructed
    from markers (no replicas: the search fits on all of them).  The middle, not the start: a take
    starts as the lab started it (the robot set down, settling).  A candidate's fit needs rows of
    rods off the ground; where a part holds too few for any of them (measured: the robot in viscous
    air, 8 takes of 5 s at 100 Hz, 1 mm: with a contact law the first second of each take does not
    identify the cables' stiffnesses, two seconds do), the search takes twice as much
    (:func:`_select_effects`)."""
    if not train.replicas:
        return None
    total = RECORDING_SEARCH_STEPS if total is None else total
    steps = min(train.n_steps, max(total // max(train.n_episodes, 1), 1000))
    start = (train.n_steps - steps) // 2
    return replace(train, replicas=()).span(slice(None), start, start + steps)


def _search(ctx: _Search, pool: TaskPool, candidates: list[str], min_gain: float, progress: bool
            ) -> tuple[list[str], list[dict[str, Any]], bool, dict[str, dict[str, Any]], _Final | None, bool]:
    """The rounds of the search (module docstring); the last element says whether it was starved:
    nothing added and no candidate of its first round ran on the held-out takes (each not
    identified, or its twin diverged)."""
    # settings of a chosen effect found by its own profile scan (the contact regulariser) are kept
    # for the later rounds' refits
    fixed: dict[str, dict[str, Any]] = {}
    topo = ctx.topo

    # the slowest fits start first: the last round's time of each, else its effect's fit_cost
    cost = {name: EFFECTS[name.split(":")[0]].fit_cost for name in candidates}
    chosen: list[str] = []
    starved = False
    final: _Final | None = None
    loop: list[dict[str, Any]] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(candidates) + 1, desc="effects", unit="fit", leave=False)
    # the model without effects first: where it leaves nothing to find (clean data: its residual at
    # rounding, its held-out one-step error too), no candidate is fitted
    first = pool.map([("fit", [], dict(fixed), True)], on_done=None if bar is None else (lambda: bar.update(1)))[0]
    base_model: IdentifiedModel | None = first.model
    base_parts: OneStepParts | None = first.one_step
    base_screen, base_err = first.screen, first.free_run
    first_err = base_err
    done = exhausted(relative_residual(base_model), _one_step_errors(ctx, [base_parts], [base_model])[0])
    while not done:
        # every remaining candidate is refitted and screened by its held-out error over short
        # windows (a tenth of the horizon, many starts); the best one must then cut the full
        # held-out free-run error by min_gain
        names = [n for n in candidates if n.split(":")[0] not in {c.split(":")[0] for c in chosen}
                 and rival(n, chosen) is None]
        names.sort(key=lambda n: -cost[n])
        if not names:
            break
        tasks: list[tuple[Any, ...]] = [("fit", chosen + [n], dict(fixed), False) for n in names]
        # after a round that added an effect, the final fit with the effects chosen so far (the
        # longest task) runs beside this round's candidates: it is the model if none is added
        early = pool.jobs > 1 and bool(chosen) and bool(names)
        if early:
            tasks.insert(0, ("final", list(chosen), _final_options(ctx, fixed)))
            if bar is not None:
                bar.total += 1
        results = pool.map(tasks, on_done=None if bar is None else (lambda: bar.update(1)))
        if early:
            final = results.pop(0)
        fits = {n: r.model for n, r in zip(names, results)}
        screens = {n: r.screen for n, r in zip(names, results)}
        parts = {n: r.one_step for n, r in zip(names, results)}
        cost.update({n: r.seconds for n, r in zip(names, results)})
        one_base, *one = _one_step_errors(ctx, [base_parts] + [parts[k] for k in names],
                                          [base_model] + [fits[k] for k in names])
        ones = dict(zip(names, one))
        if not chosen and not any(np.isfinite(v) for v in screens.values()):
            starved = True  # no candidate's twin ran on the held-out takes: not identified, or diverged
            break
        best, runs = _judge(screens, base_screen, fits, ctx, min_gain, pool)
        err = runs[best]
        evidence = "free run" if halves(base_err, err, min_gain) else None
        if evidence is None and one_base > ONE_STEP_FLOOR:
            # what the free run cannot show: an effect exact where it acts, beside another effect's
            # inexact law whose error dominates the free run (drag on a robot rolling on its ground)
            alt = min(ones, key=ones.get)
            alt_err = runs[alt] if alt in runs else _free_run(fits[alt], ctx)
            if one_step_evidence(one_base, ones[alt], base_err, alt_err, min_gain):
                best, err, evidence = alt, alt_err, "one step"
        if evidence is None:
            break
        loop.append({"added": best, "evidence": evidence,
                     "error_before": finite_or_none(base_err), "error_after": finite_or_none(err),
                     "one_step_before": finite_or_none(one_base), "one_step_after": finite_or_none(ones[best]),
                     "candidates": {k: finite_or_none(v) for k, v in screens.items()},
                     "screen": f"held-out error over {max(1, ctx.horizon // 10)}-step windows (m)",
                     "one_step": {k: finite_or_none(v) for k, v in ones.items()}})
        chosen.append(best)
        base_err, base_model, base_screen, base_parts = err, fits[best], screens[best], parts[best]
        for e in base_model.effects:
            label = next(c for c in chosen if c.split(":")[0] == e["name"])
            cls = EFFECTS[e["name"]]
            settled = {k: e["parameters"][k] for k in cls.profiled if e["parameters"].get(k) is not None}
            if settled:  # what its own profile scan settled (the contact regulariser), kept
                fixed[label] = settled
            if cls.fit_strategy == "classification" or cls.warm_starts:
                values = effect_from_json(e, topo.n_rods, topo.n_springs).values.tolist()
                if cls.fit_strategy == "classification":  # later refits start from its classification
                    fixed[label] = {"start_values": values}
                if cls.warm_starts:  # the final fit starts from the values it has now (a later
                    fixed[label] = {**fixed.get(label, {}), "final_values": values}  # round's refits search afresh)
        for name, m in fits.items():
            if name != best and m is not None and EFFECTS[name.split(":")[0]].fit_strategy == "classification":
                # a classification candidate left out has this round's classification as one more start
                # of its next search: the effect just added changes which rows the fit uses (ground
                # contact: the rods on the ground leave the joint fit), and a classification settled
                # without it can be wrong
                e = next(e for e in m.effects if e["name"] == name.split(":")[0])
                fixed[name] = {"start_values": effect_from_json(e, topo.n_rods, topo.n_springs).values.tolist(),
                               "search_too": True}
        if bar is not None:
            bar.total += len(candidates) - len(chosen)
        done = exhausted(relative_residual(base_model), ones[best])
    if bar is not None:
        bar.close()
    return chosen, loop, search_explained(relative_residual(base_model), first_err, base_err), fixed, final, starved


def exhausted(relative: float | None, one_step: float) -> bool:
    """Whether a model leaves the search nothing to find: its equation residual relative to the
    forces (``relative``, on the fitted episodes) is below :data:`~identified.fit.checks.ROUNDING`
    and its held-out relative one-step error below :data:`ONE_STEP_FLOOR`."""
    return bool(relative is not None and relative < ROUNDING and np.isfinite(one_step) and one_step <= ONE_STEP_FLOOR)


def halves(before: float, after: float, min_gain: float = 2.0) -> bool:
    """The free-run evidence for an effect: the held-out free-run error falls from ``before`` to
    ``after`` by at least ``min_gain``, from above :data:`FREE_RUN_FLOOR` (rounding)."""
    return bool(np.isfinite(after) and before >= max(min_gain * after, FREE_RUN_FLOOR))


def one_step_evidence(one_before: float, one_after: float, free_before: float, free_after: float,
                      min_gain: float = 2.0) -> bool:
    """The one-step evidence for an effect: the held-out one-step error falls from ``one_before``
    (above :data:`ONE_STEP_FLOOR`) by at least ``min_gain``, and the free-run error does not grow
    from ``free_before`` by ``min_gain`` or more."""
    return bool(one_before > ONE_STEP_FLOOR and one_before >= min_gain * one_after
                and np.isfinite(free_after) and free_after <= min_gain * free_before)


def search_explained(relative: float | None, first_err: float, last_err: float) -> bool:
    """Whether what the search leaves is explained: the final model's one-step residual relative to
    the forces (``relative``) is below :data:`~identified.fit.checks.ROUNDING`, or the held-out
    free-run error fell at least 5x from the model without effects (``first_err``) to the final
    one (``last_err``), or it was 0 to begin with."""
    return bool((relative is not None and relative < ROUNDING) or (first_err > 0 and last_err <= first_err / 5)
                or first_err == 0)


def _judge(screens: dict[str, float], base_screen: float, fits: dict[str, IdentifiedModel | None], ctx: _Search,
           min_gain: float, pool: TaskPool | None = None) -> tuple[str, dict[str, float]]:
    """The round's best candidate and the full held-out free-run errors it was chosen on: of the
    candidates whose screen error is within ``min_gain`` of the best screen's and 1 % below the
    model's without them (``base_screen``), the one with the lowest free run -- the short windows cannot rank those: on
    the robot hiding cable friction, a constant force screened 0.023 m and ground contact 0.024 m,
    and their free runs were 0.60 and 0.36 m.  With none such, the best screen's.  The free runs
    run side by side in ``pool`` (:func:`_task`), else here."""
    top = min(screens.values())
    close = [n for n, v in screens.items() if np.isfinite(v) and v <= min_gain * top and v < 0.99 * base_screen]
    close = close or [min(screens, key=screens.get)]
    if pool is None:
        runs = {n: _free_run(fits[n], ctx) for n in close}
    else:
        runs = dict(zip(close, pool.map([("free run", fits[n]) for n in close])))
    best = min(close, key=lambda n: (runs[n], screens[n]))
    return best, runs
