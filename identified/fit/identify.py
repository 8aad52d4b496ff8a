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
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from identified.dataset import Dataset, DatasetError
from identified.effects.base import Effect
from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.engine.integration import INTEGRATORS, RodState
from identified.evaluate import model_inputs, recorded_samples, residual_wrench
from identified.fit.actuation import FILTERS, activation_dataset, step_time_constant
from identified.fit.checks import (
    adam_convergence,
    apply_checks,
    check_enough_data,
    constrain_inertias,
    constrain_rigid_bodies,
    refuse_too_few_equations,
    widen_for_overlap,
)
from identified.fit.classification import iterate_classification
from identified.fit.derivatives import default_window, weak_form, weak_rows, weak_stride
from identified.fit.features import RodColumns, chunk_context, effect_rows, equation_rows, fit_context
from identified.fit.layout import ParameterLayout
from identified.fit.noise import has_noise, with_noise_replicates
from identified.fit.regression import (
    Anchor,
    IdentifiabilityError,
    Solution,
    accumulate,
    free_parameters,
    solve,
)
from identified.fit.uncertainty import MIN_BLOCK_SECONDS, MIN_BLOCK_WINDOWS, MIN_RUNS, blocks_per_run
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel, rigid_body_from_regression, unseen_moment
from identified.samples import iter_chunks, run_steps
from identified.topology import Topology
from identified.twin import engine_from_model

__all__ = ["ScaleSpec", "check_compatible", "dilate_rows", "identify", "resolve_anchor", "select_integrator"]

