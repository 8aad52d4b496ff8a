"""MuJoCo tendon actuators in the identification: activations stepped as MuJoCo steps them, gains
and biases linear, a filter's time constant by Gauss-Newton search; exact on clean data of a
plant whose rods the spring-rod equations describe exactly (the prism of ``examples/``).
"""

from __future__ import annotations

import json
import os
import re

import mujoco
import numpy as np
import pytest
import torch

from identified.engine.actuators import activations
from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit.identify import ScaleSpec
from identified.fit.pipeline import fit_model
from identified.model import IdentifiedModel, load_model, save_model
from tensegrity_gym.collect import CollectConfig, collect

PRISM = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "prism3.xml")


def _prism(actuators: str) -> str:
    with open(PRISM, encoding="utf-8") as fh:
        xml = fh.read()
    out, n = re.subn(r"<actuator>.*?</actuator>", f"<actuator>{actuators}</actuator>", xml, flags=re.DOTALL)
    assert n == 1
    return out


FILTERED = "".join(
    f'<general name="w{i}" tendon="vert{i}" dyntype="{dyn}" dynprm="{tau}" gainprm="{g}" ctrlrange="0 1"/>'
    for i, dyn, tau, g in ((1, "filter", 0.03, -7.0), (2, "filterexact", 0.05, -5.5), (3, "filter", 0.08, -6.5)))


def _truth(path: str) -> tuple[mujoco.MjModel, float]:
    m = mujoco.MjModel.from_xml_path(path)
    return m, float(sum(m.body_subtreemass[m.body_rootid == b].sum() for b in set(m.body_rootid) if b))


@pytest.mark.parametrize("dyn", ["filter", "filterexact", "integrator", "none"])
def test_activations_step_as_mujoco_steps_them(dyn, tmp_path):
    xml = _prism(f'<general name="w" tendon="vert1" dyntype="{dyn}" dynprm="0.037" gainprm="-3"/>')
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(1)
    ctrl = rng.uniform(0, 1, (1, 60, 1))
    seen = []
    for t in range(60):
        seen.append(d.act[0] if m.na else ctrl[0, t, 0])  # the activation the force of step t acts on
        d.ctrl[0] = ctrl[0, t, 0]
        mujoco.mj_step(m, d)
    act, dact = activations(ctrl, m.opt.timestep, [dyn], np.array([0.037]))
    np.testing.assert_allclose(act[0, :, 0], seen, rtol=1e-13, atol=1e-15)
    h = 1e-7  # d act / d tau against a central difference
    up, _ = activations(ctrl, m.opt.timestep, [dyn], np.array([0.037 + h]))
    dn, _ = activations(ctrl, m.opt.timestep, [dyn], np.array([0.037 - h]))
    np.testing.assert_allclose(dact, (up - dn) / (2 * h), rtol=1e-5, atol=1e-9)


def test_motor_gains_identified_exactly(tmp_path):
    m, total = _truth(PRISM)
    data = collect(PRISM, CollectConfig(episodes=2, steps=500, seed=3, push_every=50, push_magnitude=5.0))
    fit = fit_model(data, PRISM, effects="ground_contact", scale=ScaleSpec(total_mass=total), jobs=1)
    for a in fit.actuators:
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
        true = m.actuator_gainprm[i, 0] * m.actuator_gear[i, 0]
        assert a["gain"] == pytest.approx(true, rel=1e-9)
        assert 0 < a["gain_stderr"] < 1e-9  # a consistent fit: error bars at rounding level
        assert a["time_constant"] is None and a["bias"] == 0.0
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, s.name) for s in fit.topology.springs]
    np.testing.assert_allclose(fit.stiffness, m.tendon_stiffness[tid], rtol=1e-9)
    np.testing.assert_allclose(fit.rest_length, m.tendon_lengthspring[tid, 1], rtol=1e-9)
    # the fit's own verdict counts the actuators' forces: a description of its data
    assert fit.metrics["residual"]["relative_one_step"] < 1e-9
    save_model(tmp_path / "prism.json", fit)
    back = load_model(tmp_path / "prism.json")
    assert back.actuators == fit.actuators
    np.testing.assert_array_equal(back.stderr["rest_length"], fit.stderr["rest_length"])
    assert "actuator motor1 on vert1: gain -6" in back.summary()
    old = json.loads((tmp_path / "prism.json").read_text())  # a file written before actuators existed
    del old["actuators"]
    for sp in old["springs"]:
        del sp["rest_length_stderr"]
    assert IdentifiedModel.from_json(old).actuators == []


