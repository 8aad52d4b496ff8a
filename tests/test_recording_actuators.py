"""Recordings of a robot with MuJoCo actuators: the commands sent (``<actuator>.ctrl``) reach the
fit at every step, the actuators' gains come out of the markers, the marker fit's windows step the
actuators, and a recording without the commands is refused."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
import torch

from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit import contact_damping
from identified.fit.identify import ScaleSpec
from identified.fit.markers import fit_recording, recording_states, states_from_recording
from identified.fit.output_error import window_problem
from identified.fit.pipeline import fit_model
from identified.recording import RecordingError, read_recording, save_recording
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model

#: two MuJoCo motors pulling on two of the robot's cables (besides its rest-length motors)
MOTORS = ('<actuator><motor name="pull0" tendon="cable0" gear="-40" ctrlrange="0 1"/>'
          '<motor name="pull1" tendon="cable7" gear="-60" ctrlrange="0 1"/></actuator>')
GAINS = {"pull0": -40.0, "pull1": -60.0}


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    d = tmp_path_factory.mktemp("motors")
    plain = str(d / "plain.xml")
    write_model(plain, "ico", preset="robot")
    path = str(d / "robot.xml")
    with open(plain, encoding="utf-8") as fh:
        xml = fh.read().replace("</mujoco>", MOTORS + "</mujoco>")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(xml)
    return path, Topology.from_mjcf(path), d


def test_commands_reach_the_dataset_at_every_step(robot):
    """Commands logged at 1 kHz between 100 Hz frames are the plant's own at every step (to the
    CSV's 1e-7); logged at the frames, each is held until the next frame."""
    path, topo, d = robot
    data = collect(path, CollectConfig(episodes=2, steps=800, seed=3))
    assert data.actuator_names == ("pull0", "pull1") and np.ptp(data.ctrl) > 0.5
    for rate in (None, 1000.0):
        rec = record_markers(data, path, RecordConfig(rate=100, encoder_rate=rate), seed=1)
        p = d / f"r{rate}.csv"
        save_recording(p, rec)
        back = read_recording(p)
        assert back.ctrl_names == ("pull0", "pull1")
        ms = states_from_recording(back, topo)
        assert ms.data.actuator_names == ("pull0", "pull1")
        for e in range(2):
            s = round(ms.starts[e] / data.dt)
            steps = s + np.arange(ms.data.n_steps)
            held = steps if rate else (steps // 10) * 10  # the frames are every 10th step
            np.testing.assert_allclose(ms.data.ctrl[e], data.ctrl[e, held], atol=6e-8)


def test_recordings_without_the_commands_are_refused(robot):
    path, topo, _d = robot
    data = collect(path, CollectConfig(episodes=1, steps=300, seed=4))
    rec = record_markers(data, path, RecordConfig(rate=100), seed=1)
    none = dataclasses.replace(rec, ctrl_names=(), ctrl=np.zeros((rec.n_frames, 0)))
    with pytest.raises(RecordingError, match=r"no 'pull0.ctrl' column: the model's MuJoCo actuators pull on its "
                                             r"cables.*\(2 of 2 have none\)"):
        states_from_recording(none, topo)
    other = dataclasses.replace(rec, ctrl_names=("pull0", "winch9"))
    with pytest.raises(RecordingError, match=r"column 'winch9.ctrl': the model has no actuator 'winch9' "
                                             r"\(actuators: pull0, pull1\)"):
        states_from_recording(other, topo)
    late = rec.ctrl.copy()
    late[:5] = np.nan  # the log starts after the take's first frames
    with pytest.raises(RecordingError, match=r"line 7, column 'pull0.ctrl': its first command \(0.05 s\) comes after"):
        states_from_recording(dataclasses.replace(rec, ctrl=late), topo)


@pytest.fixture(scope="module")
def fitted(robot):
    """The robot's 6 takes of 5 s at 100 Hz, fitted with ground_contact; the law's friction damping
    taken as the regression's (one factor: the scan is test_contact_damping's, and takes 18 s here)."""
    path, _topo, _d = robot
    data = collect(path, CollectConfig(episodes=6, steps=5000, seed=2))
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02, encoder_rate=1000.0),
                         seed=2)
    # a stretch sensor on cable3 whose zero is 2 mm off: checked against the markers, not fitted
    steps = np.round(rec.time / data.dt).astype(int)
    t = lambda x: torch.as_tensor(x[rec.episode, steps], dtype=torch.float64)
    ends = endpoint_kinematics(Topology.from_mjcf(path), t(data.pos), t(data.quat), t(data.vel), t(data.angvel))
    length = spring_geometry(ends).length.numpy()[:, [3]] + 0.002
    rec = dataclasses.replace(rec, length_names=("cable3",), length=length,
                              encoders=dataclasses.replace(rec.encoders, length=np.full((rec.encoders.time.size, 1), np.nan)))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(contact_damping, "FACTORS", (1.0,))
        model = fit_recording(rec, path, effects="ground_contact", scale=ScaleSpec(total_mass=21.0), jobs=1)
    return path, rec, model


