"""Diagnosis of an identified model on recorded data: where it is wrong, and which effect explains it.

:func:`diagnose` is the library side of ``tensegrity diagnose``; :func:`write_report` draws its
figures and writes a report in words.  The package: :mod:`.residual` (the one-step residual, its
regions and the candidates' scores), :mod:`.stats` (Ljung-Box, correlations), :mod:`.report`
(Markdown and figures); the error measures themselves are :mod:`identified.evaluate`'s.  Everything is measured on the data given (use data the
model was not fitted on).

**Free-run error** (``error_before``, ``error_after``; the ``metric`` key says it in words): the
model is started from every episode's recorded initial state and driven by the recorded rest
lengths and pushes for ``horizon_s`` seconds; the error is the distance between each rod's
predicted and recorded centre of mass (m), averaged over rods, over the steps ``1..H`` and over the
episodes.  ``error_after`` is the model as it is, ``error_before`` the same model with its added
effects removed (``model.effects = []``).  ``None``: the free run diverged.

**One-step residual** (the acceleration residual, as a wrench): at every recorded instant, the
recorded acceleration (:func:`identified.samples.iter_chunks`; :func:`identified.evaluate.residual_wrench`: the forward difference of
the velocities, or the central one for an RK4 model) minus the model's, times the model's mass
(inertia), ``M (a - a_model)`` in newtons and ``I (α_b - α_b,model)`` in N m, i.e. the wrench the
model misses.  For the Euler integrator this is exactly ``M (a - g) - F`` and
``R (I α_b + ω_b × I ω_b) - τ``.  Forces are reported per world axis, torques per rod-frame axis
(z is the rod's axis).

**Candidates**: every effect of the library (:data:`identified.effects.EFFECTS`) the model does not
have.  The rows ``y`` are the residual force (3 rows) and the residual torque divided by the rod's
half-length (3 rows; world frame, so both are in newtons) of every rod at every instant; a
candidate's columns ``X`` are the same rows of its force and torque per unit of each of its
parameters (:meth:`identified.effects.Effect.features`).  Its *score* is the fraction of the
residual that adding it to the model would remove: least squares of ``y`` on the model's own
equation columns ``B`` (:func:`identified.fit.features.equation_rows`: K, c, M, I, h and the model's
joint effects, with the total mass held, which fixes the scale) together with ``X``, against ``B``
alone, ``score = 1 - RSS(B, X) / RSS(B)`` (``unexplained = 1 - score``): the base parameters may
move, because a fit without the effect has bent them to mimic it.  1 = the candidate explains the
residual completely, 0 = not at all; an unrelated candidate with ``P`` parameters scores about
``P / rows`` on white residuals.  ``score_alone`` is the fraction of ``y'y`` that ``X`` alone
explains.  ``score_held_out``: with the model's own columns regressed out over all the data, the
candidate's columns fitted on one half of the data (blocks of 1 s, alternating) and the share of
the residual they remove on the other half, the smaller of the two ways round
(:func:`.residual.held_out_score`): an effect the data hold removes about as much as in-sample, one
fitted to noise removes nothing; the candidates are listed best first by it.  On states
reconstructed from a recording's markers (``weak_window``, ``contact_margin``:
:func:`identified.fit.markers.diagnosis_options`) the rows are those the fit reads: each episode's
rows summed over the fit's 0.3 s windows (the splines' second derivatives carry the markers'
noise, which dominates one-step rows), and the rows of the rods in contact, with a margin, left
out (a spline spreads an impact over a few frames).  ``ground_contact`` needs the MJCF's ground
plane and capsules (``mjcf=``, else ``model.source_model`` when it is a file); without them it is
listed under ``skipped``.

**Explained** (``explained``: ``True``, ``"partial"`` or ``False``; the reasons in
``explained_by`` and ``partial_by``).  The residual is *explained* when it is at rounding level
(its RMS below ``1e-6`` times the RMS of the recorded inertial wrench, for both force and
torque), or white (no rod/dof series rejects the Ljung-Box test at 1 % after a Bonferroni
correction over the series), or the model's added effects cut the free-run error at least 5×
(``error_after <= 0.2 error_before``).  It is ``"partial"`` when it is explained so but one of the
model's added effects that acts on some rods only (an effect class with a ``region``: ground
contact's rods on the ground, as its fit classifies them) leaves a clear signature on its rows:
there, the residual relative to the recorded wrench (force or torque, ``one_step.effect_rows``)
is at least ``PARTIAL_LEVEL`` (1 %) and at least ``PARTIAL_RATIO`` (10×) the residual relative to
the recorded wrench on the other rows, in every episode that holds rows of both kinds (independent
runs agreeing; over the whole data a difference this large is never chance).  The effect's law then
explains most of its force but not all of it, and what it misses is concentrated where it acts.
``False``: none of the three rules holds; the residual is structured and the model's effects do not
account for it.  Also ``False`` whatever the rules, when a candidate is *supported*: its
``score_held_out`` is at least :data:`SUPPORTED_GAIN` (``unexplained_by`` lists them): an effect
the model lacks removes a clear share of what is left on data it was not fitted on (unless the
residual is at rounding level: nothing is left).  On a
recording, states reconstructed from coarse or noisy markers leave a residual of their own that
some candidates explain (measured: a constant force per rod, 0.28-0.87 held out on the robot in
still air at 60 Hz / 2 mm and 30 Hz / 1 cm); given the same candidate's score on a *null* (the
model's own motion under the recorded inputs, recorded with the same sensors: ``null``), the
share beyond it (:func:`held_out_share`) must reach :data:`SUPPORTED_GAIN`.

Also: the residual by region of state (each region an effect class declares -- ``near_ground``:
the rods ground contact acts on --, slack cables -- springs shorter than their rest length when no
cable is declared --, the fastest 10 % of rod-instants, rods under a push) against the rest;
k-step errors;
Ljung-Box statistics per rod and dof; the residual's correlation with the inputs (rest lengths,
pushes) and with every candidate feature.  The result is a JSON-able dict (``None`` for anything
undefined, never NaN).
"""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from identified.dataset import Dataset, DatasetError
from identified.effects import EFFECTS, RESERVED, Effect, GeometryError, make_effect, rival
from identified.evaluate import k_step_errors, rollout_errors
from identified.jsonsafe import json_safe
from identified.model import IdentifiedModel
from identified.threads import torch_threads
from identified.twin import effects_from_model

