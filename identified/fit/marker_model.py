"""An identified model from a recording by the output-error marker fit: what ``tensegrity fit
R.csv --refine`` runs where the regression on splined states cannot go (30 Hz with 1 cm of noise,
10 Hz) or as its refinement.

From a start (an earlier model of the robot, or the regression's own estimate of the same
recording), the total mass known, :func:`identified.fit.marker_fit.fit_markers` fits K, c, M, the
observable moments of inertia and the ground's contact law (``pyramid_contact``, every parameter
free, from its generic start unless the start model carries the law) to the markers themselves,
through the engine's windows.  Every number it writes has the fit's own error bar (the
Gauss-Newton covariance, scaled by the residual's variance); a parameter whose error bar is above
:data:`identified.fit.bound.NOT_IDENTIFIABLE` (30 %) is written without one and said not
identifiable, never as a number with an error bar.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection

import numpy as np

from identified.fit.bound import NOT_IDENTIFIABLE
from identified.fit.marker_blocks import combine_fits
from identified.fit.marker_fit import MarkerFit, fit_markers
from identified.model import IdentifiedModel, unseen_moment
from identified.recording import Recording, RecordingError

__all__ = ["CONTACT_EFFECTS", "MISFIT", "MISFIT_SD", "STILL_MOVING", "STILL_MOVING_SE", "MarkerRefineConfig", "refine_recording"]

#: a joint step that lowered the cost by more than this share leaves a fit still moving: its error
#: bars are withheld
STILL_MOVING = 0.01

#: an estimate that the Gauss-Newton step left at the end would still move by more than this many of
#: its standard errors is unfinished: its error bar is withheld (below it, it is widened by half the
#: step, :attr:`identified.fit.marker_fit.MarkerFit.rel_se`)
STILL_MOVING_SE = 2.0

#: the markers' residual, in units of their noise, above which the fit is said not to follow the
#: recording and its error bars are withheld (at the truth, clean markers are left at 1e-10 m; the
#: 30 Hz / 1 cm bench fits that covered the truth left 1.1 times the noise)
MISFIT = 1.2

#: where the recording states its markers' noise, the residual's variance in units of it above which
#: the fit does not follow the markers as well as their noise allows: this many standard deviations
#: of that variance under the noise alone, sqrt(2 / dof) (a chi-square), above 1.  Such a misfit is
#: a bias the Gauss-Newton error bars do not hold (measured: 30 Hz / 1 cm, seed 7, all 330 windows,
#: 1.086 at 84k degrees of freedom, 17.6 of them: M 5.4 % off at |z| 3.9, a damping at 3.8; 64
#: windows, 1.037 at 16k, 3.3: every bar covered; 128 windows, ~8: its widened bars covered, but
#: the misfit grew into the bias at all windows)
MISFIT_SD = 5.0

#: blocks of windows fitted on their own (:mod:`identified.fit.marker_blocks`) whose estimates
#: scatter about their combination with a chi-square this unlikely under the noise alone disagree:
#: the combined estimate's error bars are withheld
DISAGREE_P = 1e-3

#: effects of a start model the windows replace by their own contact law; any other effect the
#: windows do not model, and the fit refuses a start that has one
CONTACT_EFFECTS = ("ground_contact", "pyramid_contact")

#: a start's contact parameter within this of its bound (an impedance within it of 0 or 1, another
#: below this share of the law's generic start) is taken from the generic start: the windows fit
#: logarithms and logits, which could not move it from there
AT_BOUND = 1e-6


@dataclasses.dataclass(frozen=True)
class MarkerRefineConfig:
    """The windows and iterations of the marker fit (:func:`identified.fit.marker_fit.fit_markers`):
    up to ``windows`` windows of ``frames`` frames spread over the recording (``None``: all),
    their Jacobians stepped at up to ``step`` seconds (the cost always at the model's step),
    ``state_iterations`` steps in the windows' states alone, then up to ``iterations`` joint steps;
    ``blocks``: the windows fitted in that many interleaved blocks, each on its own, their
    estimates combined (:mod:`identified.fit.marker_blocks`; 1: all in one fit)."""

    windows: int | None = 64
    frames: int = 10
    step: float = 0.005
    state_iterations: int = 3
    iterations: int = 8
    blocks: int = 1


def _checked_start(start: IdentifiedModel, rec: Recording, topology, total_mass: float | None) -> IdentifiedModel:
    """The start on the recording's robot, its effects the contact's only, scaled to ``total_mass``
    (K, c, M and I together: the markers see only their ratios)."""
    if (start.topology.rod_names != topology.rod_names) or (start.topology.spring_names != topology.spring_names):
        raise RecordingError(f"'{rec.source}': the start model's rods and cables are not those of the MJCF "
                             "(give a start fitted on this robot)")
    other = [e["name"] for e in start.effects if e["name"] not in CONTACT_EFFECTS]
    if other:
        raise RecordingError(f"'{rec.source}': the marker fit models the ground's contact only; the start model has "
                             f"{', '.join(other)}: give a start without it")
    f = 1.0 if total_mass is None else float(total_mass) / float(np.sum(start.mass))
    return dataclasses.replace(start, stiffness=start.stiffness * f, damping=start.damping * f, mass=start.mass * f,
                               inertia=start.inertia * f, stderr={}, effects=list(start.effects), loop=[],
                               metrics={})


def _contact_law(start: IdentifiedModel, topology, mjcf: str):
    """The windows' contact law: ``pyramid_contact`` with the start's values if it has them (those
    at their bound, :data:`AT_BOUND`, from the generic start), else the law's generic start (a hard
    floor's order of magnitude, never the plant's); ``None`` for a robot without a ground plane.
    Also whether the start gave the law, and a line for each value taken from the generic start."""
    from identified.effects.pyramid_contact import START, PyramidContact
    from identified.fit.output_error import _impedances

    if topology.ground is None:
        return None, False, []
    law = PyramidContact.for_system(topology, mjcf)
    given = next((e for e in start.effects if e["name"] == "pyramid_contact"), None)
    generic = np.array(list(START.values()), dtype=float)
    if given is None:
        law.values = generic
        return law, False, []
    values = np.array([float(given["parameters"][n]) for n in START], dtype=float)
    # an earlier fit leaves a parameter the data could not tell at its bound (an impedance at 1, a
    # rolling friction at 1e-65): in the windows' logarithms and logits it could not move from there
    imp = _impedances(list(START))  # the windows' logits (in (0, 1)); the others' logarithms
    at_bound = np.where(imp, (values < AT_BOUND) | (values > 1 - AT_BOUND), ~(values > AT_BOUND * generic))
    notes = [f"pyramid_contact.{n} of the start model is at its bound ({v:.3g}): started from {g:g}"
             for n, v, g, b in zip(START, values, generic, at_bound) if b]
    law.values = np.where(at_bound, generic, values)
    return law, True, notes


def _withhold_error_bars(model: IdentifiedModel) -> None:
    """Every standard error of ``model`` NaN (``null`` in the file), its contact law's and its
    actuators' gains' too."""
    for k in ("stiffness", "damping", "mass", "inertia"):
        model.stderr[k] = np.full(np.shape(getattr(model, k)), np.nan)
    for e in model.effects:
        e["stderr"] = {n: None for n in e["parameters"]}
    for a in model.actuators:
        a["gain_stderr"] = None


def _why(rel: float, logit: bool) -> str:
    """Why a parameter has no value with an error bar: the fit's own standard error (relative, or
    of the logit of an impedance), or none at all."""
    if not np.isfinite(rel):
        return "not identifiable (no information in the markers)"
    se = f"standard error of its logit {rel:.3g}" if logit else f"standard error {100 * rel:.3g} %"
    return f"not identifiable from these markers ({se})"


def _model(start: IdentifiedModel, fit: MarkerFit, law, held: list[tuple[int, int]],
           withheld: Collection[str] = ()) -> IdentifiedModel:
    """The start with the fit's estimates and their standard errors (:attr:`MarkerFit.rel_se`; NaN
    where not identifiable, and for the estimates named in ``withheld`` by :func:`_said`'s names,
    whose values are kept: :func:`_still_moving`)."""
    names, values, rel = fit.cov.names, fit.cov.values, fit.rel_se
    topo = start.topology
    rod = {n: i for i, n in enumerate(topo.rod_names)}
    ok = rel <= NOT_IDENTIFIABLE
    bar = ok & ~np.isin([_said(n) for n in names], list(withheld))  # an error bar given
    not_identifiable = []
    R = topo.n_rods
    inertia = start.inertia.copy()
    inertia_se = np.full((R, 3), np.nan)
    est, stderr = {}, {}
    for field, kind in (("stiffness", "K"), ("damping", "c"), ("mass", "M")):
        idx = [i for i, n in enumerate(names) if n.startswith(f"{kind}[")]
        est[field] = values[idx]
        stderr[field] = np.where(bar[idx], values[idx] * rel[idx], np.nan)
    stderr["inertia"] = inertia_se
    for i, n in enumerate(names):
        if not n.startswith("I["):
            continue
        r, axes = n[2:-1].rsplit(":", 1)
        cols = ["xyz".index(a) for a in axes]
        inertia[rod[r], cols] = values[i]
        inertia_se[rod[r], cols] = values[i] * rel[i] if bar[i] else np.nan
    for i, n in enumerate(names):
        if not ok[i] and not n.startswith("law["):
            not_identifiable.append(f"{n}: {_why(rel[i], False)}")  # K, c, M, I and the gains
    for i, a in held:
        not_identifiable.append(unseen_moment(topo.rod_names[i], a))
    if law is not None:
        _law_estimates(law, names, values, rel, ok, bar, not_identifiable)
    # the MuJoCo actuators' gains are the fit's; their biases and filters are held at the start's
    # values in the windows: no error bar of this fit is theirs, and the start's would read as its own
    actuators = []
    for a in start.actuators:
        i = names.index(f"gain[{a['name']}]")
        actuators.append({**a, "gain": float(values[i]), "gain_stderr": float(abs(values[i]) * rel[i]) if bar[i] else None,
                          "bias_stderr": None, "time_constant_stderr": None,
                          "held": "bias and time constant at the start's (the marker fit holds them)"})
    return dataclasses.replace(start, stiffness=est["stiffness"], damping=est["damping"], mass=est["mass"],
                               inertia=inertia, stderr=stderr, actuators=actuators,
                               effects=[] if law is None else [law.to_json()],
                               metrics={"not_identifiable": not_identifiable})


def _law_estimates(law, names: list[str], values: np.ndarray, rel: np.ndarray, ok: np.ndarray, bar: np.ndarray,
                   not_identifiable: list[str]) -> None:
    """The contact law's fitted parameters and standard errors (where ``bar``) into ``law`` (the
    others held at their start, without one); its not identifiable ones (not ``ok``) appended to
    ``not_identifiable``."""
    law_names = [n[4:-1] for n in names if n.startswith("law[")]
    idx = [names.index(f"law[{n}]") for n in law_names]
    block = [b.name for b in law.blocks]
    law.values = law.values.copy()
    law.stderr = np.full(law.values.size, np.nan)
    for n, i in zip(law_names, idx):
        j = block.index(n)
        v = float(values[i])
        law.values[j] = v
        # the windows' unknowns: logits of the impedances, logarithms of the others
        if bar[i]:
            law.stderr[j] = (v * (1 - v) if n.startswith("imp_") else v) * rel[i]
        if not ok[i]:
            not_identifiable.append(f"{law.name}.{n}: {_why(rel[i], n.startswith('imp_'))}")


def _said(name: str) -> str:
    """A parameter of the fit by the name the model file gives it: ``K[cable3]``, ``M[rod0]``,
    ``I[rod2:xy]`` as they are, the contact law's ``law[beta]`` as ``pyramid_contact.beta``."""
    from identified.effects.pyramid_contact import PyramidContact

    return f"{PyramidContact.name}.{name[4:-1]}" if name.startswith("law[") else name


