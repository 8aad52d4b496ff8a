"""The loop closed on a recording: effects the diagnosis finds missing, added one at a time.

``tensegrity fit R.csv --effects auto`` first runs the fit's effect search
(:func:`identified.fit.pipeline.fit_model`: forward selection on held-out takes by their free-run
and one-step errors).  On rod states reconstructed from markers, a drag on every rod is beyond
that search: its one-step rows are the splines' second derivatives, noise-dominated, and its gain
in the free run hides under the contact law's own error (the robot in MuJoCo's viscosity 2, 100 Hz,
1 mm: held-out screen 2.2 vs 3.2 mm, not the 2x the search asks).  The diagnosis reads it
(:func:`identified.diagnose.diagnose` on a recording: every candidate's share of the residual it
removes on held-out 1 s blocks of the weak-form rows the fit reads, beyond the same share on a
*null*, the identified model's own motion recorded with the recording's rate, gaps and noise).

:func:`close_loop` runs what a user would run by hand after ``diagnose``: while a candidate of the
library (not one of the model's effects, nor a rival law of one) removes at least
:data:`~identified.diagnose.SUPPORTED_GAIN` of the held-out residual beyond its null, the model is
refitted with it added (the best first), and each step goes into the model's ``loop`` section with
its evidence and the free-run error over :data:`HORIZON_S` from every take's reconstructed start,
before and after.  The null (two draws of the markers' noise, the largest share) is made only when
a candidate's share on the recording alone reaches the threshold: a still recording costs one
scoring pass (~7 s for 10 takes of 10 s).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from identified.model import IdentifiedModel
from identified.threads import torch_threads

__all__ = ["HORIZON_S", "MAX_ADDED", "NULL_DRAWS", "close_loop", "recording_null"]

#: draws of the markers' noise for the diagnosis's null on a recording (measured: the robot in still air
#: at 60 Hz / 2 mm, one draw gave a constant force -0.18 held out, another 0.38, the recording 0.28)
NULL_DRAWS = 2
#: the free run (s) whose error each step of the loop reports, from every take's reconstructed start
HORIZON_S = 1.0
#: effects the loop adds at most after the search (each costs a refit)
MAX_ADDED = 3


@torch_threads(1)
def recording_null(model: IdentifiedModel, data: Any, rec: Any, noise: float | None, mjcf: str | None,
                   scoring: dict[str, int]) -> dict[str, float | None] | None:
    """Each candidate's held-out score on the diagnosis's null: the model's own motion under the
    recording's inputs, recorded with its rate, gaps and noise
    (:func:`tensegrity_gym.collect.twin_recordings`), reconstructed and scored alike, the largest
    over :data:`NULL_DRAWS` draws of the noise; ``None`` (and a note) where it cannot be made."""
    from identified.diagnose import held_out_scores
    from identified.fit.markers import recording_dataset
    from tensegrity_gym.collect import twin_recordings

    src = mjcf or (model.source_model if model.source_model and os.path.isfile(model.source_model) else None)
    if src is None:
        print("tensegrity: note: no null for the candidates (pass the robot's MJCF with --model): their held-out "
              "shares include what reconstructing the markers makes up", file=sys.stderr)
        return None
    try:
        twins = twin_recordings(model, data, src, rec, noise or 0.0, range(NULL_DRAWS))
    except ValueError as exc:
        print(f"tensegrity: note: no null for the candidates ({exc})", file=sys.stderr)
        return None
    out: dict[str, float | None] = {}
    for twin in twins:  # the largest over draws of the markers' noise: one draw's score scatters
        for name, v in held_out_scores(model, recording_dataset(twin, model), mjcf=src, **scoring).items():
            old = out.get(name)
            out[name] = v if old is None else (old if v is None else max(old, v))
    return out


def _free_run(model: IdentifiedModel, data: Any) -> float | None:
    """The free-run position error (m) over :data:`HORIZON_S` from every take's start, ``None`` if it diverged."""
    from identified.evaluate import rollout_errors

    H = max(1, min(data.n_steps, round(HORIZON_S / data.dt)))
    err = rollout_errors(model, data, H)["pos_mean_after_start"]
    return float(err) if np.isfinite(err) else None