SOLVERS = ("lstsq", "adam")
#: a rod's inertial parameters: all ten, the diagonal model, or chosen from the topology
INERTIA = ("auto", "full", "diagonal")
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
    inertia: str = "auto",
    _release: str | None = None,
    _rows_cache: dict | None = None,
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
    lie on its axis never shows its axial spin): held out of the fit, reported as not identifiable; the
    rotation equation about that axis holds the unseen spin's acceleration and is left out.
    ``contact_margin``: steps before and after a residual-stage effect's rows that the joint fit
    leaves out too (states smoothed from sampled markers smear an impact over a few frames).
    ``noise_copies``: when the dataset records its sensor noise, this many copies of it with fresh
    noise measure the rows' noise for the errors-in-variables fit (:mod:`identified.fit.noise`,
    :mod:`identified.fit.regression`); 0 fits as if the states were exact.
    ``inertia``: ``"full"`` identifies every rod's ten inertial parameters (mass, centre of mass
    in the rod frame, the full inertia tensor: :mod:`identified.fit.layout`), ``"diagonal"`` takes
    the rod frame at the centre of mass along the principal axes (the paper's ``M, Ixx, Iyy,
    Izz``), ``"auto"``: full for a topology with a composite rod (a rod of several bodies, whose
    centre of mass and axes the frame does not give) unless the integrator is the implicit one.
    """
    if inertia not in INERTIA:
        raise ValueError(f"inertia must be one of {', '.join(INERTIA)}, got '{inertia}'")
    if integrator == "auto":
        integrator, scores = select_integrator(dataset, topology, regressors, scale, weak_window, device)
        model = identify(dataset, topology, regressors, scale, solver, weak_window, integrator, scheme,
                         chunk_steps, progress, device, noise_copies, effects, hold_inertia, contact_margin,
                         _classified, inertia=inertia)
        model.metrics["integrator_selection"] = scores
        return model
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS + ('auto',))}, got '{integrator}'")
    check_strategies(effects)
    iterative = [e for e in effects if e.fit_strategy == "classification"]
    if iterative and not _classified:
        cache: dict = {}  # the passes' rows but the iterative effects' columns (:func:`_cached_runs`)

        def fit_once(data: Dataset, residual_stage: bool, bar: bool = False) -> IdentifiedModel:
            return identify(data, topology, regressors, scale, solver, weak_window, integrator, scheme, chunk_steps,
                            bar, device, noise_copies, effects, hold_inertia, contact_margin, _classified=True,
                            _residual_stage=residual_stage, inertia=inertia, _rows_cache=cache)

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
    forces = topology.force_actuators
    use_act = bool(forces) and all(a.name in dataset.actuator_names for a in forces)
    chosen = inertia == "auto"
    if chosen:
        inertia = "full" if integrator != "implicit" and any(len(r.bodies) > 1 for r in topology.rods) else "diagonal"
    if inertia == "full" and _release is None:
        # the centres of mass and products released after a first diagonal solve, else held from
        # none; when neither fits (the data cannot separate them), the diagonal model (for "auto")
        again = {"regressors": regressors, "scale": scale, "solver": solver, "weak_window": weak_window,
                 "integrator": integrator, "scheme": scheme, "chunk_steps": chunk_steps, "progress": progress,
                 "device": device, "noise_copies": noise_copies, "effects": effects, "hold_inertia": hold_inertia,
                 "contact_margin": contact_margin, "_classified": _classified, "_residual_stage": _residual_stage,
                 "_rows_cache": _rows_cache}
        err: IdentifiabilityError | None = None
        for release in ("after_first", "from_start"):
            try:
                return identify(dataset, topology, inertia="full", _release=release, **again)
            except IdentifiabilityError as exc:
                err = exc
        if not chosen:
            raise err  # type: ignore[misc]
        model = identify(dataset, topology, inertia="diagonal", **again)
        model.metrics["warnings"].insert(0, f"the rods' centres of mass and products of inertia were not identified "
                                            f"(with them {err}): the diagonal model")
        return model
    layout = ParameterLayout.for_topology(topology, regressors, joint, rest_lengths=True, actuators=use_act,
                                          full_inertia=inertia == "full")
    has_pushes = bool(np.any(dataset.push_force != 0))
    anchor, fixed, scale_desc = resolve_anchor(layout, scale, has_pushes)
    fixed.update(_pinned(joint, layout))
    # an actuated cable's rest length is its command (an input): its preload column stays empty
    passive = np.array([not s.actuated for s in topology.springs], dtype=bool)
    fixed.update({layout.preload(j): 0.0 for j in np.flatnonzero(~passive)})
    if layout.rest_steps:  # a step only where the law that reads the rest length may act
        reader = next(k for k, e in enumerate(joint) if e.reads_rest_length)
        acts = passive & ~np.asarray(joint[reader].pinned(), dtype=bool)[: topology.n_springs]
        fixed.update({layout.rest_step(j): 0.0 for j in np.flatnonzero(~acts)})
    # passive rest lengths: the fit's own estimate, never the recorded values (the recorded column
    # of a passive spring is replaced before any feature is built); 0 at first (every cable taut)
    rest_estimate = np.zeros(topology.n_springs)
    # MuJoCo tendon actuators: gain and bias linear, a filter's time constant by Gauss-Newton
    # steps from 20 dt (identified.fit.actuation); a motor has no bias, only filters a time constant
    act_by_name = {a.name: a for a in topology.actuators}
    dynamics = [act_by_name[n].dynamics for n in layout.actuators]
    filters = np.isin(np.array(dynamics, dtype=object), FILTERS).astype(bool)
    tau = np.where(filters, 20.0 * dataset.dt, 0.0)
    for a, n in enumerate(layout.actuators):
        if act_by_name[n].kind == "motor":
            fixed[layout.bias(a)] = 0.0
        if not filters[a]:
            fixed[layout.gain_dtau(a)] = 0.0
    src = {"data": activation_dataset(dataset, layout.actuators, dynamics, tau) if layout.actuators else dataset}
    fixed.update({layout.inertia(i, a): 0.0 for i, a in hold_inertia})  # a zero column: its value is moot
    # the rotation equations about those axes: (rods, equations) of :func:`equation_rows`' rows
    spin_rows = ([i for i, _ in hold_inertia], [3 + a for _, a in hold_inertia]) if hold_inertia else None
    gravity = torch.as_tensor(dataset.gravity, dtype=torch.float64, device=device)

    if _rows_cache is not None:  # the same data in every pass of a classification
        if _rows_cache.get("lengths", (None,))[0] is not dataset:
            _rows_cache["lengths"] = (dataset, mean_lengths(dataset, topology))
        length_ref = _rows_cache["lengths"][1]
    else:
        length_ref = mean_lengths(dataset, topology)
    columns = RodColumns.build(topology, layout, length_ref)
    implicit_dt = dataset.dt if integrator == "implicit" else None

    bar = _progress(progress, dataset.n_episodes * dataset.n_steps, "features")

    # the passes of a classification (:mod:`identified.fit.classification`) fit the same rows but
    # the columns of the effects it iterates: the rest is kept between passes (:func:`_cached_runs`)
    iterating = [k for k, e in enumerate(joint) if e.fit_strategy == "classification"]
    cacheable = (_rows_cache is not None and bool(iterating) and solver == "lstsq"
                 and not any(joint[k].reads_rest_length for k in iterating)
                 and _cache_bytes(dataset, columns, weak) <= CACHE_BYTES and (noise_copies <= 0 or not has_noise(dataset)))

    def runs(data: Dataset, primary: bool = True) -> Iterator[tuple[torch.Tensor, int]]:
        """The rows of ``data`` per chunk, with the number of episodes (independent runs) in it."""
        if cacheable and primary:
            key = ("rows", columns.full.tobytes(), None if columns.length_ref is None else columns.length_ref.tobytes(), rest_estimate.tobytes(),
                   weak, scheme, chunk_steps, contact_margin, implicit_dt, tuple(e.name for e in joint))
            chunks = _cached_runs(_rows_cache, key, data, fresh_runs(data, True), topology, columns, joint,
                                  iterating, weak, dataset.dt, bar)
        else:
            chunks = fresh_runs(data, primary)
        for A, n_ep in chunks:
            if spin_rows:  # the equation of a spin the data cannot see holds that unknown spin's
                # acceleration: it constrains nothing (and its rows, the reconstruction's round-off,
                # would carry weights of ~1e9 into the standard errors): left out, also after a
                # classification's pass added its effects' columns to the kept rows
                A[:, spin_rows[0], spin_rows[1]] = 0.0
            yield A, n_ep

    def fresh_runs(data: Dataset, primary: bool = True) -> Iterator[tuple[torch.Tensor, int]]:
        """:func:`runs` computed afresh."""
        base = cacheable and primary  # the rows without the iterative effects' columns, and the chunk
        for ch, n_ep in iter_chunks(data, chunk_steps, scheme, device=device, min_steps=weak):
            ch.rest = _with_estimate(ch.rest, passive, rest_estimate)
            if late:  # rods touched by a residual-stage effect are fitted in the second stage
                hit = _affected(late, topology, ch)
                keep = ~(dilate_rows(hit, n_ep, contact_margin) if contact_margin else hit)
                ch.row_weight = keep.to(ch.pos.dtype) * (1.0 if ch.row_weight is None else ch.row_weight)
            fitted = [None if base and k in iterating else e for k, e in enumerate(joint)]
            A = equation_rows(topology, columns, ch, gravity, implicit_dt, fitted, dt=dataset.dt)
            # steps, counted once (not for the noisy copies; Adam makes 30 passes)
            if primary and bar is not None and bar.n < bar.total:
                bar.update(ch.pos.shape[0])
            A = weak_form(A, n_ep, weak) if weak > 1 else A
            yield ((A, ch) if base else A), n_ep

    def rows() -> Iterator[torch.Tensor]:
        return (A for A, _ in runs(src["data"]))

    cut = run_blocks(dataset, chunk_steps, scheme, weak)  # fewer than MIN_RUNS runs: blocks of them
    # the factor updates are many small LAPACK calls: one BLAS thread each is faster than a team
    # (and far faster on a shared, loaded machine); torch keeps its threads for the features
    with threadpool_limits(1, user_api="blas"):
        if solver == "lstsq":
            factors = accumulate(with_noise_replicates(runs, src["data"], noise_copies), columns, layout.n_full, **cut)

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

            def solve_separating(f: dict[int, float]) -> Any:
                """Solve; an actuator's constant bias on a cable taut in every row of the current
                classification is the same column as that cable's preload: held at 0 in ``f``
                (absorbed into its rest length), noted in ``absorbed``."""
                try:
                    return solve_holding(f)
                except IdentifiabilityError as err:
                    hit = [a for a, n in enumerate(layout.actuators) if f"{n}.bias" in err.names
                           and layout.bias(a) not in f]
                    if not hit:
                        raise
                    for a in hit:
                        f[layout.bias(a)] = 0.0
                        absorbed.append(layout.actuators[a])
                    return solve_separating(f)

            # the biases absorbed by the latest classification: the first one takes every cable taut
            # (no rest length estimated yet), so a bias is held there and released with the estimate
            absorbed: list[str] = []
            biases = {layout.bias(a) for a in range(len(layout.actuators))}
            # a law that switches at a passive spring's rest length (Effect.reads_rest_length) has
            # empty columns while the estimate is 0 (every cable taut): held at 0 in the first solve,
            # released once the rest lengths are estimated
            rest_law = [i for k, e in enumerate(joint) if e.reads_rest_length
                        for i in range(layout.effect_slice(k).start, layout.effect_slice(k).stop) if i not in fixed]
            # and so has its rest-length step (the Gauss-Newton column in the estimate)
            steps = [layout.rest_step(j) for j in range(topology.n_springs)] if layout.rest_steps else []
            rest_law += [i for i in steps if i not in fixed]
            names = layout.full_names
            # the full inertia's first moments and products are held at 0 in the first solve too (the
            # diagonal model classifies the cables' taut rows by a sound first estimate of their rest
            # lengths), then released with the rest lengths' estimate
            released = [j for i in range(layout.n_rods) for j in _inertial_extras(layout, i)
                        if j not in fixed] if layout.full_inertia and _release == "after_first" else []

            def solve_classified(f: dict[int, float], hold: Sequence[int] = ()) -> Any:
                """Solve with ``hold`` at 0; such a parameter whose spring has no row on the other
                side of the current estimate (an empty column) is held at 0 for this
                classification only. What the solve holds for good (a bias) is kept in ``f``."""
                held = {**f, **{i: 0.0 for i in hold}}
                unseen.clear()
                absorbed.clear()
                absorbed_now = {i for i in biases if i not in f}
                for _ in range(3):
                    try:
                        sol = solve_separating(held)
                        break
                    except IdentifiabilityError as err:
                        hit = [i for i in rest_law if names[i] in err.names and i not in held]
                        if not hit:
                            raise
                        held.update({i: 0.0 for i in hit})
                        unseen.extend(hit)
                else:
                    sol = solve_separating(held)
                f.update({i: v for i, v in held.items() if i not in rest_law and i not in released
                          and i not in absorbed_now})
                return sol

            unseen: list[int] = []  # held by the last classification: no row on the other side

            try:
                sol = solve_classified(fixed, hold=rest_law + released)
            except IdentifiabilityError:  # too few equations is the cause to name, when it is one
                refuse_too_few_equations(sum(factors.rows), free_parameters(layout, anchor, fixed),
                                         dataset.n_episodes * dataset.n_steps, weak)
                raise
            # a passive cable is taut while longer than its rest length: classify the rows by the
            # estimate and fit again until the rest lengths settle (exact once the classes are)
            # and step the filters' time constants until they settle too
            # a spring an effect's law switches at its rest length (cable_slack) is reclassified too
            slack = passive & (topology.pull_only | any(e.reads_rest_length for e in joint))
            U = len(layout.actuators)
            # a bias absorbed by a settled classification puts the estimate at ``l0 + b / K``, below
            # the rest length for a bias that tightens the cable: the rows between stay taut and
            # the bias inseparable. Probed once from above (a low quantile of the cable's lengths),
            # the classification settles again; the probe is kept if it fits the rows better. A bias
            # the probe separates only by the row at the estimate itself (the cable's shortest length
            # in the fitted rows: any l0 at or below it fits as well) is no evidence: held at 0
            before_probe: dict[str, Any] | None = None
            held_bias: list[str] = []
            for it in range(REST_ITERATIONS if (slack.any() or filters.any() or released) else 0):
                new = _rest_from(sol.theta, layout, passive, columns.length_ref)
                # a cable whose stiffness the rows leave indistinguishable from 0 never pulled: none of
                # its rows is taut (its columns vanish, and the solve names it as unidentifiable)
                if sol.cov is not None:
                    k_i = layout.k(np.arange(topology.n_springs))
                    k_se = np.sqrt(np.clip(np.diag(sol.cov)[k_i], 0.0, None))
                    new[slack & topology.pull_only & ~(sol.theta[k_i] > 3.0 * k_se)] = np.inf
                # a spring a law reads the rest length of (declared two-sided) is always attached: an
                # estimate the solve cannot give (its K indistinguishable from 0 while the law is
                # held) keeps the last one; the law's columns would be infinite at l0 = inf
                reader = slack & ~topology.pull_only & ~np.isfinite(new)
                new[reader] = rest_estimate[reader]
                change = np.where(new == rest_estimate, 0.0, np.abs(new - rest_estimate))[slack]
                size = max(np.max(np.abs(new[np.isfinite(new)]), initial=0.0), 1e-12)
                settled = not slack.any() or bool(np.max(change) <= REST_TOL * size)
                rest_estimate[passive] = new[passive]
                if filters.any():
                    th = sol.theta
                    tau_new = step_time_constant(tau, th[layout.gain(np.arange(U))], th[layout.gain_dtau(np.arange(U))],
                                                 dynamics, dataset.dt)
                    settled &= bool(np.all(np.abs(tau_new - tau)[filters] <= TAU_TOL * tau[filters]))
                    tau = tau_new
                    src["data"] = activation_dataset(dataset, layout.actuators, dynamics, tau)
                probe = [topology.spring_names.index(act_by_name[n].tendon) for n in absorbed]
                probe = [j for j in probe if passive[j] and topology.pull_only[j]]
                if settled and before_probe is None and probe:
                    before_probe = {"sol": sol, "factors": factors, "rest": rest_estimate.copy(), "tau": tau,
                                    "absorbed": list(absorbed), "unseen": list(unseen)}
                    low = np.quantile(recorded_lengths(dataset, topology)[:, probe], PROBE_QUANTILE, axis=0)
                    rest_estimate[probe] = np.maximum(rest_estimate[probe], low)
                    settled = False
                elif settled and before_probe is not None and "shortest" not in before_probe:
                    separated = [n for n in before_probe["absorbed"] if n not in absorbed]
                    js = [topology.spring_names.index(act_by_name[n].tendon) for n in separated]
                    before_probe["shortest"] = shortest = fitted_min_lengths(
                        src["data"], topology, late, js, scheme, chunk_steps, device, contact_margin)
                    edge = [(n, j) for n, j, x in zip(separated, js, shortest)
                            if rest_estimate[j] <= x + REST_EDGE * abs(rest_estimate[j])]
                    for n, j in edge:
                        fixed[layout.bias(layout.actuators.index(n))] = 0.0
                        held_bias.append(n)
                        rest_estimate[j] = before_probe["rest"][j]
                    settled = not edge
                if settled and (it > 0 or not released):  # the released inertia solved at least once
                    break
                factors = accumulate(with_noise_replicates(runs, src["data"], noise_copies), columns, layout.n_full, **cut)
                sol = solve_classified(fixed)
            if before_probe is not None and _misfit(sol) >= _misfit(before_probe["sol"]):
                sol, factors, tau = before_probe["sol"], before_probe["factors"], before_probe["tau"]
                rest_estimate[:] = before_probe["rest"]
                absorbed[:], unseen[:] = before_probe["absorbed"], before_probe["unseen"]
                if filters.any():
                    src["data"] = activation_dataset(dataset, layout.actuators, dynamics, tau)
            if rest_law and layout.rest_steps:  # the settled estimate: its steps held at 0, solved once more
                fixed.update({i: 0.0 for i in steps})
                factors = accumulate(with_noise_replicates(runs, src["data"], noise_copies), columns, layout.n_full, **cut)
                sol = solve_classified(fixed)
            fixed.update({layout.bias(layout.actuators.index(n)): 0.0 for n in absorbed})  # held for good
            absorbed += [n for n in held_bias if n not in absorbed]
            tau_se = np.zeros(U)
            if filters.any():  # the last step's spread, then the fit at the settled time constants
                g_i, d_i = layout.gain(np.arange(U)), layout.gain_dtau(np.arange(U))
                tau_se = np.where(filters, np.sqrt(np.clip(np.diag(sol.cov)[d_i], 0, None)) / np.abs(sol.theta[g_i]),
                                  0.0) if sol.cov is not None else np.full(U, np.nan)
                fixed.update({layout.gain_dtau(a): 0.0 for a in np.flatnonzero(filters)})
                factors = accumulate(with_noise_replicates(runs, src["data"], noise_copies), columns, layout.n_full, **cut)
                sol = solve_separating(fixed)
            fixed.update(_pinned(joint, layout))
            not_estimable = check_enough_data(sol, dataset.n_episodes * dataset.n_steps, weak)
            rigid: list[str] = []
            if layout.full_inertia:  # first: a rod that is no rigid body gets the diagonal model
                sol, rigid, held_rigid = constrain_rigid_bodies(sol, solve_holding, layout, fixed)
            sol, notes, held = constrain_inertias(sol, solve_holding,
                                                  layout.inertia, layout.n_rods, layout.rod_names, fixed)
            notes = rigid + notes
            held = held_rigid + held if layout.full_inertia else held
            sol = widen_for_overlap(sol, weak)
        else:
            from identified.fit.adam import adam_solve

            absorbed = []
            sol = adam_solve(rows, columns, layout, anchor, fixed)
            tau_se = np.full(len(layout.actuators), np.nan)  # Adam: the start, not searched
            not_estimable, held = check_enough_data(sol, dataset.n_episodes * dataset.n_steps, weak), []
            notes = adam_convergence(sol, solve(accumulate(runs(dataset, False), columns, layout.n_full),
                                                layout, anchor, fixed))
    if bar:
        bar.close()
    elapsed = time.perf_counter() - t0
    model = _to_model(topology, layout, sol, dataset, scale_desc, has_pushes, regressors, solver, elapsed,
                      columns.length_ref)
    model.integrator = integrator
    if solver == "lstsq" and unseen:
        _mark_unseen(model, layout, unseen)
    model.actuators = _actuators_json(layout, sol, act_by_name, dynamics, tau, tau_se, topology)
    for a in model.actuators:
        if a["name"] in absorbed:
            a["bias"], a["bias_stderr"] = 0.0, None
            a["note"] = (f"its constant bias is not separable from the rest length of '{a['tendon']}' (the cable "
                         "never went slack in the data): held at 0, the rest length holds it")
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


def run_blocks(dataset: Dataset, chunk_steps: int, scheme: str, weak: int) -> dict[str, Any]:
    """How :func:`~identified.fit.regression.accumulate` cuts the independent runs of ``dataset``
    (:func:`identified.samples.run_steps`) for the error bars: ``{"blocks": k, "clusters": what}``.
    With fewer than ``MIN_RUNS`` runs, each is cut into the fewest consecutive blocks that make
    ``MIN_RUNS`` in all, each spanning at least ``MIN_BLOCK_SECONDS`` and ``MIN_BLOCK_WINDOWS``
    weak-form windows (:mod:`identified.fit.uncertainty`); ``k`` = 1 when no cut is needed or
    the runs are too short for one."""
    steps = run_steps(dataset, chunk_steps, scheme)
    min_rows = _block_min_rows(dataset.dt, weak)
    rows = [weak_rows(n, weak) for n in steps]
    k = blocks_per_run(len(steps), min(rows, default=0), min_rows)
    if k == 1:
        return {"blocks": 1, "clusters": ""}
    seconds = sum(steps) * dataset.dt / (k * len(steps))
    return {"blocks": k, "clusters": f"{k * len(steps)} blocks of {seconds:.2g} s cut within {len(steps)} independent "
                                     f"runs (episodes; fewer than {MIN_RUNS})"}


def _block_min_rows(dt: float, weak: int) -> int:
    """The fewest rows of a block (:func:`run_blocks`): at least ``MIN_BLOCK_SECONDS`` and
    ``MIN_BLOCK_WINDOWS`` windows (rows every :func:`~identified.fit.derivatives.weak_stride` steps)."""
    return int(np.ceil(max(MIN_BLOCK_SECONDS / dt, MIN_BLOCK_WINDOWS * weak) / weak_stride(weak) - 1e-9))


def shortest_cut_run(runs: int, dt: float, weak: int) -> int:
    """The fewest steps each of ``runs`` runs needs for :func:`run_blocks` to cut them into
    ``MIN_RUNS`` blocks in all (runs of at most the chunks' length)."""
    rows = -(-MIN_RUNS // max(runs, 1)) * _block_min_rows(dt, weak)
    return (rows - 1) * weak_stride(weak) + weak if weak > 1 else rows


def shortest_cut_take(takes: int, dt: float, weak: int, at_least: int = 0, chunk_steps: int = 4096,
                      scheme: str = "forward") -> int | None:
    """The fewest steps, at least ``at_least``, each of ``takes`` takes needs for :func:`run_blocks`
    to cut them into blocks, the chunks' own cut of a take longer than ``chunk_steps`` included (its
    last piece is a run of its own, and may be too short to cut: 4 takes of 5 s are not cut, of 4.1 s
    they are); ``None`` where no take up to 64 chunks long is."""
    n = max(int(at_least), shortest_cut_run(takes, dt, weak))
    step = weak_stride(weak) if weak > 1 else 1
    while n <= 64 * chunk_steps:
        like = SimpleNamespace(n_episodes=takes, n_steps=n, dt=dt)
        if run_blocks(like, chunk_steps, scheme, weak)["blocks"] > 1:
            return n
        n += step
    return None


#: the passes of a classification keep the rows between them (:func:`_cached_runs`) when they take
#: at most this many bytes (:func:`_cache_bytes`)
CACHE_BYTES = 512 * 2**20
#: bytes a recorded instant's states and step context take (the robot, 24 cables on 6 rods: ~6.5 kB)
_STATE_BYTES = 8_000


def _cache_bytes(data: Dataset, columns: RodColumns, weak: int) -> int:
    """What :func:`_cached_runs` keeps of ``data``: every instant's states and step context, and its
    rows (summed over the weak form's windows, which start every quarter window)."""
    R, L = columns.full.shape
    per = R * 6 * L * 8 / weak_stride(weak)
    return int(data.n_episodes * data.n_steps * (per + _STATE_BYTES))


def _cached_runs(cache: dict, key: tuple, data: Dataset, fresh: Iterator[tuple[tuple[torch.Tensor, Any], int]],
                 topology: Topology, columns: RodColumns, joint: Sequence[Effect], iterating: Sequence[int],
                 weak: int, dt: float, bar: Any) -> Iterator[tuple[torch.Tensor, int]]:
    """The rows of ``data`` per chunk for a pass of a classification: the rows without the columns
    of the effects it iterates (``joint[k]`` for ``k`` in ``iterating``), summed over the weak form's
    windows, and each chunk's states and step context are kept in ``cache`` under ``key`` (the same
    data, layout and rest lengths) from the first pass (``fresh``: the chunks' rows without those
    columns, and each chunk); every pass adds those columns, made from its own classification
    (:func:`identified.fit.features.effect_rows`; the weak form is linear, row by row)."""
    hit = cache.get(key)
    if hit is None or hit[0] is not data:
        parts = []
        for (base, ch), n_ep in fresh:
            parts.append((base, ch, fit_context(topology, ch, dt), n_ep))
            yield _with_iterative(parts[-1], topology, columns, joint, iterating, weak), n_ep
        cache.clear()  # one data set at a time: the search's parts are tried in turn
        cache[key] = (data, parts)
        return
    for part in hit[1]:
        if bar is not None and bar.n < bar.total:
            bar.update(part[1].pos.shape[0])
        yield _with_iterative(part, topology, columns, joint, iterating, weak), part[3]


def _with_iterative(part: tuple, topology: Topology, columns: RodColumns, joint: Sequence[Effect],
                    iterating: Sequence[int], weak: int) -> torch.Tensor:
    """A cached chunk's rows (:func:`_cached_runs`) with the iterated effects' columns as they are now."""
    base, ch, context, n_ep = part
    A = base.clone()
    for k in iterating:
        cols = effect_rows(topology, columns, ch, context, joint[k], k)
        c0 = columns.effect_start[k]
        A[..., c0 : c0 + cols.shape[-1]] += weak_form(cols, n_ep, weak) if weak > 1 else cols
    return A


#: at most this many reclassifications of passive cables' taut rows; stop when the rest lengths
#: change by less than REST_TOL (relative)
REST_ITERATIONS = 25
REST_TOL = 1e-11
#: the quantile of a cable's recorded lengths its rest-length estimate is probed from when its
#: actuator's bias was absorbed (``identify``)
PROBE_QUANTILE = 0.05
#: a probed rest length within this (relative) of the cable's shortest fitted length sits at the edge
#: of the data: its bias is not separated by any slack row
REST_EDGE = 1e-6
TAU_TOL = 1e-10  # relative change of a filter's time constant at which the search stops


def _actuators_json(layout: ParameterLayout, sol: Solution, by_name: dict, dynamics: Sequence[str],
                    tau: np.ndarray, tau_se: np.ndarray, topology: Topology) -> list[dict[str, Any]]:
    """The identified actuators: ``name``, ``tendon``, ``gain`` (force on the tendon per unit
    activation, N; positive lengthens), ``bias`` (N), their standard errors, ``dynamics`` and
    ``time_constant`` (s; None without a filter)."""
    se = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None)) if sol.cov is not None else None
    out = []
    for a, n in enumerate(layout.actuators):
        g, b = layout.gain(a), layout.bias(a)
        filt = dynamics[a] in FILTERS
        out.append({"name": n, "tendon": by_name[n].tendon, "kind": by_name[n].kind, "dynamics": dynamics[a],
                    "gain": float(sol.theta[g]), "gain_stderr": None if se is None else float(se[g]),
                    "bias": float(sol.theta[b]), "bias_stderr": None if se is None else float(se[b]),
                    "time_constant": float(tau[a]) if filt else None,
                    "time_constant_stderr": float(tau_se[a]) if filt else None})
    return out