from .report import write_report
from .residual import one_step
from .stats import ALPHA, DOFS, LJUNG_BOX_LAGS, input_correlation, ljung_box, whiteness

__all__ = ["DOFS", "K_STEPS", "SUPPORTED_GAIN", "at_rounding_level", "diagnose", "held_out_scores", "held_out_share",
           "improved", "ljung_box", "missing_effects", "supported", "verdict", "write_report"]

#: k-step prediction errors are reported for these k
K_STEPS = (1, 10, 100)
ROUNDING_LEVEL = 1e-6  # residual RMS relative to the recorded wrench RMS
EXPLAINED_GAIN = 0.2  # error_after <= this x error_before
#: an added effect's rows leave a clear signature when their relative residual is at least this ...
PARTIAL_LEVEL = 0.01
#: ... and at least this many times the other rows', in every episode
PARTIAL_RATIO = 10.0
#: a candidate effect the data support: it removes at least this share of the residual on each
#: half of the data with its coefficients fitted on the other half
SUPPORTED_GAIN = 0.15
_CURVE_POINTS = 200
_KSTEP_STARTS = 256


# ---------------------------------------------------------------------- public API
@torch_threads(1)
def diagnose(
    model: IdentifiedModel,
    data: Dataset,
    horizon_s: float = 1.0,
    max_steps: int = 50_000,
    mjcf: str | os.PathLike | None = None,
    chunk_steps: int = 2048,
    weak_window: int | None = None,
    contact_margin: int | None = None,
    null: dict[str, float | None] | None = None,
) -> dict[str, Any]:
    """Residual analysis of ``model`` on ``data`` (see the module docstring for every rule).

    ``horizon_s``: free-run horizon, s (the data must hold at least that much per episode);
    ``max_steps``: at most this many recorded steps are analysed (whole episodes first);
    ``mjcf``: path or text of the plant's MJCF, for the geometry a candidate effect reads (the
    ground plane; default: the model's ``source_model`` when it is a readable file);
    ``weak_window`` (steps), ``contact_margin`` (steps): the candidates scored on the weak form of
    the rows, without the rows of the model's regional effects and that many steps around them --
    for states reconstructed from markers (:func:`identified.fit.markers.diagnosis_options`);
    ``null``: per candidate, its ``score_held_out`` on the model's own motion recorded with the same
    sensors (what the reconstruction alone makes it explain; ``tensegrity diagnose`` on a recording
    makes one): a candidate is then supported by its share beyond that (:func:`held_out_share`).
    Raises ``DatasetError`` when the data do not belong to the model, ``ValueError`` when they are
    too short for the horizon (or, with ``weak_window``, for one window).

    Keys: ``error_before``, ``error_after`` (m), ``metric``, ``horizon_s``, ``added``,
    ``explained`` (``True``, ``"partial"``, ``False``), ``explained_by`` (``"rounding"``,
    ``"white"``, ``"improved"``), ``partial_by`` (the added effects whose rows leave a clear
    signature), ``unexplained_by`` (the supported candidates), ``explained_rule``; ``candidates`` (best
    first by ``score_held_out``: ``name``, ``score``, ``score_held_out``, ``score_held_out_halves``,
    ``unexplained``, ``score_alone``, ``n_params``, ``max_abs_corr``, ``best_feature``,
    ``top_features``, ``note``), ``score_rule``, ``skipped`` (``name``, ``reason``),
    ``base_refit_explains``; ``data``; ``one_step`` (``force_rms`` N and ``torque_rms`` N m per
    axis, ``relative``, ``per_rod``, ``worst_rod``, ``effect_rows``: per added effect with a region,
    the relative residual on its rows and on the others, ``inside``/``outside``, overall and per
    episode, and for an effect with a contact point (ground contact) ``inside.torque_about_contact_point``:
    the residual torque less the residual force's moment about that point, relative to the recorded
    torque -- what a pure torque at the contact would have to explain; the rest of the torque
    residual is the moment of a force the law misses); ``k_step`` (``after``/``before``: ``{"1", "10", "100"}`` with ``pos`` m and
    ``quat``); ``free_run`` (``time_s``, ``before``, ``after`` curves, subsampled); ``regions``
    (``near_ground``, ``slack``, ``fast``, ``pushed``: RMS residual in and out); ``whiteness``
    (Ljung-Box per rod and dof, ``white``, ``min_p``); ``input_correlation`` (``rest_length``,
    ``push_force``); ``best_feature``; ``plot_data`` (what :func:`write_report` draws).

    Runs on one thread: its work is many small steps, which a team of threads only slows down
    (badly so on a loaded machine).
    """
    with threadpool_limits(1):
        return _diagnose(model, data, horizon_s, max_steps, mjcf, chunk_steps, weak_window, contact_margin, null)