def _steps_left(fit: MarkerFit) -> dict[str, float]:
    """``{name: |step|}``: how many of its standard errors the Gauss-Newton step left at the end
    would move each parameter that has an error bar (:func:`_said`'s names; empty where the fit has
    no such step)."""
    if fit.to_minimum is None:
        return {}
    z = np.where(fit.rel_se <= NOT_IDENTIFIABLE, np.abs(fit.to_minimum), np.nan)
    return {_said(n): float(v) for n, v in zip(fit.cov.names, z) if np.isfinite(v)}


def _farthest(fit: MarkerFit) -> tuple[str, float]:
    """The parameter with an error bar that the Gauss-Newton step left at the end would move the
    most, and by how many of its standard errors (``("", 0.0)`` where the fit has no such step)."""
    steps = _steps_left(fit)
    if not steps:
        return "", 0.0
    name = max(steps, key=steps.get)
    return name, steps[name]


def _still_moving(fit: MarkerFit) -> dict[str, float]:
    """``{name: |step|}`` of the estimates that the step left to the minimum of the cost's quadratic
    model would move by more than :data:`STILL_MOVING_SE` of their standard errors: their error
    bars describe the scatter about the minimum, not about a point this far from it, and are
    withheld (:func:`_model`'s ``withheld``; the others are widened by half their step)."""
    return {n: round(v, 3) for n, v in _steps_left(fit).items() if v > STILL_MOVING_SE}


