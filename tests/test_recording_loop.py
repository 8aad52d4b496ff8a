"""The loop closed on a recording (tensegrity_gym.loop): the effect the diagnosis finds missing is
added by a refit, with its evidence and the free run before and after; nothing is added, and no
null is made, where nothing is missing.

The recordings of tests/test_diagnose_recording.py's kind (the robot in still air and in MuJoCo's
viscosity 2, 6 takes of 2 s, end-cap markers at 100 Hz, 1 mm, 2 % missing) against the robot's
ground-contact fit (tests/data/robot_ground_contact.json: no drag).
"""

from __future__ import annotations

import numpy as np
import pytest

from identified.diagnose import SUPPORTED_GAIN
from identified.fit.identify import ScaleSpec
from identified.fit.markers import fit_recording
from identified.model import load_model
from tensegrity_gym.loop import close_loop
from tests._data import GROUND
from tests._recordings import drag_recordings


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    return drag_recordings(tmp_path_factory.mktemp("loop"))


def _refit(rec, xml, calls):
    def refit(effects):
        calls.append(list(effects))
        return fit_recording(rec, xml, effects=list(effects), scale=ScaleSpec(total_mass=21.0), jobs=1)
    return refit


@pytest.mark.expensive  # ~40 s (a refit and the null); cheap siblings: the two tests below
def test_a_hidden_drag_is_added_with_its_evidence(recordings):
    rec, xml, calls = recordings["viscous"], recordings["xml"], []
    model = close_loop(load_model(str(GROUND)), rec, xml, _refit(rec, xml, calls))
    assert calls == [["ground_contact", "linear_drag"]]  # the best first; quadratic_drag is its rival after
    assert sorted(e["name"] for e in model.effects) == ["ground_contact", "linear_drag"]
    step = model.loop[-1]
    assert step["added"] == "linear_drag" and step["evidence"] == "held-out share on the recording"
    # the share is the held-out score beyond a null that holds no drag (a negative null counts as 0)
    assert step["share"] == pytest.approx(step["held_out"] - max(step["null"], 0.0), abs=1e-12)
    assert step["share"] >= SUPPORTED_GAIN and step["null"] < SUPPORTED_GAIN
    assert 0 < step["error_after"] < step["error_before"]
    rounds = model.metrics["recording_loop"]["rounds"]
    assert rounds[0]["effects"] == ["ground_contact"] and "null" in rounds[0]
    assert sorted(rounds[-1]["effects"]) == ["ground_contact", "linear_drag"]
    assert "null" not in rounds[-1] and max(rounds[-1]["held_out"].values()) < SUPPORTED_GAIN  # then it stops


def test_nothing_is_added_where_nothing_is_hidden(recordings):
    rec, xml, calls = recordings["still"], recordings["xml"], []
    model = close_loop(load_model(str(GROUND)), rec, xml, _refit(rec, xml, calls))
    assert calls == [] and model.loop == load_model(str(GROUND)).loop
    (only,) = model.metrics["recording_loop"]["rounds"]
    assert "null" not in only  # no candidate reached the threshold on the recording: no null made
    assert max(only["held_out"].values()) < SUPPORTED_GAIN and np.isfinite(list(only["held_out"].values())).all()


def test_fit_auto_on_a_recording_runs_the_loop(recordings, tmp_path, monkeypatch, capsys):
    """``tensegrity fit R.csv --effects auto`` passes the search's model to the loop and writes what
    it returns (the search itself stood in for by the robot's ground-contact fit: the wiring, cheaply)."""
    from identified.fit import markers
    from identified.recording import save_recording
    from tensegrity_gym.cli import main

    asked = []

    def search(rec, mjcf, effects, **kwargs):
        asked.append(effects)
        model = load_model(str(GROUND))
        model.metrics["recording"] = {"frames": rec.n_frames, "rate_hz": 100.0, "missing": 0.02}
        return model

    monkeypatch.setattr(markers, "fit_recording", search)
    path, out = str(tmp_path / "still.csv"), str(tmp_path / "F.json")
    save_recording(path, recordings["still"])
    assert main(["fit", path, "--model", recordings["xml"], "--total-mass", "21", "--effects", "auto",
                 "--out", out, "--quiet"]) == 0
    assert asked == ["auto"]
    written = load_model(out)
    assert written.metrics["recording_loop"]["rounds"][0]["effects"] == ["ground_contact"]
    assert "effects: ground_contact" in capsys.readouterr().out


def test_the_summary_says_a_loop_steps_evidence():
    model = load_model(str(GROUND))
    model.loop = [{"added": "linear_drag", "evidence": "held-out share on the recording", "share": 0.7283,
                   "held_out": 0.7283, "null": -0.006, "error_before": 0.04287, "error_after": 0.02961}]
    assert ("loop: added linear_drag: it removed 73% of the held-out residual beyond the null (held-out share on "
            "the recording); free-run error from every take's start 0.04287 m -> 0.02961 m") in model.summary()


def test_a_refit_that_fails_leaves_the_model_and_warns(recordings, monkeypatch):
    """Every candidate counted as missing (the threshold lowered, no null): the best one's refit is
    not identified; the search's model stays, the loop says why."""
    import identified.diagnose
    import tensegrity_gym.loop
    from identified.fit.regression import IdentifiabilityError

    monkeypatch.setattr(identified.diagnose, "SUPPORTED_GAIN", -1.0)
    monkeypatch.setattr(tensegrity_gym.loop, "recording_null", lambda *a, **k: None)

    def refit(effects):
        raise IdentifiabilityError("the data cannot identify constant_force.f", ["constant_force.f"])

    start = load_model(str(GROUND))
    model = close_loop(start, recordings["still"], recordings["xml"], refit)
    (only,) = model.metrics["recording_loop"]["rounds"]
    best = max(only["held_out"], key=only["held_out"].get)
    assert only["refit_failed"] == f"{best}: the data cannot identify constant_force.f"
    assert model.loop == start.loop and [e["name"] for e in model.effects] == ["ground_contact"]
    assert model.metrics["warnings"][-1].startswith(f"the diagnosis finds {best} missing")