def test_gains_from_a_recording(fitted):
    """Markers at 100 Hz with 1 mm noise and 2 % missing, commands at 1 kHz: each motor's gain
    (gear x gain, the truth) within 2 %, its error bar covering it, the cables within 1 %."""
    path, _rec, model = fitted
    m = mujoco.MjModel.from_xml_path(path)
    for a in model.actuators:
        g = GAINS[a["name"]]
        assert abs(a["gain"] / g - 1) < 0.02 and abs(a["gain"] - g) < 3 * a["gain_stderr"], a
    K = m.tendon_stiffness[[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, s) for s in model.topology.spring_names]]
    assert np.abs(model.stiffness / K - 1).max() < 0.01


@pytest.fixture(scope="module")
def exact(robot):
    """Two takes of 2 s of the robot, the full-state fit (exact: its gains to 1e-6) and their clean
    100 Hz markers with the commands at 1 kHz."""
    path = robot[0]
    data = collect(path, CollectConfig(episodes=2, steps=2000, seed=7))
    model = fit_model(data, path, effects="ground_contact", scale=ScaleSpec(total_mass=21.0), jobs=1)
    rec = record_markers(data, path, RecordConfig(rate=100, encoder_rate=1000.0), seed=1)
    return path, data, model, rec


def test_the_marker_fits_windows_step_the_actuators(exact):
    """The marker fit's windows (the output-error fit through the engine) apply the actuators'
    forces from the recorded commands: started from the plant's own states with the parameters a
    full-state fit recovers exactly, they put every simulated marker where the plant's was, to
    rounding; without the actuators' forces, centimetres off."""
    path, data, full, rec = exact
    assert [round(a["gain"], 6) for a in full.actuators] == [GAINS["pull0"], GAINS["pull1"]]
    off = {}
    for name, model in (("with", full), ("without", dataclasses.replace(full, actuators=[]))):
        # order 0: the rods near the ground move as recorded, the others are simulated
        win, _, prob, dx, _ = window_problem(model, rec, data, [0.0, 0.0], path, 0.001, [], 10, 64, order=0)
        assert win.n_windows == 40 and 0.3 < float(win.free.float().mean()) < 0.9
        off[name] = 0.001 * float(prob.window_residuals(prob.theta0, dx).abs().max())
    assert off["with"] < 1e-12 and off["without"] > 0.01


def test_the_marker_fit_writes_its_gains_and_holds_the_rest(robot):
    """The model the marker fit writes carries its own estimates of the actuators' gains with their
    error bars; their biases and filters, held at its start's values in the windows, get no error bar
    (the start's would read as this fit's) and the model says they are held, in the file and in
    its summary."""
    from identified.fit.bound import CramerRao
    from identified.fit.marker_fit import MarkerFit
    from identified.fit.marker_model import _model
    from identified.model import load_model, save_model

    path, topo, d = robot
    data = collect(path, CollectConfig(episodes=1, steps=1500, seed=2))
    start = fit_model(data, path, effects="ground_contact", scale=ScaleSpec(total_mass=21.0), jobs=1)
    assert all(a["gain_stderr"] is not None for a in start.actuators)
    names = ([f"K[{s}]" for s in topo.spring_names] + [f"c[{s}]" for s in topo.spring_names]
             + [f"M[{r}]" for r in topo.rod_names] + ["gain[pull0]", "gain[pull1]"])
    gains = np.array([-41.0, -57.0])
    values = np.concatenate([start.stiffness, start.damping, start.mass, gains])
    rel = np.full(len(names), 0.01)
    rel[-1] = 0.5  # a gain the markers cannot see: its value written, no error bar, and said
    cov = CramerRao(names, values, np.diag(rel ** 2), np.ones(len(names), dtype=bool))
    model = _model(start, MarkerFit(cov, 8, 8, 0.001, [1.0], 1.0), None, [])
    assert [a["gain"] for a in model.actuators] == [-41.0, -57.0]
    assert model.actuators[0]["gain_stderr"] == pytest.approx(0.41) and model.actuators[1]["gain_stderr"] is None
    assert "gain[pull1]: not identifiable from these markers (standard error 50 %)" in model.metrics["not_identifiable"]
    for a in model.actuators:
        assert a["bias_stderr"] is None and "bias and time constant at the start's" in a["held"]
    assert np.allclose(model.stderr["stiffness"], 0.01 * start.stiffness)  # the fit's own bars, where it has them
    save_model(d / "held.json", model)
    back = load_model(d / "held.json")
    assert back.actuators == model.actuators and "(held: bias and time constant at the start's" in back.summary()