def _excess_sd(fit: MarkerFit, sigma: float) -> float:
    """How many standard deviations of a chi-square over the fit's degrees of freedom the markers'
    residual variance lies above their noise's ``sigma**2`` (NaN where the degrees are not known)."""
    if fit.dof <= 0:
        return float("nan")
    return ((fit.residual_rms / sigma) ** 2 - 1.0) / float(np.sqrt(2.0 / fit.dof))


def _judge_fit(model: IdentifiedModel, fit: MarkerFit, iterations: int, sigma: float,
               stated: bool = False) -> None:
    """The fit's error bars withheld where they would not mean what they say: all of them where the
    fit leaves the markers more than :data:`MISFIT` times their noise ``sigma`` off, or (``stated``:
    the recording states that noise) their variance more than :data:`MISFIT_SD` standard deviations
    of a chi-square above it (the windows do not follow the recording: their states short of their
    minimum -- measured at 30 Hz / 1 cm, at the truth from the plant's own states, eight state-only
    steps left a variance 1.075 times the noise's --, a local minimum, or an effect the model lacks)
    or blocks of windows fitted on their own disagree (:data:`DISAGREE_P`), or an unconverged fit's
    last joint step still lowered the cost by more than :data:`STILL_MOVING`; else those of
    :func:`_still_moving` (``model`` built by :func:`_model` with them withheld), named with their
    steps in ``metrics.withheld`` and a warning; a fit that had nearly stopped keeps them, and says
    so."""
    last = (fit.history[-2] - fit.history[-1]) / fit.history[-1] if len(fit.history) > 1 else 0.0
    name, far = _farthest(fit)
    withheld = None
    if fit.residual_rms > MISFIT * sigma:
        # measured: 30 Hz / 1 cm, 16 windows from values 15 % off, stalled with the markers 13.4 mm
        # off against 10 mm of noise: K up to 10 % off at |z| 4.7 under the Gauss-Newton error bars
        withheld = ("the marker fit leaves the markers off by more than their noise",
                    (f"the marker fit leaves the markers {1e3 * fit.residual_rms:.3g} mm off against their noise of "
                    f"{1e3 * sigma:.3g} mm ({fit.residual_rms / sigma:.2f} times, more than {MISFIT:g}): its windows "
                    "do not follow the recording (a local minimum from this start, or an effect the model lacks), so "
                    "its values have no error bars; try more --windows, a start nearer the robot, or `tensegrity "
                    "diagnose`"))
    elif stated and (excess := _excess_sd(fit, sigma)) > MISFIT_SD:
        withheld = ("the marker fit leaves the markers off by more than their stated noise allows",
                    (f"the marker fit leaves the markers {1e3 * fit.residual_rms:.3g} mm off against their stated noise "
                     f"of {1e3 * sigma:.3g} mm: a variance {(fit.residual_rms / sigma) ** 2:.3g} times the noise's over "
                     f"{fit.dof:.0f} degrees of freedom, {excess:.1f} standard deviations above it (more than "
                     f"{MISFIT_SD:g}): the model does not follow the recording as its noise allows (the windows' "
                     "states short of their minimum, an effect it lacks, or a local minimum), a bias its error bars "
                     "would not cover, so its values have none; try `tensegrity diagnose`, or check the "
                     "recording's stated noise"))
    elif fit.agreement is not None and fit.agreement.dof > 0 and fit.agreement.p < DISAGREE_P:
        a = fit.agreement
        withheld = ("the marker fit's blocks of windows disagree",
                    (f"the marker fit's {len(fit.blocks)} blocks of windows disagree by more than their error bars: "
                     f"their estimates scatter about the combined one with a chi-square of {a.chi2:.4g} over {a.dof} "
                     f"degrees of freedom (p = {a.p:.2g}, below {DISAGREE_P:g}): some block is not at its minimum or "
                     "is biased, so the combined values have no error bars; run more --iterations (with --checkpoint "
                     "it goes on where it stopped) or compare the blocks' fits"))
    elif not fit.converged and last > STILL_MOVING:
        # the Gauss-Newton error bars of a point the fit is still leaving say nothing about the
        # estimate it would reach (measured: 30 Hz / 1 cm, 16 windows, 8 joint steps still falling
        # 7 % a step: a K 10 % off at |z| 3.7)
        withheld = ("the marker fit had not converged",
                    (f"the marker fit did not converge in {iterations} joint steps (its cost per residual fell "
                    f"{100 * last:.2g} % in the last, {fit.history[-2]:.4g} -> {fit.history[-1]:.4g}): the values "
                    "are those of an unfinished fit and have no error bars; run more --iterations (with --checkpoint "
                    "it goes on where it stopped)"))
    if withheld is not None:
        _withhold_error_bars(model)
        model.metrics["stderr"] = f"withheld: {withheld[0]}"
        model.metrics.setdefault("warnings", []).append(withheld[1])
        return
    # widening by half the step stands for an estimate that crept to a stop near its minimum: at 30
    # Hz / 1 cm, 64 windows, the step left was 0.4-0.7 se for K and 1.2 for the law's kappa; at 128
    # windows 5.4 for the law's beta and 2.1-2.4 for three moments, at most 1.3 for every K, c and M,
    # whose widened bars covered the truth
    moving = _still_moving(fit)
    if moving:
        model.metrics["withheld"] = moving
        said = ", ".join(f"{n} by {v:.3g}" for n, v in sorted(moving.items(), key=lambda kv: -kv[1]))
        model.metrics.setdefault("warnings", []).append(
            f"the marker fit is not at its minimum in {len(moving)} of its estimates: one more Gauss-Newton step "
            f"would move {said} of their standard errors (more than {STILL_MOVING_SE:g}), so these have no error "
            "bars (the others' are widened by half their step); run more --iterations (with --checkpoint it goes "
            "on where it stopped)")
    if not fit.converged:
        model.metrics.setdefault("warnings", []).append(
            f"the marker fit stopped after {iterations} joint steps with its cost per residual still falling "
            f"{100 * last:.2g} % a step: error bars from its last step (the step left to its minimum would move "
            f"{name or 'no estimate'} by {far:.2g} of its standard errors)")


