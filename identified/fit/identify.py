"""Identify a spring-rod model from recorded rod states: the ``tensegrity fit`` pipeline.

``identify(dataset, topology)`` builds the regression features
(:mod:`identified.fit.features`), reduces them to triangular factors, fixes the global scale by
an anchor and solves (:mod:`identified.fit.regression`), optionally trains the same linear model
with the paper's Adam schedule (:mod:`identified.fit.adam`) or refines it through multi-step
rollouts (:mod:`identified.fit.refine`), and returns an :class:`~identified.model.IdentifiedModel`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from identified.dataset import Dataset, DatasetError
from identified.effects.base import Effect
from identified.engine.integration import INTEGRATORS, RodState
from identified.evaluate import recorded_samples, residual_wrench
from identified.fit.checks import (
    adam_convergence,
    apply_checks,
    check_enough_data,
    constrain_inertias,
    widen_for_overlap,
)
from identified.fit.classification import iterate_classification
from identified.fit.derivatives import default_window, weak_form
from identified.fit.features import RodColumns, chunk_context, equation_rows
from identified.fit.layout import ParameterLayout
from identified.fit.noise import with_noise_replicates
from identified.fit.regression import Anchor, IdentifiabilityError, Solution, accumulate, solve
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel
from identified.samples import iter_chunks
from identified.topology import Topology
from identified.twin import engine_from_model

__all__ = ["ScaleSpec", "check_compatible", "identify", "resolve_anchor", "select_integrator"]

SOLVERS = ("lstsq", "adam")
#: the fit's strategies an effect may declare (``Effect.fit_strategy``): its columns join the main
#: regression; the same after a classification search (:mod:`identified.fit.classification`); on the
#: joint model's residual (:func:`fit_residual_effects`)
STRATEGIES = ("joint", "classification", "residual")
@dataclass(frozen=True)
class ScaleSpec:
    """What fixes the global scale: known rod masses, a known total mass, or known pushes."""

    masses: tuple[tuple[str, float], ...] = ()
    total_mass: float | None = None
    pushes_in_newton: bool = True


def check_compatible(dataset: Dataset, topology: Topology) -> None:
    """Raise DatasetError when the data do not belong to this model (names, counts, motion)."""
    if dataset.rod_names != topology.rod_names:
        raise DatasetError(
            f"dataset rods {list(dataset.rod_names)} do not match the model's rods {list(topology.rod_names)}"
        )
    if dataset.tendon_names != topology.spring_names:
        raise DatasetError(
            f"dataset has {len(dataset.tendon_names)} tendons {list(dataset.tendon_names)[:4]}..., "
            f"the model has {topology.n_springs} {list(topology.spring_names)[:4]}...: they do not match"
        )
    moving = max(np.abs(np.diff(dataset.pos, axis=1)).max(), np.abs(np.diff(dataset.vel, axis=1)).max(),
                 np.abs(np.diff(dataset.angvel, axis=1)).max())
    if moving <= 1e-12:
        raise DatasetError("the dataset holds no motion: every rod stays still, nothing can be identified")


def resolve_anchor(
    layout: ParameterLayout, scale: ScaleSpec, has_pushes: bool
) -> tuple[Anchor, dict[int, float], dict]:
    """The anchor that fixes the scale, entries pinned by it, and how the JSON describes it."""
    fixed: dict[int, float] = {}
    names = list(layout.rod_names)
    for name, kg in scale.masses:
        if name not in names:
            raise ValueError(f"--mass names rod '{name}', which is not in the model (rods: {', '.join(names)})")
        if not kg > 0:
            raise ValueError(f"--mass {name}={kg}: a mass must be positive")
    if scale.total_mass is not None and not scale.total_mass > 0:
        raise ValueError(f"--total-mass {scale.total_mass}: a mass must be positive")
    if not has_pushes:
        fixed[layout.h] = 1.0  # no pushes in the data: h does not enter, keep the nominal 1
    if scale.masses:
        (first, kg), rest = scale.masses[0], scale.masses[1:]
        e = np.zeros(layout.n_full)
        e[layout.m(names.index(first))] = 1.0
        for name, kg2 in rest:
            fixed[layout.m(names.index(name))] = kg2
        desc = {"anchor": "mass", "rod": first, "value": kg,
                "description": f"absolute: mass of {first} known ({kg} kg)"}
        return Anchor(e, kg, desc["description"]), fixed, desc
    if scale.total_mass is not None:
        e = np.zeros(layout.n_full)
        e[[layout.m(i) for i in range(layout.n_rods)]] = 1.0
        desc = {"anchor": "total_mass", "value": scale.total_mass,
                "description": f"absolute: total rod mass known ({scale.total_mass} kg)"}
        return Anchor(e, scale.total_mass, desc["description"]), fixed, desc
    if has_pushes and scale.pushes_in_newton:
        e = np.zeros(layout.n_full)
        e[layout.h] = 1.0
        fixed.pop(layout.h, None)
        desc = {"anchor": "push", "description": "absolute: recorded pushes are in newtons (h = 1)"}
        return Anchor(e, 1.0, desc["description"]), fixed, desc
    e = np.zeros(layout.n_full)
    e[[layout.m(i) for i in range(layout.n_rods)]] = 1.0 / layout.n_rods
    desc = {
        "anchor": "normalised",
        "description": "normalised: states fix only ratios; values are scaled so that the mean rod mass is 1 kg "
        "(multiply every mass, inertia, stiffness and damping by the true mean rod mass)",
        "mean_rod_mass": 1.0,
    }
    return Anchor(e, 1.0, desc["description"]), fixed, desc


def check_strategies(effects: Sequence[Effect]) -> None:
    """ValueError naming an effect whose declared ``fit_strategy`` is not one of :data:`STRATEGIES`."""
    for e in effects:
        if e.fit_strategy not in STRATEGIES:
            raise ValueError(f"effect '{e.name}' declares fit_strategy {e.fit_strategy!r}; the fit has "
                             f"{', '.join(STRATEGIES)}")


def identify(
    dataset: Dataset,
    topology: Topology,
    regressors: str = "multiple",
    scale: ScaleSpec = ScaleSpec(),
    solver: str = "lstsq",
    weak_window: int | str | None = "auto",
    integrator: str = "euler",
    scheme: str | None = None,
    chunk_steps: int = 4096,
    progress: bool = False,
    device: str = "cpu",
    noise_copies: int = 1,
    effects: Sequence[Effect] = (),
    hold_inertia: Sequence[tuple[int, int]] = (),
    contact_margin: int = 0,
    _classified: bool = False,
    _residual_stage: bool = True,
) -> IdentifiedModel:
    """Fit K, c per spring, M, I per rod and the control scale h from rod states alone.

    ``effects``: unfitted effects (:mod:`identified.effects`) to fit with the model: ``joint``
    ones as extra regression columns, ``residual`` ones (ground contact) on the residual wrench of
    the rods they touch, whose equations the joint fit leaves out.

    ``weak_window``: sum the equations over windows of this many steps (the weak form, for noisy
    data; :mod:`identified.fit.derivatives`); ``None`` or 0: step by step (exact on clean data);
    ``"auto"``: the weak form with a ~0.3 s window when the dataset records sensor noise.
    ``integrator``: how the plant steps, and so how the identified engine will: ``"euler"``
    (MuJoCo's default), ``"implicit"`` (MuJoCo's implicit and implicitfast), ``"rk4"``, or
    ``"auto"``: chosen from the data (:func:`select_integrator`).  ``scheme``: how accelerations
    are taken from the states, ``"forward"`` (exact for euler and implicit) or ``"central"``
    (second order for any integrator; the default for rk4), :mod:`identified.samples`.
    ``hold_inertia``: (rod, body axis) moments of inertia the data cannot see (a rod whose markers
    lie on its axis never shows its axial spin): held out of the fit, reported as not identifiable.
    ``contact_margin``: steps before and after a residual-stage effect's rows that the joint fit
    leaves out too (states smoothed from sampled markers smear an impact over a few frames).
    ``noise_copies``: when the dataset records its sensor noise, this many copies of it with fresh
    noise measure the rows' noise for the errors-in-variables fit (:mod:`identified.fit.noise`,
    :mod:`identified.fit.regression`); 0 fits as if the states were exact.
    """
    if integrator == "auto":
        integrator, scores = select_integrator(dataset, topology, regressors, scale, weak_window, device)
        model = identify(dataset, topology, regressors, scale, solver, weak_window, integrator, scheme,
                         chunk_steps, progress, device, noise_copies, effects, hold_inertia, contact_margin,
                         _classified)
        model.metrics["integrator_selection"] = scores
        return model
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS + ('auto',))}, got '{integrator}'")
    check_strategies(effects)
    iterative = [e for e in effects if e.fit_strategy == "classification"]
    if iterative and not _classified:
        def fit_once(data: Dataset, residual_stage: bool, bar: bool = False) -> IdentifiedModel:
            return identify(data, topology, regressors, scale, solver, weak_window, integrator, scheme, chunk_steps,
                            bar, device, noise_copies, effects, hold_inertia, contact_margin, _classified=True,
                            _residual_stage=residual_stage)

        return iterate_classification(dataset, topology, iterative, fit_once, progress)
    scheme = scheme or ("central" if integrator == "rk4" else "forward")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got '{solver}'")
    check_compatible(dataset, topology)
    if weak_window == "auto":
        weak_window = default_window(dataset.dt) if np.any(dataset.noise > 0) else None
    weak = int(weak_window or 0)
    t0 = time.perf_counter()
    joint = [e for e in effects if e.fit_strategy != "residual"]
    late = [e for e in effects if e.fit_strategy == "residual"]
    layout = ParameterLayout.for_topology(topology, regressors, joint)
    has_pushes = bool(np.any(dataset.push_force != 0))
    anchor, fixed, scale_desc = resolve_anchor(layout, scale, has_pushes)
    fixed.update(_pinned(joint, layout))
    fixed.update({layout.inertia(i, a): 0.0 for i, a in hold_inertia})  # a zero column: its value is moot
    gravity = torch.as_tensor(dataset.gravity, dtype=torch.float64, device=device)

    columns = RodColumns.build(topology, layout)
    implicit_dt = dataset.dt if integrator == "implicit" else None

    bar = _progress(progress, dataset.n_episodes * dataset.n_steps, "features")

    def runs(data: Dataset, primary: bool = True) -> Iterator[tuple[torch.Tensor, int]]:
        """The rows of ``data`` per chunk, with the number of episodes (independent runs) in it."""
        for ch, n_ep in iter_chunks(data, chunk_steps, scheme, device=device):
            if late:  # rods touched by a residual-stage effect are fitted in the second stage
                hit = _affected(late, topology, ch)
                keep = ~(_dilate(hit, n_ep, contact_margin) if contact_margin else hit)
                ch.row_weight = keep.to(ch.pos.dtype) * (1.0 if ch.row_weight is None else ch.row_weight)
            A = equation_rows(topology, columns, ch, gravity, implicit_dt, joint, dt=dataset.dt)
            # steps, counted once (not for the noisy copies; Adam makes 30 passes)
            if primary and bar is not None and bar.n < bar.total:
                bar.update(ch.pos.shape[0])
            yield (weak_form(A, n_ep, weak) if weak > 1 else A), n_ep

    def rows() -> Iterator[torch.Tensor]:
        return (A for A, _ in runs(dataset))

    # the factor updates are many small LAPACK calls: one BLAS thread each is faster than a team
    # (and far faster on a shared, loaded machine); torch keeps its threads for the features
    with threadpool_limits(1, user_api="blas"):
        if solver == "lstsq":
            factors = accumulate(with_noise_replicates(runs, dataset, noise_copies), columns, layout.n_full)

            def solve_holding(f: dict[int, float]) -> Any:
                """Solve; parameters of an iterative effect the data cannot identify are held
                (:meth:`Effect.hold`) and the same rows solved again."""
                for _ in range(3):
                    try:
                        return solve(factors, layout, anchor, f)
                    except IdentifiabilityError as err:
                        if not any(e.hold(err.names, topology) for e in iterative):
                            raise
                        f = {**f, **_pinned(joint, layout)}
                return solve(factors, layout, anchor, f)

            sol = solve_holding(fixed)
            fixed.update(_pinned(joint, layout))
            not_estimable = check_enough_data(sol, dataset.n_episodes * dataset.n_steps, weak)
            sol, notes, held = constrain_inertias(sol, solve_holding,
                                                  layout.inertia, layout.n_rods, layout.rod_names, fixed)
            sol = widen_for_overlap(sol, weak)
        else:
            from identified.fit.adam import adam_solve

            sol = adam_solve(rows, columns, layout, anchor, fixed)
            not_estimable, held = check_enough_data(sol, dataset.n_episodes * dataset.n_steps, weak), []
            notes = adam_convergence(sol, solve(accumulate(runs(dataset, False), columns, layout.n_full),
                                                layout, anchor, fixed))
    if bar:
        bar.close()
    elapsed = time.perf_counter() - t0
    model = _to_model(topology, layout, sol, dataset, scale_desc, has_pushes, regressors, solver, elapsed)
    model.integrator = integrator
    if hold_inertia:  # before the residual stage: its engine divides by every moment
        _mark_unobservable(model, hold_inertia)
    if late and _residual_stage:
        model.metrics["residual_stage"] = fit_residual_effects(model, dataset, late, scheme, device)
    apply_checks(model, sol, not_estimable, held, notes, weak)
    model.metrics["weak_window"] = weak if weak > 1 else None
    model.metrics["scheme"] = scheme
    model.metrics["integrator"] = integrator
    model.metrics["stderr"] = sol.covariance or None
    model.metrics["errors_in_variables"] = sol.errors_in_variables
    return model


def _mark_unobservable(model: IdentifiedModel, held: Sequence[tuple[int, int]]) -> None:
    """Held moments of inertia: a placeholder the twin can step with (1e-3 of the rod's largest
    identified moment, or the difference of the other two if larger, so that the three remain a
    rigid body's), no standard error, and the list in ``metrics.not_identifiable``."""
    names = model.metrics.setdefault("not_identifiable", [])
    for i, a in held:
        others = [model.inertia[i, b] for b in range(3) if (i, b) not in held]
        spread = abs(others[0] - others[1]) if len(others) == 2 else 0.0  # keeps the triangle inequality
        model.inertia[i, a] = max(1e-3 * max(max(others, default=1.0), 1e-12), 1.001 * spread)
        if "inertia" in model.stderr:
            model.stderr["inertia"][i, a] = np.nan
        names.append(f"{model.topology.rods[i].name}: moment of inertia about body axis {'xyz'[a]} "
                     "(its spin is not observable)")


def _pinned(joint: Sequence[Effect], layout: ParameterLayout) -> dict[int, float]:
    """The effects' held parameters (:meth:`Effect.pinned`) as fixed values by layout index."""
    out = {}
    for k, e in enumerate(joint):
        held = e.pinned_values()
        out.update({layout.effect_offset(k) + int(p): float(held[p]) for p in np.flatnonzero(e.pinned())})
    return out


def _dilate(mask: torch.Tensor, n_episodes: int, margin: int) -> torch.Tensor:
    """(N, R) bool over (episode, time) rows: true also within ``margin`` steps of a true row."""
    N, R = mask.shape
    x = mask.reshape(n_episodes, N // n_episodes, R).permute(0, 2, 1).reshape(-1, 1, N // n_episodes)
    y = torch.nn.functional.max_pool1d(x.to(torch.float32), 2 * margin + 1, stride=1, padding=margin) > 0.5
    return y.reshape(n_episodes, R, -1).permute(0, 2, 1).reshape(N, R)


def _affected(late: Sequence[Effect], topology: Topology, ch: Any) -> torch.Tensor:
    """(N, R) bool: rods whose equations hold a residual-stage effect's force."""
    ctx = chunk_context(topology, ch)
    state = RodState(ch.pos, ch.quat, ch.vel, ch.angvel)
    out = torch.zeros(ch.pos.shape[:2], dtype=torch.bool, device=ch.pos.device)
    for e in late:
        out |= e.rows_affected(state, ctx)
    return out


def fit_residual_effects(model: IdentifiedModel, dataset: Dataset, late: Sequence[Effect], scheme: str = "forward",
                         device: str = "cpu", max_steps: int = 200_000) -> dict[str, Any]:
    """Second stage: fit residual-stage effects (ground contact) on what the joint model leaves.

    The jointly fitted model (its spring-rod parameters and joint effects) gives, at every
    recorded state, the wrench of every other force and the accelerations it alone would cause;
    the rest of the recorded wrench ``M (a - g)``, ``R (I α_b + ω_b × I ω_b)`` is the residual the
    effect's law is fitted to (on the rods it touches).  Appends each fitted effect to
    ``model.effects`` and returns per-effect fit statistics.
    """
    E = dataset.n_episodes
    per = max(1, min(E, max_steps // max(dataset.n_steps, 1)))
    data = dataset.select(episodes=slice(0, per)) if per < E else dataset
    ch, n_ep, push_point = recorded_samples(data, scheme, device=device)
    groups = np.repeat(np.arange(n_ep), ch.pos.shape[0] // n_ep)
    state = RodState(ch.pos, ch.quat, ch.vel, ch.angvel)
    with torch.no_grad():
        rw = residual_wrench(engine_from_model(model, dtype=torch.float64, device=device), ch, push_point)
        force, torque = rw.missing_world()
        terms = rw.terms
        ctx = terms.ctx._replace(base_lin_acc=terms.lin_acc, base_ang_acc_body=terms.ang_acc_body)
        stats = {}
        for e in late:
            rows = e.rows_affected(state, ctx)
            stats[e.name] = e.fit_residual(state, ctx, force, torque, groups, rows)
            model.effects.append(e.to_json())
    return stats


def select_integrator(
    dataset: Dataset,
    topology: Topology,
    regressors: str = "multiple",
    scale: ScaleSpec = ScaleSpec(),
    weak_window: int | str | None = "auto",
    device: str = "cpu",
    max_steps: int = 20000,
) -> tuple[str, dict[str, float]]:
    """Which integrator's equations fit the data best: the plant's own, when it is one of them.

    Fits every candidate of :data:`INTEGRATORS` on a part of the data (up to ``max_steps``
    steps) and compares their equation residuals (translation and rotation RMS, each relative to
    the best candidate's, summed).  On clean data the plant's integrator leaves a residual at
    rounding level and the others ``O(dt)``; noise narrows the margin but not the order.
    Returns the winner and every candidate's score (1 per residual kind at best, so 2 = best).
    """
    per = max(1, max_steps // max(dataset.n_episodes, 1))
    steps = min(dataset.n_steps, max(per, 64))
    episodes = slice(0, max(1, min(dataset.n_episodes, max_steps // steps)))
    part = dataset.select(episodes=episodes, steps=steps)
    res = {}
    for name in INTEGRATORS:
        fit = identify(part, topology, regressors, scale, "lstsq", weak_window, name)
        rms = fit.metrics["equation_residual_rms"]
        res[name] = (rms["translation"] or np.inf, rms["rotation"] or np.inf)
    best = [max(min(r[k] for r in res.values()), 1e-300) for k in range(2)]
    scores = {n: float(r[0] / best[0] + r[1] / best[1]) for n, r in res.items()}
    return min(scores, key=scores.get), scores


def _to_model(
    topology: Topology,
    layout: ParameterLayout,
    sol: Solution,
    dataset: Dataset,
    scale_desc: dict,
    has_pushes: bool,
    regressors: str,
    solver: str,
    elapsed: float,
) -> IdentifiedModel:
    S, R = topology.n_springs, topology.n_rods
    th = sol.theta
    se = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None)) if sol.cov is not None else None
    k_idx, c_idx = np.arange(S), S + np.arange(S)
    m_idx = np.array([layout.m(i) for i in range(R)])
    i_idx = np.array([[layout.inertia(i, a) for a in range(3)] for i in range(R)])
    stderr: dict[str, np.ndarray] = {}
    if se is not None:
        stderr = {"stiffness": se[k_idx], "damping": se[c_idx], "mass": se[m_idx], "inertia": se[i_idx]}
        if has_pushes:
            stderr["control_scale"] = np.array(se[layout.h])
    metrics = {
        "solver": solver,
        "regressors": regressors,
        "fit_seconds": round(elapsed, 4),
        "data": {
            "episodes": dataset.n_episodes,
            "steps_per_episode": dataset.n_steps,
            "steps": dataset.n_episodes * dataset.n_steps,
            "equations": sol.rows,
            "free_parameters": sol.free,
            "noise": dataset.noise.tolist(),
        },
        "equation_residual_rms": {"translation": finite_or_none(np.mean(sol.residual_rms[0::2])),
                                  "rotation": finite_or_none(np.mean(sol.residual_rms[1::2]))},
        "condition_number": finite_or_none(sol.condition),
    }
    if not has_pushes:
        scale_desc = dict(scale_desc, control_scale="not identified: no pushes in the data (kept at 1)")
    effects = []
    for k, e in enumerate(layout.effects):
        sl = layout.effect_slice(k)
        e.values = th[sl].copy()
        e.stderr = None if se is None else se[sl].copy()
        effects.append(e.to_json())
    return IdentifiedModel(
        effects=effects,
        topology=topology,
        stiffness=th[k_idx],
        damping=th[c_idx],
        rest_length=dataset.rest_length.mean(axis=(0, 1)),
        mass=th[m_idx],
        inertia=th[i_idx],
        control_scale=float(th[layout.h]),
        dt=dataset.dt,
        gravity=dataset.gravity.copy(),
        stderr=stderr,
        scale=scale_desc,
        metrics=metrics,
    )


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="step", leave=False)