@torch_threads(1)
def close_loop(model: IdentifiedModel, rec: Any, mjcf: str, refit: Callable[[list[str]], IdentifiedModel],
               progress: bool = False) -> IdentifiedModel:
    """The model with the effects the diagnosis finds missing added one at a time (module
    docstring); ``model``: the fit of ``rec`` (a :class:`~identified.recording.Recording`) with
    ``--effects auto``; ``refit(effects)``: the same fit with these effects named.  Each step is
    appended to the returned model's ``loop`` (``added``, ``evidence``, ``share``, ``null``,
    ``error_before``/``error_after``: the free run's, m); ``metrics["recording_loop"]`` says what
    was scored and what it cost.  A refit that fails (the effect not identified by the data) leaves
    the model as it was, with a warning in ``metrics["warnings"]``."""
    from identified.diagnose import SUPPORTED_GAIN, held_out_scores, held_out_share
    from identified.effects import EFFECTS, rival
    from identified.fit.markers import diagnosis_options, recording_states

    t0 = time.perf_counter()
    states = recording_states(rec, model, noise=True)  # the reconstruction does not depend on the parameters
    data = states.data
    scoring = diagnosis_options(rec, model.dt)
    loop = list(model.loop)
    search = model.metrics.get("effect_search")
    rounds: list[dict[str, Any]] = []
    current: float | None = None  # the current model's free run, once made (the last refit's)
    for _ in range(MAX_ADDED):
        names = [e["name"] for e in model.effects]
        t = time.perf_counter()
        raw = held_out_scores(model, data, mjcf=mjcf, **scoring)
        open_ = {n: v for n, v in raw.items() if v is not None and n in EFFECTS and n not in names
                 and rival(n, names) is None}
        entry: dict[str, Any] = {"effects": names, "held_out": dict(open_),
                                 "seconds": {"scores": round(time.perf_counter() - t, 2)}}
        rounds.append(entry)
        if not open_ or max(open_.values()) < SUPPORTED_GAIN:
            break  # nothing the data support, even before the null
        t = time.perf_counter()
        null = recording_null(model, data, rec, states.marker_noise, mjcf, scoring) or {}
        entry["seconds"]["null"] = round(time.perf_counter() - t, 2)
        entry["null"] = {k: null.get(k) for k in open_}
        share = {n: held_out_share({"score_held_out": v, **({"score_held_out_null": null[n]} if n in null else {})})
                 for n, v in open_.items()}
        best = max(share, key=lambda n: share[n] if share[n] is not None else -np.inf)
        if share[best] is None or share[best] < SUPPORTED_GAIN:
            break
        if progress:
            print(f"loop: {best} removes {share[best]:.0%} of the held-out residual beyond the null: refitting "
                  f"with {', '.join([*names, best])}", flush=True)
        t = time.perf_counter()
        try:
            new = refit([*names, best])
        except ValueError as exc:  # not identified with it (IdentifiabilityError, DatasetError): the model stays
            entry["refit_failed"] = f"{best}: {exc}"
            warning = (f"the diagnosis finds {best} missing ({share[best]:.0%} of the held-out residual beyond the "
                       f"null) but the fit with it failed: {exc}")
            model.metrics.setdefault("warnings", []).append(warning)
            break
        entry["seconds"]["refit"] = round(time.perf_counter() - t, 2)
        t = time.perf_counter()
        before = current if current is not None else _free_run(model, data)
        after = current = _free_run(new, data)
        entry["seconds"]["free_runs"] = round(time.perf_counter() - t, 2)
        loop.append({"added": best, "evidence": "held-out share on the recording",
                     "share": float(share[best]), "held_out": float(open_[best]),
                     "null": None if null.get(best) is None else float(null[best]),
                     "error_before": before, "error_after": after,
                     "metric": f"free-run position error over {HORIZON_S:g} s from every take's reconstructed start (m)"})
        model = new
    model.loop = loop
    if search is not None:  # the search that chose the first model's effects (a refit names them)
        model.metrics["effect_search"] = search
    model.metrics["recording_loop"] = {
        "rounds": rounds, "supported_gain": SUPPORTED_GAIN, "seconds": round(time.perf_counter() - t0, 2),
        "rule": (f"a candidate removing >= {SUPPORTED_GAIN:g} of the held-out weak-form residual beyond its share "
                 f"on the model's own motion recorded alike is added, best first, up to {MAX_ADDED}")}
    return model