def test_filter_time_constants_found_by_search(tmp_path):
    path = tmp_path / "prism_filtered.xml"
    path.write_text(_prism(FILTERED), encoding="utf-8")
    m, total = _truth(str(path))
    data = collect(str(path), CollectConfig(episodes=2, steps=500, seed=3, push_every=50, push_magnitude=5.0))
    fit = fit_model(data, str(path), effects="ground_contact", scale=ScaleSpec(total_mass=total), jobs=1)
    assert [a["name"] for a in fit.actuators] == ["w1", "w2", "w3"]
    for a in fit.actuators:
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
        assert a["gain"] == pytest.approx(m.actuator_gainprm[i, 0], rel=1e-8)
        assert a["time_constant"] == pytest.approx(m.actuator_dynprm[i, 0], rel=1e-8)
        assert 0 < a["time_constant_stderr"] < 1e-9
    # the diagnosis's residual counts the actuators' forces too, their filters carried across the
    # windows it cuts the episodes into (100 steps): off the ground what is left is rounding
    from identified.diagnose import diagnose

    rows = diagnose(fit, data, horizon_s=0.2, mjcf=str(path), chunk_steps=100)["one_step"]["effect_rows"]
    assert [e["effect"] for e in rows] == ["ground_contact"]
    assert rows[0]["outside"]["force"] < 1e-9 and rows[0]["outside"]["torque"] < 1e-9


#: filtered general actuators with a constant bias: on cables that go slack in 1-1.5 % of the rows
#: (top12, top23) and on one taut throughout (vert3); (time constant, gain, bias)
BIASES = {"top12": (0.03, -7.0, 0.6), "top23": (0.05, -5.5, 0.8), "vert3": (0.04, -6.0, 0.5)}


def _biased(top12_bias: float) -> str:
    b = dict(BIASES, top12=BIASES["top12"][:2] + (top12_bias,))
    return "".join(f'<general name="w_{t}" tendon="{t}" dyntype="filter" dynprm="{tau}" gainprm="{g}" '
                   f'biastype="affine" biasprm="{x} 0 0" ctrlrange="0 1"/>' for t, (tau, g, x) in b.items())


def _lengths(data, topology) -> np.ndarray:
    """(N, S) every spring's length at the recorded instants."""
    flat = lambda x: torch.as_tensor(x[:, :-1].reshape(-1, *x.shape[2:]))
    ends = endpoint_kinematics(topology, flat(data.pos), flat(data.quat), flat(data.vel), flat(data.angvel))
    return spring_geometry(ends)[0].numpy()


@pytest.mark.parametrize("top12_bias", [0.6, pytest.param(-1.5, marks=pytest.mark.expensive)],
                         ids=["loosening", "tightening"])