@torch_threads(1)
def held_out_scores(model: IdentifiedModel, data: Dataset, mjcf: str | os.PathLike | None = None,
                    max_steps: int = 50_000, chunk_steps: int = 2048, weak_window: int | None = None,
                    contact_margin: int | None = None) -> dict[str, float | None]:
    """Each candidate effect's ``score_held_out`` on ``data``, scored as :func:`diagnose` scores
    them (the same arguments), without the rest of the diagnosis (free runs, k-step errors): what a
    null of the diagnosis needs (``null=``)."""
    with threadpool_limits(1):
        H = min(data.n_steps, max(1, int(weak_window or 1)))
        one, _, _ = _one_step_pass(model, _subset(data, int(max_steps), H), _mjcf_source(model, mjcf), chunk_steps,
                                   weak_window, contact_margin)
    return {c["name"]: c["score_held_out"] for c in one["candidates"]}


def at_rounding_level(relative: dict[str, float | None]) -> bool:
    """Whether the one-step residual relative to the recorded wrench is below
    :data:`ROUNDING_LEVEL` for the force AND the torque (``None``: undefined, not at rounding)."""
    return all(v is not None and v < ROUNDING_LEVEL for v in relative.values())


def improved(added: list[str], error_before: float | None, error_after: float | None) -> bool:
    """Whether the model's added effects cut the free-run error at least ``1 / EXPLAINED_GAIN``
    (5x), or turned a diverging free run (``None``) into a finite one."""
    eb, ea = error_before, error_after
    return bool(added) and ((eb is None and ea is not None)
                            or (eb is not None and ea is not None and eb > 0 and ea <= EXPLAINED_GAIN * eb))


