"""The effect search's rules, each on its own numbers (milliseconds, not a search of minutes).

The search adds a candidate on the free-run evidence (:func:`halves`), failing that on the
one-step evidence (:func:`one_step_evidence`), stops when its model leaves nothing to find
(:func:`exhausted`) and calls what it leaves explained by :func:`search_explained`; each rule is
checked at and beside its thresholds, and the search's use of the last two on stand-in fits.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from identified.fit.checks import ROUNDING
from identified.fit.pipeline import (
    FREE_RUN_FLOOR,
    ONE_STEP_FLOOR,
    exhausted,
    halves,
    one_step_evidence,
    search_explained,
)

INF = math.inf


def test_free_run_evidence_halves_from_above_rounding():
    assert halves(0.2, 0.1) and halves(0.2, 0.1, min_gain=2.0)
    assert not halves(0.2, 0.1000001)
    assert halves(1.0, 0.25, min_gain=4.0) and not halves(0.99, 0.25, min_gain=4.0)
    assert not halves(FREE_RUN_FLOOR / 2, 0.0)  # both at rounding: no evidence, whatever the ratio
    assert halves(FREE_RUN_FLOOR, 0.0)
    assert not halves(1.0, INF) and not halves(1.0, math.nan)
    assert halves(INF, 1.0)  # a base model whose free run diverged, a candidate whose does not


def test_one_step_evidence_cuts_the_one_step_error_without_spoiling_the_free_run():
    # one-step 0.022 -> 6e-14 (the robot's exact drag), free run 0.0185 -> 0.026 m: within 2x, added
    assert one_step_evidence(0.022, 6e-14, 0.0185, 0.026)
    # the one-step error must fall by min_gain ...
    assert one_step_evidence(0.02, 0.01, 0.1, 0.1) and not one_step_evidence(0.02, 0.0100001, 0.1, 0.1)
    assert not one_step_evidence(0.02, 0.01, 0.1, 0.1, min_gain=3.0)
    # ... from above the floor (rounding: no evidence)
    assert not one_step_evidence(ONE_STEP_FLOOR, 0.0, 0.1, 0.1)
    assert one_step_evidence(2 * ONE_STEP_FLOOR, 0.0, 0.1, 0.1)
    # ... and the free run may not get min_gain worse, nor diverge
    assert one_step_evidence(0.02, 0.0, 0.1, 0.2) and not one_step_evidence(0.02, 0.0, 0.1, 0.2000001)
    assert not one_step_evidence(0.02, 0.0, 0.1, INF) and not one_step_evidence(0.02, 0.0, INF, INF)
    assert one_step_evidence(0.02, 0.0, INF, 5.0)  # a diverging model made finite


def test_search_explained_by_rounding_or_a_fivefold_cut():
    assert search_explained(ROUNDING / 2, 1.0, 1.0)  # rounding-level residual
    assert not search_explained(ROUNDING, 1.0, 1.0)
    assert search_explained(None, 1.0, 0.2) and not search_explained(None, 1.0, 0.2000001)
    assert search_explained(0.5, 0.0, 0.0)  # nothing to explain
    assert not search_explained(0.5, 1.0, 0.5)
    assert search_explained(None, INF, 1.0)


def test_exhausted_needs_both_a_rounding_residual_and_a_rounding_one_step_error():
    assert exhausted(ROUNDING / 2, ONE_STEP_FLOOR)
    assert not exhausted(ROUNDING, ONE_STEP_FLOOR)  # the fitted equations' residual above rounding
    assert not exhausted(ROUNDING / 2, 2 * ONE_STEP_FLOOR)  # the held-out one-step error above it
    assert not exhausted(None, 0.0) and not exhausted(ROUNDING / 2, math.nan)


# --- the search on stand-in fits: which fits it makes, and what each starts from -------------------

#: held-out errors of the stand-ins: linear drag cuts the free run 10x; beside it a constant force
#: would cut it again 10x (a second round would add it)
_ERR = {(): 1.0, ("linear_drag",): 0.1, ("constant_force",): 0.8, ("linear_drag", "constant_force"): 0.01}


class _Model:
    def __init__(self, effects, takes: int, residual: float) -> None:
        self.names = tuple(e.name for e in effects)
        self.takes, self.residual = takes, residual
        self.effects = [e.to_json() for e in effects]
        self.metrics: dict = {}
        self.loop: list = []


def _search(monkeypatch, residual: float, one_step: float, warm: bool, base_one_step: float = 1.0,
            recording_needs: int | None = None):
    """Run ``fit_model(effects="auto")`` in one process on stand-ins; the fits made, in order, as
    (effects, takes, each effect's starting values, steps).  ``recording_needs``: the data are a
    recording's (with a noise replica; 4 takes of 2400 steps, the search's part 3000 steps in all),
    and a fit with effects on fewer steps a take than this is not identified."""
    from identified import predict
    from identified.effects.linear_drag import LinearDrag
    from identified.fit import checks, pipeline
    from identified.fit.regression import IdentifiabilityError
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import write_model

    fits: list = []

    def identify(data, topology, effects=(), **kw):
        names = tuple(e.name for e in effects)
        if names not in _ERR:
            raise IdentifiabilityError("not a stand-in")
        assert torch.get_num_threads() == 1  # the fit runs on one torch thread
        fits.append((names, data.n_episodes, [None if e.values is None else e.values.tolist() for e in effects],
                     data.n_steps))
        if names and recording_needs is not None and data.n_steps < recording_needs:
            raise IdentifiabilityError("too few rows off the ground")
        for k, e in enumerate(effects):  # fitted values: the fit's index, so a start says which fit it came from
            e.values = np.full(e.n_params, float(len(fits)))
        return _Model(effects, data.n_episodes, residual)

    monkeypatch.setattr(LinearDrag, "warm_starts", warm)
    monkeypatch.setattr(pipeline, "identify", identify)
    monkeypatch.setattr(pipeline, "window_error", lambda m, data, steps: _ERR[m.names])
    monkeypatch.setattr(pipeline, "_free_run", lambda m, ctx: math.inf if m is None else _ERR[m.names])
    monkeypatch.setattr(pipeline, "one_step_parts", lambda m, data, scheme=None: m)
    monkeypatch.setattr(pipeline, "_one_step_errors",
                        lambda ctx, parts, models: [one_step if m is not None and m.names else base_one_step
                                                    for m in models])
    monkeypatch.setattr(pipeline, "relative_residual", lambda m: m.residual)
    for mod, name in ((checks, "refresh_physics"), (checks, "residual_check"), (predict, "attach_metrics")):
        monkeypatch.setattr(mod, name, lambda *a, **k: None)
    import os
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "ico.xml")
        write_model(path, "ico", preset="paper-uniform")
        if recording_needs is None:
            data = collect(path, CollectConfig(episodes=4, steps=30, seed=1))
        else:
            from dataclasses import replace

            data = collect(path, CollectConfig(episodes=4, steps=2400, seed=1))
            data = replace(data, replicas=(data,))
            monkeypatch.setattr(pipeline, "RECORDING_SEARCH_STEPS", 3000)
        threads = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            model = pipeline.fit_model(data, path, effects="auto", jobs=1)
            assert torch.get_num_threads() == 2  # the caller's count given back
        finally:
            torch.set_num_threads(threads)
    return model, fits


def test_the_search_stops_where_its_model_leaves_nothing_to_find(monkeypatch):
    """Linear drag cuts the error 10x; with a rounding-level residual and one-step error after it,
    no second round is fitted (its constant force would have cut the free run again); with a
    residual just above rounding the second round runs and adds it."""
    model, fits = _search(monkeypatch, residual=ROUNDING / 2, one_step=ONE_STEP_FLOOR / 2, warm=False)
    assert [s["added"] for s in model.loop] == ["linear_drag"]
    made = [f[:2] for f in fits]  # the base, the first round (linear_drag twice: its variant), the final fit
    assert made == [((), 3), (("linear_drag",), 3), (("linear_drag",), 3), (("constant_force",), 3),
                    (("linear_drag",), 4)]
    model, fits = _search(monkeypatch, residual=ROUNDING * 2, one_step=ONE_STEP_FLOOR / 2, warm=False)
    assert [s["added"] for s in model.loop] == ["linear_drag", "constant_force"]
    assert (("linear_drag", "constant_force"), 3) in [f[:2] for f in fits]


def test_a_model_without_effects_that_leaves_nothing_is_not_searched(monkeypatch):
    """Clean data: the model without effects has a rounding-level residual and held-out one-step
    error, so no candidate is fitted (the base fit, then the final fit on all the data); one
    held-out one-step error above the floor and the candidates are fitted (and linear drag added)."""
    model, fits = _search(monkeypatch, residual=ROUNDING / 2, one_step=ONE_STEP_FLOOR / 2, warm=False,
                          base_one_step=ONE_STEP_FLOOR)
    assert [f[:2] for f in fits] == [((), 3), ((), 4)]
    assert model.loop == [] and model.metrics["effect_search"]["explained"] is True
    model, fits = _search(monkeypatch, residual=ROUNDING / 2, one_step=ONE_STEP_FLOOR / 2, warm=False,
                          base_one_step=2 * ONE_STEP_FLOOR)
    assert len(fits) == 5 and [s["added"] for s in model.loop] == ["linear_drag"]


def test_a_recording_part_no_candidate_fits_on_is_doubled(monkeypatch):
    """On a recording the candidates are fitted on the middle of each training take (3000 steps in
    all: 1000 of each of 3 takes); where no candidate of the first round can be fitted there, the
    search runs again on twice as much (2000 a take), and says what it was fitted on (a failed fit
    has an infinite screen, as has a twin that diverged)."""
    model, fits = _search(monkeypatch, residual=ROUNDING * 2, one_step=1.0, warm=False, recording_needs=2000)
    first = [f for f in fits if f[3] == 1000]
    assert [f[0] for f in first] == [(), ("linear_drag",), ("linear_drag",), ("constant_force",)]  # none ran
    assert fits[len(first)][:2] == ((), 3) and fits[len(first)][3] == 2000  # the search again, on 2000
    assert [s["added"] for s in model.loop] == ["linear_drag", "constant_force"]
    assert model.metrics["effect_search"]["fitted_on"].startswith("the middle 2 s of each of 3 training takes")
    assert fits[-1][:2] == (("linear_drag", "constant_force"), 4) and fits[-1][3] == 2400  # the final fit: all
    # where the part suffices, one search on it
    model, fits = _search(monkeypatch, residual=ROUNDING * 2, one_step=1.0, warm=False, recording_needs=1000)
    assert {f[3] for f in fits[:-1]} == {1000}
    assert model.metrics["effect_search"]["fitted_on"].startswith("the middle 1 s of each of 3 training takes")


def test_a_warm_starting_effect_is_refitted_from_the_values_the_search_found(monkeypatch):
    """The final fit of an effect that ``warm_starts`` starts from the values of the fit that chose
    the model (the second round's, which added the constant force beside it); the rounds' refits
    search afresh, and any other effect starts unfitted."""
    model, fits = _search(monkeypatch, residual=ROUNDING * 2, one_step=1.0, warm=True)
    assert [s["added"] for s in model.loop] == ["linear_drag", "constant_force"]
    both = ("linear_drag", "constant_force")
    k = next(i for i, f in enumerate(fits) if f[:2] == (both, 3))  # the second round's fit that chose it
    assert all(v is None for f in fits[:-1] for v in f[2])  # every fit of the search from its own starts
    final = fits[-1]
    assert final[:2] == (both, 4) and final[2][0] == [k + 1.0] * len(final[2][0]) and final[2][1] is None
    _, fits = _search(monkeypatch, residual=ROUNDING * 2, one_step=1.0, warm=False)
    assert all(v is None for f in fits for v in f[2])


def test_a_search_that_adds_nothing_says_so_when_the_bare_model_is_not_identified(monkeypatch, tmp_path):
    """The search adds no effect and the spring-rod model alone is not identified (a robot on the
    ground with no contact law): the refusal names the search's outcome and what to do, keeping the
    rank error's parameters; a fit asked for no effects keeps the rank error as it is."""
    import pytest

    from identified.fit import pipeline
    from identified.fit.regression import IdentifiabilityError
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import write_model

    def identify(data, topology, effects=(), **kw):
        raise IdentifiabilityError("the data cannot identify cable0.stiffness", ["cable0.stiffness"])

    monkeypatch.setattr(pipeline, "identify", identify)
    monkeypatch.setattr(pipeline, "_select_effects", lambda *a, **k: ([], [], False, {}, None, None))
    path = str(tmp_path / "ico.xml")
    write_model(path, "ico", preset="paper-uniform")
    data = collect(path, CollectConfig(episodes=4, steps=30, seed=1))
    with pytest.raises(IdentifiabilityError) as err:
        pipeline.fit_model(data, path, effects="auto", jobs=1)
    said = str(err.value)
    assert said.startswith("--effects auto added no effect") and "cable0.stiffness" in said
    assert "--effects ground_contact" in said and err.value.names == ["cable0.stiffness"]
    with pytest.raises(IdentifiabilityError, match="^the data cannot identify cable0.stiffness$"):
        pipeline.fit_model(data, path, effects="none", jobs=1)