def test_biases_identified_where_their_cables_go_slack(tmp_path, top12_bias):
    """A constant bias is the same column as its cable's preload only while the cable is taut: the
    first solve (no rest length estimated, every cable taut) cannot separate them, the later ones
    can where the cable goes slack (top12, top23, 1-1.5 % of the rows: the bias is recovered
    exactly; where top12's bias tightens its cable (-1.5 N) the absorbed estimate ``l0 + b / K`` lies below the
    rest length and the fit must probe it from above); on a cable taut throughout (vert3) the bias
    is held at 0, noted, and the rest length holds it (``l0 + b / K``)."""
    path = tmp_path / "prism_biased.xml"
    path.write_text(_prism(_biased(top12_bias)), encoding="utf-8")
    m, total = _truth(str(path))
    data = collect(str(path), CollectConfig(episodes=2, steps=500, seed=3, push_every=50, push_magnitude=5.0))
    fit = fit_model(data, str(path), effects="ground_contact", scale=ScaleSpec(total_mass=total), jobs=1)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, s.name) for s in fit.topology.springs]
    K, l0 = m.tendon_stiffness[tid], m.tendon_lengthspring[tid, 1].copy()
    slack = np.mean(_lengths(data, fit.topology) < l0, axis=0)
    for a in fit.actuators:
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
        j = fit.topology.spring_names.index(a["tendon"])
        b = m.actuator_biasprm[i, 0]
        assert a["gain"] == pytest.approx(m.actuator_gainprm[i, 0], rel=1e-8)
        assert a["time_constant"] == pytest.approx(m.actuator_dynprm[i, 0], rel=1e-8)
        if a["tendon"] == "vert3":
            assert slack[j] == 0.0 and a["bias"] == 0.0 and "never went slack" in a["note"]
            l0[j] += b / K[j]
        else:
            assert 0.0 < slack[j] < 0.1 and "note" not in a
            assert a["bias"] == pytest.approx(b, rel=1e-8)
    np.testing.assert_allclose(fit.stiffness, K, rtol=1e-9)
    np.testing.assert_allclose(fit.rest_length, l0, rtol=1e-9)
    assert fit.metrics["residual"]["relative_one_step"] < 1e-9


@pytest.mark.expensive
def test_nested_six_bar_with_biased_filters_exactly():
    """The nested 6-bar of ``examples/`` (six filtered general actuators, each with a -1.5 N bias that
    tightens its cable), 3 x 1000 steps: every spring, rod and actuator to rounding. Two winch
    cables (t5, t13) are taut in every fitted row: their biases are held at 0 and noted (their rest
    lengths hold ``l0 + b / K``), never a value separated by the shortest row alone (t13: a probe
    from above settled there with a bias of -9.4 N)."""
    from identified import Topology

    path = os.path.join(os.path.dirname(PRISM), "six_bar_nested.xml")
    m = mujoco.MjModel.from_xml_path(path)  # (its floor's body has a mass of its own: the rods' bodies only)
    total = sum(m.body_mass[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b)]
                for r in Topology.from_mjcf(path).rods for b in (r.bodies or (r.name,)))
    data = collect(path, CollectConfig(episodes=3, steps=1000, seed=1, push_every=50, push_magnitude=5.0))
    fit = fit_model(data, path, effects="ground_contact", scale=ScaleSpec(total_mass=total), jobs=1)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, s.name) for s in fit.topology.springs]
    K, l0 = m.tendon_stiffness[tid], m.tendon_lengthspring[tid, 1].copy()
    for a in fit.actuators:
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
        j = fit.topology.spring_names.index(a["tendon"])
        assert a["gain"] == pytest.approx(m.actuator_gainprm[i, 0], rel=1e-9)
        assert a["time_constant"] == pytest.approx(m.actuator_dynprm[i, 0], rel=1e-9)
        if a["tendon"] in ("t5", "t13"):
            assert a["bias"] == 0.0 and "never went slack" in a["note"]
            l0[j] += m.actuator_biasprm[i, 0] / K[j]
        else:
            assert "note" not in a and a["bias"] == pytest.approx(m.actuator_biasprm[i, 0], rel=1e-9)
    np.testing.assert_allclose(fit.stiffness, K, rtol=1e-9)
    np.testing.assert_allclose(fit.damping, m.tendon_damping[tid], rtol=1e-9)
    np.testing.assert_allclose(fit.rest_length, l0, rtol=1e-9)
    assert fit.metrics["residual"]["relative_one_step"] < 1e-9