def supported(candidates: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The candidates the data support, best first: their held-out share (:func:`held_out_share`)
    at least :data:`SUPPORTED_GAIN`; each as ``name``, ``score_held_out`` and, where a null was
    given, ``score_held_out_null``."""
    hits = [c for c in candidates if (v := held_out_share(c)) is not None and v >= SUPPORTED_GAIN]
    return [{"name": c["name"], "score_held_out": c["score_held_out"],
             **({"score_held_out_null": c["score_held_out_null"]} if "score_held_out_null" in c else {})}
            for c in sorted(hits, key=lambda c: -held_out_share(c))]


def missing_effects(candidates: list[dict[str, Any]], rounding: bool) -> list[dict[str, Any]]:
    """The ``unexplained_by`` of the verdict: the :func:`supported` candidates, none where the
    residual is at rounding level (nothing is left to explain; a share of rounding noise on held-out
    data means nothing, and can come out large either way: -683 for cable friction on the demo's
    exact contact model)."""
    return [] if rounding else supported(candidates)


def held_out_share(c: dict[str, Any]) -> float | None:
    """A candidate's held-out share beyond what the reconstruction alone gives it: ``score_held_out``
    less the same candidate's score on the null (``score_held_out_null``: the model's own motion
    recorded with the same sensors, which holds no such effect; a negative null counts as 0);
    without a null, ``score_held_out`` itself."""
    held = c.get("score_held_out")
    if held is None or "score_held_out_null" not in c:
        return held
    null = c["score_held_out_null"]
    return None if null is None else held - max(null, 0.0)


def verdict(rounding: bool, white: bool, improved: bool,
            effect_rows: list[dict[str, Any]]) -> tuple[bool | str, list[str], list[dict[str, Any]]]:
    """``explained`` (``True``, ``"partial"``, ``False``), its reasons, and the added effects whose
    rows leave a clear signature (module docstring), from the three rules and ``one_step.effect_rows``."""
    reasons = [r for r, ok in (("rounding", rounding), ("white", white), ("improved", improved)) if ok]
    if not reasons:
        return False, reasons, []
    partial = []
    for entry in effect_rows:
        for part in ("force", "torque"):
            r_in, r_out = entry["inside"][part], entry["outside"][part]
            if r_in is None or r_in < PARTIAL_LEVEL:
                continue
            pairs = [(i[part], o[part]) for i, o in zip(entry["inside_per_episode"], entry["outside_per_episode"])
                     if i[part] is not None and o[part] is not None]
            if r_out is not None and r_in < PARTIAL_RATIO * r_out:
                continue
            if pairs and all(i >= PARTIAL_RATIO * o for i, o in pairs):
                partial.append({"effect": entry["effect"], "part": part, "relative_inside": r_in,
                                "relative_outside": r_out})
    return ("partial" if partial else True), reasons, partial


def _diagnose(model: IdentifiedModel, data: Dataset, horizon_s: float, max_steps: int,
              mjcf: str | os.PathLike | None, chunk_steps: int, weak_window: int | None,
              contact_margin: int | None, null: dict[str, float | None] | None) -> dict[str, Any]:
    topo = model.topology
    if data.rod_names != topo.rod_names or data.tendon_names != topo.spring_names:
        missing = sorted(set(topo.rod_names + topo.spring_names) - set(data.rod_names + data.tendon_names))
        raise DatasetError("the dataset's rods/tendons do not match the identified model's"
                           + (f" (the data lack {', '.join(missing[:4])})" if missing else ""))
    if not (np.isfinite(horizon_s) and horizon_s > 0):
        raise ValueError(f"horizon must be a positive number of seconds, got {horizon_s}")
    H = round(horizon_s / data.dt)
    if H < 1 or H > data.n_steps:
        raise ValueError(f"the data hold {data.n_steps * data.dt:g} s per episode, shorter than the "
                         f"{horizon_s:g} s horizon")
    if weak_window is not None and weak_window > data.n_steps:
        raise ValueError(f"the data hold {data.n_steps * data.dt:g} s per episode, shorter than one "
                         f"{weak_window * data.dt:g} s window of the weak form the candidates are scored on")
    sub = _subset(data, int(max_steps), H)
    added = [str(e.get("name")) for e in model.effects]
    base = replace(model, effects=[])
    src = _mjcf_source(model, mjcf)

    # free run, before and after the added effects
    fr_after = _free_run(model, sub, H)
    fr_before = _free_run(base, sub, H) if added else fr_after
    k_after = k_step_errors(model, sub, K_STEPS, _KSTEP_STARTS)
    k_before = k_step_errors(base, sub, K_STEPS, _KSTEP_STARTS) if added else k_after

    one, regions, skipped = _one_step_pass(model, sub, src, chunk_steps, weak_window, contact_margin)
    res = one["res"]  # (E, T', R, 6)
    lb = whiteness(res, topo.rod_names)
    rel = one["relative"]
    eb, ea = fr_before["error"], fr_after["error"]
    explained, reasons, partial = verdict(at_rounding_level(rel), lb["white"], improved(added, eb, ea),
                                          one["effect_rows"])
    region_out = dict(one["regions"])
    for name, why in _unavailable_regions(regions, src).items():
        region_out[name] = why

    if null is not None:  # what the reconstruction alone makes each candidate explain
        for c in one["candidates"]:
            c["score_held_out_null"] = null.get(c["name"])
    # best first: by the share each removes on data it was not fitted on, then by the in-sample score
    key = lambda v: -np.inf if v is None else v
    cand = sorted(one["candidates"], key=lambda c: (-key(held_out_share(c)), -key(c["score"])))
    missing = missing_effects(cand, at_rounding_level(rel))
    if missing:  # a library effect removes a clear share of what is left, on data it was not fitted on
        explained, partial = False, []
    result: dict[str, Any] = {
        "metric": (f"free-run position error: distance between predicted and recorded rod centres of mass, m, "
                   f"mean over rods, steps 1..{H} ({H * sub.dt:g} s) and {sub.n_episodes} episodes, from each "
                   f"episode's recorded initial state under the recorded rest lengths and pushes"),
        "horizon_s": H * sub.dt,
        "horizon_steps": H,
        "error_before": eb,
        "error_after": ea,
        "added": added,
        "explained": explained,
        "explained_by": reasons,
        "partial_by": partial,
        "unexplained_by": missing,
        "explained_rule": (f"explained (true) when the one-step residual is at rounding level (RMS < "
                           f"{ROUNDING_LEVEL:g} x the recorded wrench RMS, force and torque), or white (Ljung-Box, "
                           f"{LJUNG_BOX_LAGS} lags, no rod/dof series rejects at {ALPHA:g} after Bonferroni), or the "
                           f"added effects cut the free-run error at least {1 / EXPLAINED_GAIN:g}x; \"partial\" when "
                           f"so but an added effect acting on some rods leaves there a residual of at least "
                           f"{PARTIAL_LEVEL:g} of the recorded force or torque and at least {PARTIAL_RATIO:g}x the "
                           f"other rods', in every episode; false otherwise, and false whenever a candidate effect "
                           f"removes at least {SUPPORTED_GAIN:g} of the residual on each half of the data with its "
                           f"coefficients fitted on the other half (unexplained_by; beyond its share on the null, "
                           f"the model's own motion recorded alike, where one is given), unless the residual is at rounding level"),
        "candidates": cand,
        "score_rule": _score_rule(weak_window, contact_margin, sub.dt),
        "skipped": skipped,
        "base_refit_explains": one["base_refit"],
        "data": {"episodes": sub.n_episodes, "steps_per_episode": sub.n_steps, "dt": sub.dt,
                 "instants": int(one["rows"]), "scheme": one["scheme"], "integrator": model.integrator,
                 "episodes_given": data.n_episodes, "steps_given": data.n_steps},
        "one_step": {
            "definition": ("M (a_recorded - a_model) N per world axis, I (alpha_b,recorded - alpha_b,model) N m "
                           "per rod-frame axis (z = rod axis)"),
            "force_rms": one["force_rms"],
            "torque_rms": one["torque_rms"],
            "relative": rel,
            "per_rod": one["per_rod"],
            "worst_rod": one["worst_rod"],
            "effect_rows": one["effect_rows"],
        },
        "k_step": {"after": k_after, "before": k_before if added else None},
        "free_run": {"before": fr_before["curve"], "after": fr_after["curve"], "time_s": fr_after["time"]},
        "regions": region_out,
        "whiteness": lb,
        "input_correlation": input_correlation(res, one["times"], sub),
        "best_feature": one["best_feature"],
        "plot_data": {"residual_time": one["time_series"], "feature": one["scatter"]},
    }
    return json_safe(result)


# ---------------------------------------------------------------------- parts
def _score_rule(weak_window: int | None, contact_margin: int | None, dt: float) -> str:
    """The candidates' score in words, for the rows it was computed on."""
    rows = "the one-step residual (rows: force and torque / rod half-length, world frame, every rod and instant"
    if weak_window and weak_window > 1:
        rows += f", each episode's rows summed over {weak_window * dt:g} s windows: the fit's weak form"
    if contact_margin is not None:
        rows += (f"; the rows of the rods the model's regional effects act on, and within {contact_margin * dt:g} s "
                 "of them, left out")
    return (f"fraction of {rows}) that adding the candidate would remove: 1 - RSS(model columns + candidate "
            "columns) / RSS(model columns), least squares with the model's own K, c, M, I, h (total mass held) free "
            "to move; score_alone: the fraction the candidate's columns alone explain; score_held_out: with the "
            "model's columns regressed out over all the data, the fraction of each half (1 s blocks, alternating) "
            "that the candidate's columns fitted on the other half remove, the smaller of the two; best first by "
            "score_held_out")