def _fit_blocks(start: IdentifiedModel, rec: Recording, ms, mjcf: str, sigma: float, law, config: MarkerRefineConfig,
                windows: int, substeps: int, progress: bool, checkpoint: str | None) -> MarkerFit:
    """The marker fit of ``config``: of all its windows at once, or of its ``blocks`` one after
    another (block ``b``'s checkpoint ``checkpoint.block<b>``), combined
    (:func:`identified.fit.marker_blocks.combine_fits`)."""
    B = max(1, int(config.blocks))
    law_free = () if law is None else tuple(bl.name for bl in law.blocks)
    fits = []
    for b in range(B):
        if progress and B > 1:
            print(f"marker fit: block {b + 1} of {B}", flush=True)
        fits.append(fit_markers(start, rec, ms.data, ms.starts, mjcf, sigma, ms.unobservable, frames=config.frames,
                                max_windows=windows, state_iters=config.state_iterations, joint_iters=config.iterations,
                                contact=law, law_free=law_free, substeps=substeps, progress=progress,
                                checkpoint=checkpoint if checkpoint is None or B == 1 else f"{checkpoint}.block{b}",
                                block=(b, B)))
    return fits[0] if B == 1 else combine_fits(fits)


def refine_recording(rec: Recording, mjcf: str, start: IdentifiedModel, total_mass: float | None = None,
                     config: MarkerRefineConfig = MarkerRefineConfig(), progress: bool = False,
                     checkpoint: str | None = None) -> IdentifiedModel:
    """The model the markers of ``rec`` give by the output-error fit from ``start`` (the module
    docstring); ``total_mass`` (kg) fixes the scale (``None``: the start's).  ``mjcf`` gives the
    topology, the sites and the capsules' geometry, never a parameter.  The result's
    ``metrics.output_error``: windows used and available, frames, step, the markers' residual and
    noise (m), the cost per residual after every iteration and the seconds taken.  ``checkpoint``:
    a file the fit is saved to after every step and resumed from (:func:`~identified.fit.marker_fit.fit_markers`)."""
    from identified.fit.markers import labelled, states_from_recording
    from identified.topology import Topology

    topo = Topology.from_mjcf(mjcf)
    rec = labelled(rec, topo, mjcf)
    start = _checked_start(start, rec, topo, total_mass)
    if total_mass is not None:
        start.scale = {"anchor": "total_mass", "total_mass": float(total_mass),
                       "description": f"the total rod mass given, {float(total_mass):g} kg"}
    ms = states_from_recording(rec, topo, start.dt, tuple(start.gravity), measure_noise=True)
    sigma = float(ms.marker_noise or rec.noise_pos or 1e-3)
    law, law_given, law_notes = _contact_law(start, topo, mjcf)
    if progress:
        for note in law_notes:
            print(f"marker fit: {note}", flush=True)
    substeps = max(1, round(config.step / start.dt))
    windows = 10 ** 9 if config.windows is None else int(config.windows)
    fit = _fit_blocks(start, rec, ms, mjcf, sigma, law, config, windows, substeps, progress, checkpoint)
    model = _model(start, fit, law, ms.unobservable, withheld=_still_moving(fit))
    converged = fit.converged
    model.metrics["output_error"] = {
        "windows": fit.windows, "windows_available": fit.available, "frames_per_window": config.frames,
        "jacobian_step_s": substeps * start.dt, "marker_residual_m": fit.residual_rms, "marker_noise_m": sigma,
        "degrees_of_freedom": fit.dof, "excess_variance_sd": None if fit.dof <= 0 else round(_excess_sd(fit, sigma), 3),
        "cost_per_residual": [b.history for b in fit.blocks] if fit.blocks else fit.history,
        "converged": converged, "seconds": round(fit.seconds, 3),
        "step_left_se": dict(zip(("parameter", "standard_errors"), _farthest(fit))),
        "contact_start": ("no ground plane" if law is None else
                          "the start model's pyramid_contact" if law_given else "pyramid_contact's generic start"),
    }
    if fit.agreement is not None:
        model.metrics["output_error"]["blocks"] = {
            "blocks": len(fit.blocks), "windows": [b.windows for b in fit.blocks],
            "agreement_chi2": round(fit.agreement.chi2, 3), "agreement_dof": fit.agreement.dof,
            "agreement_p": None if not np.isfinite(fit.agreement.p) else fit.agreement.p}
    model.metrics["recording"] = {"source": rec.source, "frames": rec.n_frames, "takes": rec.n_episodes,
                                  "rate_hz": rec.rate_hz(), "missing": rec.missing_fraction(),
                                  "labelled_automatically": rec.unlabelled, "notes": ms.notes, "marker_noise": sigma}
    model.metrics["fit_seconds"] = round(fit.seconds, 3)
    model.metrics["stderr"] = ("Gauss-Newton covariance of the marker fit, scaled by its residual's variance, "
                               "each widened by half the step left to the minimum of the cost's quadratic model; "
                               f"{fit.windows} of {fit.available} windows")
    if law_notes:
        model.metrics.setdefault("warnings", []).extend(law_notes)
    _judge_fit(model, fit, config.iterations, sigma, stated=rec.stated_noise is not None)
    return model
