"""A recording's measured cable lengths (``<tendon>.length``) checked against the markers'."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit.cable_lengths import cable_length_check
from identified.fit.markers import states_from_recording
from identified.recording import read_recording, save_recording
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("lengths") / "robot.xml")
    write_model(path, "ico", preset="robot")
    topo = Topology.from_mjcf(path)
    data = collect(path, CollectConfig(episodes=2, steps=1500, seed=4))
    rec = record_markers(data, path, RecordConfig(rate=100), seed=1)
    true = _lengths_at(topo, data, rec.episode, np.round(rec.time / data.dt).astype(int))
    return topo, rec, true, data, path


def _lengths_at(topo: Topology, data, episode: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Every cable's length (m) at the plant's states, from the engine's geometry (not MuJoCo's)."""
    t = lambda x: torch.as_tensor(x[episode, steps], dtype=torch.float64)
    return spring_geometry(endpoint_kinematics(topo, t(data.pos), t(data.quat), t(data.vel), t(data.angvel))).length.numpy()


def test_measured_lengths_against_the_markers(robot):
    """Sensor zero, noise and a swapped column: the offset and the noise come back as they were put
    in, and only the swapped column is named (clean markers through interpolating splines: the
    markers' own lengths are the plant's)."""
    topo, rec, true = robot[:3]
    s = list(topo.spring_names)
    noise = np.random.default_rng(0).normal(0.0, 0.005, true.shape[0])
    lengths = np.stack([true[:, s.index("cable0")] + 0.003,  # the sensor's zero 3 mm off
                        true[:, s.index("cable1")],
                        true[:, s.index("cable9")],  # the column of another cable
                        true[:, s.index("cable3")]], axis=1)
    names = ("cable0", "cable1", "cable2", "cable3")
    clean = dataclasses.replace(rec, length_names=names, length=lengths)
    ms = states_from_recording(clean, topo, lam=1e-12)
    report, warnings = cable_length_check(clean, ms.data, ms.starts, topo)
    assert report["cable0"]["offset_m"] == pytest.approx(0.003, abs=1e-5)
    assert abs(report["cable1"]["offset_m"]) < 1e-5 and report["cable1"]["rms_m"] < 2e-5 and report["cable0"]["rms_m"] < 2e-5
    assert report["cable1"]["correlation"] > 0.99999 and report["cable2"]["correlation"] < 0.9
    assert len(warnings) == 1 and warnings[0].startswith("cable 'cable2': its measured length ('cable2.length')")
    assert report["cable0"]["frames"] == report["cable3"]["frames"] > 250
    # the sensor's noise
    noisy = dataclasses.replace(clean, length=lengths + np.c_[0 * noise, 0 * noise, 0 * noise, noise])
    again, _ = cable_length_check(noisy, ms.data, ms.starts, topo)
    assert again["cable3"]["rms_m"] == pytest.approx(noise.std(), rel=0.05)
    assert abs(again["cable3"]["offset_m"]) < 1e-3


def test_collect_records_the_cables_lengths(robot):
    """``RecordConfig.lengths``: the plant's tendon lengths (MuJoCo's ``ten_length``) at the frames
    are the cables' lengths the engine's geometry gives at the same states; the sensors' noise has
    its stated size and leaves the markers' noise and gaps as they were without sensors."""
    topo, plain, true, data, path = robot
    rec = record_markers(data, path, RecordConfig(rate=100, lengths=("all",)), seed=1)
    assert rec.length_names == topo.spring_names
    np.testing.assert_allclose(rec.length, true, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rec.markers, plain.markers)
    noisy = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.01, dropout=0.05, lengths=("all",),
                                                    noise_length=0.002), seed=1)
    without = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.01, dropout=0.05), seed=1)
    np.testing.assert_array_equal(noisy.markers, without.markers)  # drawn after the markers' noise and gaps
    d = (noisy.length - true).ravel()
    assert d.std() == pytest.approx(0.002, rel=0.05) and abs(d.mean()) < 4 * 0.002 / np.sqrt(d.size)


def test_length_sensors_at_the_encoders_rate_round_trip(robot, tmp_path):
    """With encoders faster than the cameras the sensors are read at the encoders' instants (named
    cables in the model's order); the written file reads back to the same samples, and the frames'
    lengths are those samples interpolated, as for the rest lengths."""
    topo, _, _, data, path = robot
    rec = record_markers(data, path, RecordConfig(rate=50, encoder_rate=500, lengths=("cable7", "cable2")), seed=1)
    assert rec.length_names == ("cable2", "cable7")
    enc = rec.encoders
    steps = np.round(enc.time / data.dt).astype(int)
    assert enc.time.size == 2 * 750 and steps[1] == 2
    cols = [list(topo.spring_names).index(n) for n in rec.length_names]
    np.testing.assert_allclose(enc.length, _lengths_at(topo, data, enc.episode, steps)[:, cols], rtol=0, atol=1e-12)
    out = tmp_path / "r.csv"
    save_recording(out, rec)
    back = read_recording(str(out))
    assert back.length_names == rec.length_names
    np.testing.assert_allclose(back.encoders.length, enc.length, rtol=0, atol=5e-8)
    np.testing.assert_allclose(back.length, rec.length, rtol=0, atol=5e-8)
    frames = np.round(rec.time / data.dt).astype(int)
    exact = _lengths_at(topo, data, rec.episode, frames)[:, cols]
    assert np.abs(rec.length - exact).max() < 1e-6  # the frames fall on encoder samples at 500 Hz


def test_cli_collect_lengths(robot, tmp_path):
    path = robot[4]
    run = lambda *a: subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", *a], check=False, capture_output=True,
                                    text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    out = tmp_path / "r.csv"
    r = run("collect", "--model", path, "--episodes", "1", "--steps", "300", "--record", "markers", "--lengths",
            "cable3,cable0", "--noise-length", "0.001", "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    assert "2 cable lengths" in r.stdout
    assert read_recording(str(out)).length_names == ("cable0", "cable3")
    for bad, words in ((("--record", "markers", "--lengths", "cable0,cable99"), "--lengths: 'cable99' is not a tendon"),
                       (("--record", "markers", "--lengths", "cable0,,cable1"), "argument --lengths: an empty name"),
                       (("--record", "markers", "--lengths", "cable0,cable0"), "'cable0' is named twice"),
                       (("--record", "markers", "--noise-length", "0.01"), "name the sensed cables with --lengths"),
                       (("--lengths", "all", "--out", str(tmp_path / "d.npz")), "--lengths is for a recording")):
        args = bad if "--out" in bad else (*bad, "--out", str(tmp_path / "x.csv"))
        r = run("collect", "--model", path, "--episodes", "1", "--steps", "100", *args, "--quiet")
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and words in r.stderr, r.stderr
    assert not (tmp_path / "x.csv").exists()