def _one_step_pass(model: IdentifiedModel, data: Dataset, src: str | None, chunk_steps: int,
                   weak_window: int | None, contact_margin: int | None
                   ) -> tuple[dict[str, Any], dict[str, Effect], list[dict[str, str]]]:
    """The one-step pass (:func:`.residual.one_step`) with the library's candidates the model
    lacks; the regions of the model's and the candidates' effects; the candidates not made."""
    candidates, skipped = _candidates(model, [str(e.get("name")) for e in model.effects], src)
    regions = _region_effects(model, candidates)
    return one_step(model, data, candidates, regions, chunk_steps, weak_window, contact_margin), regions, skipped


def _candidates(model: IdentifiedModel, added: list[str], src: str | None
                ) -> tuple[list[Effect], list[dict[str, str]]]:
    """The library's effects the model does not have, made for its system, and those that cannot
    be (with the reason)."""
    candidates, skipped = [], []
    for name, cls in EFFECTS.items():
        if name in added:
            continue
        if not cls.searched:  # named by the user only (its own docstring says why)
            skipped.append({"name": name, "reason": "not tried as a candidate: name it with --effects"})
            continue
        other = rival(name, added)
        if other is not None:  # another law of the same thing is in the model
            skipped.append({"name": name, "reason": f"the model has {other}, another law of the {cls.phenomenon}"})
            continue
        try:
            eff = make_effect(name, model.topology, src)
        except (GeometryError, ValueError, OSError) as exc:
            reason = str(exc) if src is not None else "no MJCF geometry (pass the plant's MJCF)"
            skipped.append({"name": name, "reason": reason})
            continue
        candidates.append(eff)
    skipped += [{"name": name, "reason": f"not available: {why}"} for name, why in RESERVED.items()]
    return candidates, skipped


