"""Passive springs' rest lengths are identified (``l0 = P / K`` from the columns ``K`` and
``P = K l0``), never read from the data; actuated cables' rest lengths stay inputs.

The plants are MuJoCo models on the Euler integrator: the regression's equations are the exact
discretisation, so clean data give every rest length to rounding, also for pull-only cables that
go slack (the fit classifies their taut rows by its own estimate until it settles).
"""

from __future__ import annotations

import re
from dataclasses import replace

import mujoco
import numpy as np
import torch

from identified import Topology
from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit.identify import identify
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters


def _true_rest(xml: str, topo: Topology) -> np.ndarray:
    m = mujoco.MjModel.from_xml_string(xml)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    lo, hi = m.tendon_lengthspring[tid, 0], m.tendon_lengthspring[tid, 1]
    return np.where(lo == hi, lo, hi)  # a spring "L": (L, L); a cable "0 L": (0, L)


def _cables(xml: str, names: tuple[str, ...], longer: float) -> str:
    """The springs ``names`` made pull-only cables whose rest length is ``longer`` times their own."""
    def swap(match: re.Match) -> str:
        return f'{match.group(1)}springlength="0 {float(match.group(2)) * longer:.6f}"'

    for n in names:
        xml, k = re.subn(rf'(<spatial name="{n}"[^>]*?)springlength="([0-9.eE+-]+)"', swap, xml)
        assert k == 1, n
    return xml


def test_push_pull_springs_rest_lengths_recovered_to_rounding_with_error_bars():
    xml = build_model("ico", "paper-nonuniform", seed=7)
    topo = Topology.from_mjcf(xml)
    data = collect(xml, CollectConfig(episodes=3, steps=300, seed=4, push_every=50))
    model = identify(data, topo)
    true = np.array([s["rest_length"] for s in preset_parameters("ico", "paper-nonuniform", 7)["springs"]])
    np.testing.assert_allclose(model.rest_length, true, rtol=1e-10)
    se = model.stderr["rest_length"]
    assert np.all(se > 0) and np.all(se < 1e-9)
    assert np.all(np.abs(model.rest_length - true) <= 5 * se + 1e-14)
    K = np.array([s["stiffness"] for s in preset_parameters("ico", "paper-nonuniform", 7)["springs"]])
    np.testing.assert_allclose(model.stiffness, K, rtol=1e-10)


def test_recorded_rest_lengths_of_passive_springs_are_never_read():
    xml = build_model("ico", "paper-uniform")
    topo = Topology.from_mjcf(xml)
    data = collect(xml, CollectConfig(episodes=2, steps=300, seed=2))
    wrong = replace(data, rest_length=data.rest_length * np.random.default_rng(0).uniform(
        0.5, 2.0, data.rest_length.shape))
    a, b = identify(data, topo), identify(wrong, topo)
    np.testing.assert_array_equal(a.rest_length, b.rest_length)
    np.testing.assert_array_equal(a.stiffness, b.stiffness)
    np.testing.assert_allclose(a.rest_length, 0.637, rtol=1e-10)


def test_slack_pull_only_cables_rest_lengths_recovered_exactly():
    names = ("spring0", "spring3", "spring7", "spring12", "spring20")
    xml = _cables(build_model("ico", "paper-nonuniform", seed=3), names, 1.02)
    topo = Topology.from_mjcf(xml)
    assert all(topo.springs[topo.spring_names.index(n)].pull_only for n in names)
    data = collect(xml, CollectConfig(episodes=3, steps=400, seed=5, push_every=40))
    true = _true_rest(xml, topo)
    # the cables do go slack in these data (else the classification would not be exercised)
    flat = [torch.as_tensor(x.reshape(-1, *x.shape[2:])) for x in (data.pos, data.quat, data.vel, data.angvel)]
    length = spring_geometry(endpoint_kinematics(topo, *flat)).length.numpy()
    idx = [topo.spring_names.index(n) for n in names]
    slack = (length[:, idx] < true[idx]).mean(0)
    assert np.all(slack > 0.02) and np.all(slack < 0.98), slack
    model = identify(data, topo)
    np.testing.assert_allclose(model.rest_length, true, rtol=1e-10)
    K = np.array([s["stiffness"] for s in preset_parameters("ico", "paper-nonuniform", 3)["springs"]])
    np.testing.assert_allclose(model.stiffness, K, rtol=1e-9)


def test_actuated_cables_keep_their_commands_as_rest_lengths():
    xml = build_model("ico", "robot")
    topo = Topology.from_mjcf(xml)
    assert all(s.actuated for s in topo.springs)
    data = collect(xml, CollectConfig(episodes=1, steps=200, seed=0))
    model = identify(data, topo)
    np.testing.assert_array_equal(model.rest_length, data.rest_length.mean(axis=(0, 1)))
    assert "rest_length" not in model.stderr or np.all(model.stderr["rest_length"] == 0)
