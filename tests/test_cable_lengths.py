"""A recording's measured cable lengths (``<tendon>.length``) checked against the markers'."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit.cable_lengths import cable_length_check
from identified.fit.markers import states_from_recording
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
    steps = np.round(rec.time / data.dt).astype(int)
    t = lambda x: torch.as_tensor(x[rec.episode, steps], dtype=torch.float64)
    true = spring_geometry(endpoint_kinematics(topo, t(data.pos), t(data.quat), t(data.vel), t(data.angvel))).length
    return topo, rec, true.numpy()


def test_measured_lengths_against_the_markers(robot):
    """Sensor zero, noise and a swapped column: the offset and the noise come back as they were put
    in, and only the swapped column is named (clean markers through interpolating splines: the
    markers' own lengths are the plant's)."""
    topo, rec, true = robot
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
