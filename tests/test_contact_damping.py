"""identified.fit.contact_damping: the scan over the friction damping's factors, against a known
error profile (the free runs' error replaced by a function of the factor with its minimum at 3):
the factor of least error chosen, both dampings scaled by it exactly, their error bars withdrawn,
a diverged run skipped, the takes and steps the free runs start from bounded.  The free runs
themselves are the expensive tests of test_recording_fit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from identified.fit import contact_damping
from identified.fit.contact_damping import FACTORS, MAX_STEPS, WINDOW_STEPS, refine_friction_damping
from tensegrity_gym.collect import CollectConfig, collect

from .test_record_output_error import _robot, _truth

FITTED = {"beta_a": 4.0, "beta_p": 2.5}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    path = _robot(tmp_path_factory.mktemp("cd"), floor=True)
    data = collect(path, CollectConfig(episodes=2, steps=400, seed=1))
    return _truth(path), data


def _law_model(truth):
    law = {"name": "ground_contact", "parameters": {**FITTED, "kappa": 1e4},
           "stderr": {"beta_a": 0.4, "beta_p": 0.3, "kappa": 10.0}}
    return dataclasses.replace(truth, effects=[{"name": "linear_drag", "parameters": {}}, law])


def _profile(best: float, diverged: tuple[float, ...] = (), nan: tuple[float, ...] = ()):
    """A stand-in for the free runs' error: ``(log(f / best))^2 + 0.01`` m at the factor ``f`` the
    model's beta_a carries, infinite at ``diverged``, NaN at ``nan``; the calls recorded."""
    seen = []

    def error(model, part, steps):
        f = model.effects[1]["parameters"]["beta_a"] / FITTED["beta_a"]
        assert model.effects[1]["parameters"]["beta_p"] == pytest.approx(f * FITTED["beta_p"], rel=1e-15)
        seen.append((f, part.n_episodes, part.n_steps, steps, part.replicas))
        if any(abs(f - d) < 1e-12 for d in nan):
            return np.nan
        return np.inf if any(abs(f - d) < 1e-12 for d in diverged) else float(np.log(f / best) ** 2 + 0.01)

    return error, seen


def test_the_factor_of_least_error_scales_both_and_withdraws_their_error_bars(setup, monkeypatch):
    truth, data = setup
    error, seen = _profile(3.0, diverged=(12.0,), nan=(1.0,))
    monkeypatch.setattr(contact_damping, "window_error", error)
    model = _law_model(truth)
    noisy = dataclasses.replace(data, replicas=(data,))  # noise copies: the free runs start from the data alone
    out = refine_friction_damping(model, noisy, jobs=1)
    assert out["factor"] == 3.0 and out["window_steps"] == WINDOW_STEPS
    assert out["errors"]["3.0"] == pytest.approx(0.01) and out["errors"]["12.0"] is None is out["errors"]["1.0"]
    assert sorted(f for f, *_ in seen) == sorted(FACTORS)
    assert {(e, n, s, r) for _, e, n, s, r in seen} == {(2, min(MAX_STEPS, data.n_steps), WINDOW_STEPS, ())}
    law = model.effects[1]
    assert law["parameters"] == {"beta_a": 12.0, "beta_p": 7.5, "kappa": 1e4}
    assert law["stderr"] == {"beta_a": None, "beta_p": None, "kappa": 10.0}


def test_a_fit_already_at_its_least_error_keeps_its_values_and_error_bars(setup, monkeypatch):
    truth, data = setup
    monkeypatch.setattr(contact_damping, "window_error", _profile(1.0)[0])
    model = _law_model(truth)
    assert refine_friction_damping(model, data, jobs=1)["factor"] == 1.0
    assert model.effects[1]["parameters"]["beta_a"] == 4.0 and model.effects[1]["stderr"]["beta_p"] == 0.3


def test_nothing_to_scan_without_the_law_or_a_window(setup, monkeypatch):
    truth, data = setup
    error, seen = _profile(3.0)
    monkeypatch.setattr(contact_damping, "window_error", error)
    assert refine_friction_damping(truth, data, jobs=1) is None  # no ground_contact
    assert refine_friction_damping(_law_model(truth), data.select(steps=WINDOW_STEPS), jobs=1) is None  # too short
    assert seen == []