def test_the_marker_fit_estimates_the_actuators_gains(exact):
    """The marker fit's windows step the actuators at gains it estimates with K, c and M: from the
    plant's own states, clean markers and the exact K, c, M, gains started 10 % off come back to
    the plant's (within 1e-3 after three joint steps, the cost 1e4 times lower).  The output-error
    refinement of the regression holds them (they are not among its unknowns)."""
    from identified.fit.marker_bound import _names
    from identified.fit.marker_fit import fit_markers

    path, data, full, rec = exact
    start = dataclasses.replace(full, actuators=[{**a, "gain": a["gain"] * f} for a, f in zip(full.actuators, (1.1, 0.9))])
    # order 0: the rods near the ground move as recorded (the plant's states), the others simulated
    fit = fit_markers(start, rec, data, [0.0, 0.0], path, 0.001, frames=5, max_windows=8, state_iters=0,
                      joint_iters=3, wrench_order=0)
    got = dict(zip(fit.cov.names, fit.cov.values))
    assert got["gain[pull0]"] == pytest.approx(GAINS["pull0"], rel=1e-3)
    assert got["gain[pull1]"] == pytest.approx(GAINS["pull1"], rel=1e-3)
    assert fit.history[-1] < 1e-4 * fit.history[0]
    _, _, prob, _, _ = window_problem(start, rec, data, [0.0, 0.0], path, 0.001, [], 5, 8, order=0)
    assert "gain[pull0]" not in _names(prob, start)  # held where not asked for (the 100 Hz refinement)


def test_the_fit_reports_measured_lengths(fitted):
    """A recording's ``.length`` columns are checked against the markers' lengths (1 mm noise: the
    2 mm zero comes back to a tenth of a millimetre), a cable that follows raises no warning."""
    _, _, model = fitted
    report = model.metrics["recording"]["cable_lengths"]
    assert list(report) == ["cable3"] and report["cable3"]["offset_m"] == pytest.approx(0.002, abs=1e-4)
    assert report["cable3"]["correlation"] > 0.99 and not [w for w in model.metrics["warnings"] if "cable3" in w]


def test_predict_and_diagnose_read_the_commands(fitted):
    """On the identified model (whose topology carries no MuJoCo actuators; the model lists them),
    the recording's states carry the commands that predict and diagnose step the actuators with."""
    _, rec, model = fitted
    data = recording_states(rec, model).data
    assert data.actuator_names == ("pull0", "pull1") and data.ctrl.shape[-1] == 2
    np.testing.assert_array_equal(data.ctrl, states_from_recording(rec, Topology.from_mjcf(fitted[0])).data.ctrl)


def test_the_marker_fit_starts_from_a_contact_regression_where_it_must(robot, tmp_path, monkeypatch, capsys):
    """``fit R.csv --refine`` without ``--start``: on this robot the regression without effects
    cannot identify the cables (the rods near the ground leave too few rows; two takes of 3 s), so
    the marker fit starts from the regression with ground_contact, and says so."""
    from identified.fit import marker_model
    from tensegrity_gym import cli

    path, _topo, _d = robot
    data = collect(path, CollectConfig(episodes=2, steps=3000, seed=2))
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02, encoder_rate=1000.0),
                         seed=2)
    csv = tmp_path / "r.csv"
    save_recording(csv, rec)
    seen = {}

    def refine(rec, mjcf, start, **kwargs):  # the marker fit itself is tested elsewhere: its start here
        seen["start"] = start
        return start

    monkeypatch.setattr(marker_model, "refine_recording", refine)
    monkeypatch.setattr(contact_damping, "FACTORS", (1.0,))  # the law's friction scan: not what this tests
    rc = cli.main(["fit", str(csv), "--model", path, "--total-mass", "21", "--refine", "--quiet",
                   "--out", str(tmp_path / "f.json")])
    assert rc == 0
    assert "starting from one with ground_contact" in capsys.readouterr().err
    assert [e["name"] for e in seen["start"].effects] == ["ground_contact"]