def _region_effects(model: IdentifiedModel, candidates: list[Effect]) -> dict[str, Effect]:
    """Per region an effect class declares (``region``): the effect whose rows define it, the
    model's own fitted one first, else the candidate made from the MJCF."""
    out: dict[str, Effect] = {}
    for eff in [*effects_from_model(model), *candidates]:
        if eff.region is not None and eff.region not in out:
            out[eff.region] = eff
    return out


def _unavailable_regions(regions: dict[str, Effect], src: str | None) -> dict[str, dict[str, Any]]:
    """The regions the library declares that neither the model nor the MJCF could give."""
    out = {}
    for cls in EFFECTS.values():
        if cls.region is not None and cls.region not in regions and cls.region not in out:
            out[cls.region] = {"description": f"the rods {cls.name} acts on", "available": False,
                               "reason": f"no {cls.name} effect in the model and none from the MJCF"
                                         + ("" if src is not None else " (pass the plant's MJCF)")}
    return out


def _subset(data: Dataset, max_steps: int, H: int) -> Dataset:
    E, T = data.n_episodes, data.n_steps
    if E * T <= max_steps:
        return data
    T_use = min(T, max(H, max_steps))
    E_use = max(1, min(E, max_steps // T_use))
    return data.select(episodes=slice(0, E_use), steps=T_use)


def _mjcf_source(model: IdentifiedModel, mjcf: str | os.PathLike | None) -> str | None:
    if mjcf is not None:
        return os.fspath(mjcf)
    src = model.source_model
    if src and not str(src).startswith("preset:") and os.path.isfile(src):
        return str(src)
    return None


def _free_run(model: IdentifiedModel, data: Dataset, H: int) -> dict[str, Any]:
    """The free run's position error over steps 1..H (mean over episodes, rods and steps; ``None``:
    diverged) and its curve, subsampled."""
    fr = rollout_errors(model, data, H)
    err = fr["per_step"]["pos"]
    idx = np.unique(np.linspace(0, H, min(H + 1, _CURVE_POINTS)).round().astype(int))
    mean = fr["pos_mean_after_start"]
    return {"error": mean if np.isfinite(mean) else None,
            "curve": [float(v) if np.isfinite(v) else None for v in err[idx]],
            "time": (idx * data.dt).tolist()}