def _with_estimate(rest: torch.Tensor, passive: np.ndarray, estimate: np.ndarray) -> torch.Tensor:
    """The chunk's rest lengths (N, S) with every passive spring's column the fit's estimate."""
    mask = torch.as_tensor(passive, device=rest.device)
    return torch.where(mask, torch.as_tensor(estimate, dtype=rest.dtype, device=rest.device), rest)


def recorded_lengths(dataset: Dataset, topology: Topology, max_instants: int = 20000) -> np.ndarray:
    """(N, S) every spring's length at (up to ``max_instants`` of) the recorded states, m."""
    E, T = dataset.n_episodes, dataset.n_steps + 1
    stride = max(1, (E * T) // max_instants)
    t = lambda x: torch.as_tensor(x.reshape(-1, *x.shape[2:])[::stride], dtype=torch.float64)
    ends = endpoint_kinematics(topology, t(dataset.pos), t(dataset.quat), t(dataset.vel), t(dataset.angvel))
    return spring_geometry(ends).length.numpy()


def mean_lengths(dataset: Dataset, topology: Topology, max_instants: int = 20000) -> np.ndarray:
    """(S,) every spring's mean length over the recorded states (:func:`recorded_lengths`), m: the
    reference of the preload columns (:class:`~identified.fit.features.RodColumns`)."""
    return recorded_lengths(dataset, topology, max_instants).mean(0)


def fitted_min_lengths(dataset: Dataset, topology: Topology, late: Sequence[Effect], springs: Sequence[int],
                       scheme: str, chunk_steps: int = 4096, device: str = "cpu", margin: int = 0) -> np.ndarray:
    """(len(springs),) each spring's shortest length, m, at the instants the joint fit keeps for it (a
    rod it holds not touched by a residual-stage effect ``late``, within ``margin`` steps)."""
    out = np.full(len(springs), np.inf)
    if not len(springs):
        return out
    for ch, n_ep in iter_chunks(dataset, chunk_steps, scheme, device=device):
        length = spring_geometry(endpoint_kinematics(topology, ch.pos, ch.quat, ch.vel, ch.angvel)).length
        keep = torch.ones(ch.pos.shape[:2], dtype=torch.bool, device=ch.pos.device)
        if late:
            hit = _affected(late, topology, ch)
            keep = ~(dilate_rows(hit, n_ep, margin) if margin else hit)
        for k, j in enumerate(springs):
            seen = keep[:, [r for r in topology.springs[j].rods if r >= 0]].any(-1)
            if bool(seen.any()):
                out[k] = min(out[k], float(length[seen, j].min()))
    return out


def _misfit(sol: Solution) -> float:
    """The solution's equation residual, summed over rods and equations (same rows, same scale)."""
    return float(np.sum(np.square(np.asarray(sol.residual_rms, dtype=float))))


def _rest_from(theta: np.ndarray, layout: ParameterLayout, passive: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Passive springs' rest lengths ``l0 = l_ref + P / K`` from a solution (NaN where K is 0);
    0 elsewhere."""
    S = layout.n_springs
    k = theta[layout.k(np.arange(S))]
    p = theta[layout.preload(np.arange(S))]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(passive, np.where(k != 0, ref + p / np.where(k != 0, k, 1.0), np.nan), 0.0)


def _rest_stderr(theta: np.ndarray, cov: np.ndarray, layout: ParameterLayout, passive: np.ndarray) -> np.ndarray:
    """Standard error of ``l0 = l_ref + P / K`` by first-order propagation of the (K, P)
    covariance: ``var l0 = (var P - 2 x cov(K, P) + x² var K) / K²`` with ``x = P / K``; 0 for
    actuated cables (an input)."""
    S = layout.n_springs
    ki, pi = layout.k(np.arange(S)), layout.preload(np.arange(S))
    k = theta[ki]
    x = _rest_from(theta, layout, passive, np.zeros(S))
    var = (cov[pi, pi] - 2 * x * cov[ki, pi] + x**2 * cov[ki, ki]) / np.where(k != 0, k, np.nan) ** 2
    return np.where(passive, np.sqrt(np.clip(var, 0.0, None)), 0.0)


def _inertial_extras(layout: ParameterLayout, i: int) -> list[int]:
    """Full-vector indices of rod ``i``'s first moment and products (the full model's extras)."""
    return [layout.first_moment(i, k) for k in range(6)]


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
        names.append(unseen_moment(model.topology.rods[i].name, a))


def _mark_unseen(model: IdentifiedModel, layout: ParameterLayout, unseen: Sequence[int]) -> None:
    """Parameters of a law that switches at a spring's rest length whose spring never crossed it in
    the data (an empty column, held at 0): no standard error, and the list in
    ``metrics.not_identifiable``, never printed as a number with an error bar."""
    names = model.metrics.setdefault("not_identifiable", [])
    for k, e in enumerate(layout.effects):
        sl = layout.effect_slice(k)
        mine = [i for i in unseen if sl.start <= i < sl.stop]
        if not mine or e.stderr is None:
            continue
        e.stderr[[i - sl.start for i in mine]] = np.nan
        model.effects[k] = e.to_json()
        names += [f"{layout.full_names[i]}: its spring never crossed its rest length in the data (held at 0)"
                  for i in mine]


def _pinned(joint: Sequence[Effect], layout: ParameterLayout) -> dict[int, float]:
    """The effects' held parameters (:meth:`Effect.pinned`) as fixed values by layout index."""
    out = {}
    for k, e in enumerate(joint):
        held = e.pinned_values()
        out.update({layout.effect_offset(k) + int(p): float(held[p]) for p in np.flatnonzero(e.pinned())})
    return out


def dilate_rows(mask: torch.Tensor, n_episodes: int, margin: int) -> torch.Tensor:
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
        rest, tendon_force = model_inputs(model, data, ch)
        ch.rest = rest.to(ch.pos.device)
        rw = residual_wrench(engine_from_model(model, dtype=torch.float64, device=device), ch, push_point,
                             None if tendon_force is None else tendon_force.to(ch.pos.device))
        force, torque = rw.missing_world()
        terms = rw.terms
        ctx = terms.ctx._replace(base_lin_acc=terms.lin_acc, base_ang_acc_body=terms.ang_acc_body)
        stats = {}
        for e in late:
            rows = e.rows_affected(state, ctx)
            if ch.row_weight is not None:  # steps the data weigh out (a rod's markers missing) stay out
                rows = rows & (ch.row_weight > 0)
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
    length_ref: np.ndarray | None = None,
) -> IdentifiedModel:
    S, R = topology.n_springs, topology.n_rods
    th = sol.theta
    se = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None)) if sol.cov is not None else None
    k_idx, c_idx = np.arange(S), S + np.arange(S)
    m_idx = np.array([layout.m(i) for i in range(R)])
    i_idx = np.array([[layout.inertia(i, a) for a in range(3)] for i in range(R)])
    stderr: dict[str, np.ndarray] = {}
    passive = np.array([not s.actuated for s in topology.springs], dtype=bool)
    rest = dataset.rest_length.mean(axis=(0, 1))  # an actuated cable's: its mean command
    if layout.rest_lengths:
        rest = np.where(passive, _rest_from(th, layout, passive, length_ref), rest)
    inertia, inertia_se, com, com_se, frame = th[i_idx], None if se is None else se[i_idx], None, None, None
    if layout.full_inertia:  # the ten parameters -> centre of mass, principal moments and axes
        cols = np.array([layout.inertial(i) for i in range(R)])
        com, inertia, frame, com_se, inertia_se = rigid_body_from_regression(th, sol.cov, cols)
    if se is not None:
        stderr = {"stiffness": se[k_idx], "damping": se[c_idx], "mass": se[m_idx], "inertia": inertia_se}
        if com_se is not None:
            stderr["com"] = com_se
        if layout.rest_lengths:
            stderr["rest_length"] = _rest_stderr(th, sol.cov, layout, passive)
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
        rest_length=rest,
        mass=th[m_idx],
        inertia=inertia,
        com=com,
        inertia_frame=frame,
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
