"""Any lab's tensegrity MJCF: the system read from the compiled model, refusals of what is not one,
and the env on the three lab-style example models."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from identified.mjcf import MjcfError, read_system
from identified.rotation import quat_to_matrix
from identified.topology import Topology, TopologyError
from tensegrity_gym.models import build_model
from tensegrity_gym.plant import MujocoPlant

EXAMPLES = os.path.join(os.path.dirname(__file__), os.pardir, "examples")


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as fh:
        return fh.read()


LAB = {name: os.path.join(EXAMPLES, f"{name}.xml") for name in ("prism3", "six_bar_composite", "six_bar_nested")}


# ---------------------------------------------------------------------- geometry as MuJoCo compiles it
@pytest.mark.parametrize("name", sorted(LAB))
def test_sites_in_the_rod_frame_are_where_mujoco_puts_them(name: str) -> None:
    """In random poses, every site's world position from the topology (rod pose + site in the rod
    frame) equals MuJoCo's own ``site_xpos``: nested bodies, classes, euler/xyaxes/axisangle/zaxis
    frames all resolved."""
    topo = Topology.from_mjcf(LAB[name])
    m = mujoco.MjModel.from_xml_path(LAB[name])
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for _ in range(3):
        for r in topo.rods:
            j = m.body_jntadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, r.name)]
            q = rng.normal(size=4)
            d.qpos[m.jnt_qposadr[j]:m.jnt_qposadr[j] + 7] = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)])
        mujoco.mj_kinematics(m, d)
        for r in topo.rods:
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, r.name)
            j = m.jnt_qposadr[m.body_jntadr[b]]
            pos, rot = d.qpos[j:j + 3], quat_to_matrix(d.qpos[j + 3:j + 7])
            for s in r.sites:
                sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)
                np.testing.assert_allclose(pos + rot @ r.site_offset(s), d.site_xpos[sid], atol=1e-12)


def test_the_nested_model_is_not_read_literally() -> None:
    """The nested model's sites sit at pos="0 0 0" of their end bodies: their rod-frame positions
    are the rod's ends along the free body's x axis (xyaxes), +-0.45 m apart, which the XML
    attributes alone do not say."""
    topo = Topology.from_mjcf(LAB["six_bar_nested"])
    rod = topo.rods[0]
    assert rod.bodies == ("rod_A", "box_A", "tube_A", "end_A0", "end_A1")
    np.testing.assert_allclose(rod.site_offsets, [[-0.45, 0, 0], [0.45, 0, 0]], atol=1e-12)
    assert rod.length == pytest.approx(0.9)


def test_composite_rods_are_one_rigid_body() -> None:
    sysd = read_system(LAB["six_bar_composite"])
    assert [r.name for r in sysd.rods] == [f"strut{k}" for k in range(6)]
    assert sysd.rods[2].bodies == ("strut2", "strut2_capA", "strut2_capB", "strut2_electronics")
    np.testing.assert_allclose(sysd.rods[0].site_pos, [[0.03, 0, -0.5], [0, 0.03, 0.5]], atol=1e-12)
    plant = MujocoPlant(LAB["six_bar_composite"])
    m = plant.model
    b = plant._bid[0]
    np.testing.assert_allclose(plant.masses[0], m.body_mass[b:b + 4].sum())  # the rod's bodies together


def test_physical_values_are_not_read() -> None:
    """Geometry and topology are the same whatever the masses, stiffnesses, damping, rest lengths
    and gains written in the file."""
    text = _read(LAB["six_bar_nested"])
    wrong = re.sub(r'stiffness="[0-9.]+"', 'stiffness="1"', text)
    wrong = re.sub(r'springlength="0 [0-9.]+"', 'springlength="0 0.3"', wrong)
    wrong = re.sub(r'gainprm="-?[0-9.]+"', 'gainprm="-3"', wrong).replace('density="2700"', 'density="10"')
    a, b = Topology.from_mjcf(text), Topology.from_mjcf(wrong)
    np.testing.assert_array_equal(a.endpoint_offsets, b.endpoint_offsets)
    assert a.actuators == b.actuators and a.spring_names == b.spring_names
    np.testing.assert_array_equal(a.pull_only, b.pull_only)


def test_actuators_and_motors_are_read() -> None:
    prism = Topology.from_mjcf(LAB["prism3"])
    assert [(a.name, a.kind, a.tendon, a.dynamics, a.ctrlrange) for a in prism.actuators] == [
        (f"motor{i}", "motor", f"vert{i}", "none", (0.0, 1.0)) for i in (1, 2, 3)]
    nested = Topology.from_mjcf(LAB["six_bar_nested"])
    assert {(a.kind, a.dynamics) for a in nested.actuators} == {("general", "filter")}
    composite = Topology.from_mjcf(LAB["six_bar_composite"])
    assert {a.kind for a in composite.actuators} == {"rest_length"}
    assert composite.actuated_names == tuple(a.tendon for a in composite.actuators)
    position = _read(LAB["prism3"]).replace(
        '<motor name="motor1" tendon="vert1" gear="-6" ctrlrange="0 1"/>',
        '<position name="servo" tendon="vert1" kp="50" ctrlrange="0.2 0.4"/>')
    assert Topology.from_mjcf(position).actuators[0] == Topology.from_mjcf(position).actuators[0].__class__(
        "servo", "general", "vert1", "none", (0.2, 0.4))


def test_a_cable_anchored_to_the_world_is_valid() -> None:
    topo = Topology.from_mjcf(build_model("simple", "paper"))
    assert topo.n_rods == 1 and set(topo.endpoint_rods[:, 1]) | set(topo.endpoint_rods[:, 0]) >= {-1, 0}


# ---------------------------------------------------------------------- refusals: one line naming the element
PRISM = _read(LAB["prism3"])


def _cable(name: str, a: str, b: str) -> str:
    return f'<spatial name="{name}" stiffness="100" springlength="0 0.3"><site site="{a}"/><site site="{b}"/></spatial>'


MALFORMED = {
    "one site": (PRISM.replace('<site name="bar3_top"', '<site name="bar3_marker"')
                 .replace('site="bar3_top"', 'site="bar3_bot"'), re.escape("rod 'bar3' has one attachment site ('bar3_bot')")),
    "same rod": (PRISM.replace("</tendon>", _cable("loop", "bar1_bot", "bar1_top") + "</tendon>"),
                 "tendon 'loop' joins two sites of rod 'bar1'"),
    "site on no rod": (PRISM.replace('<geom name="floor"', '<body name="arm" pos="1 0 0.5"><joint name="hinge" '
                                     'type="hinge"/><geom size="0.05" mass="1"/><site name="tip"/></body>'
                                     '<geom name="floor"').replace("</tendon>", _cable("tether", "tip", "bar1_top")
                                                                   + "</tendon>"),
                       "tendon 'tether' uses site 'tip' on body 'arm', which is neither on a rod"),
    "falls apart": (PRISM.replace('<light', '<body name="loose" pos="2 0 1"><freejoint/><geom size="0.05" '
                                  'mass="1"/><site name="l0"/></body><light'),
                    "rod 'loose' is not attached by any cable: the model falls apart"),
    "two pieces": (PRISM.replace('<light', '<body name="x1" pos="2 0 1"><freejoint/><geom size="0.05" mass="1"/>'
                                 '<site name="x1a"/><site name="x1b" pos="0 0 0.1"/></body><body name="x2" pos="2 1 1">'
                                 '<freejoint/><geom size="0.05" mass="1"/><site name="x2a"/><site name="x2b" '
                                 'pos="0 0 0.1"/></body><light')
                   .replace("</tendon>", _cable("p", "x1a", "x2a") + _cable("q", "x1b", "x2b") + "</tendon>"),
                   r"rods \['x1', 'x2'\] are not connected to rod 'bar1'"),
    "joint actuator": (PRISM.replace('<site name="bar1_bot"', '<body name="wheel"><joint name="spin" type="hinge"/>'
                                     '<geom size="0.02" mass="0.1"/></body><site name="bar1_bot"')
                       .replace("</actuator>", '<motor name="drive" joint="spin"/></actuator>'),
                       "body 'wheel' moves on a hinge joint"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_models_are_refused_naming_the_element(case: str) -> None:
    xml, message = MALFORMED[case]
    with pytest.raises(MjcfError, match=message):
        read_system(xml)
    with pytest.raises(TopologyError, match=message):
        Topology.from_mjcf(xml)
    with pytest.raises(ValueError, match=message):
        MujocoPlant(xml)


#: what the plant can simulate (and ``collect`` records) but the identified engine does not model
UNMODELLED = {
    "three sites": (lambda x: x.replace('<site site="bar1_top"/><site site="bar2_top"/>',
                                        '<site site="bar1_top"/><site site="bar3_bot"/><site site="bar2_top"/>'),
                    "tendon 'top12' is routed over 3 sites"),
    "length limit": (lambda x: x.replace('<spatial name="top12"', '<spatial name="top12" limited="true" range="0 1"'),
                     "tendon 'top12' has a length limit"),
    "dead band": (lambda x: re.sub(r'(<spatial name="top12" [^>]*springlength=")0 ', r'\g<1>0.1 ', x),
                  "tendon 'top12': a dead-band with a non-zero lower bound"),
    "site actuator": (lambda x: x.replace('<motor name="motor1" tendon="vert1"', '<motor name="motor1" site="bar1_top"'),
                      "actuator 'motor1' drives a site, not a tendon"),
}


@pytest.mark.parametrize("edit, message", list(UNMODELLED.values()), ids=list(UNMODELLED))
def test_what_the_engine_does_not_model_is_refused(edit, message) -> None:
    with pytest.raises(TopologyError, match=message):
        Topology.from_mjcf(edit(PRISM))


NO_CONTROLS = PRISM.split("<actuator>")[0] + "</mujoco>"


@pytest.mark.parametrize("case", sorted(MALFORMED) + ["no controls"] + sorted(UNMODELLED))
def test_cli_refuses_each_malformed_model_in_one_line(case: str, tmp_path, capsys) -> None:
    """Every malformed model through the command line (in process): exit status 2, one line on
    stderr naming the element, nothing written. A model with no actuator and no motor is a valid
    structure (it can be recorded) but gives nothing to control: ``train`` refuses it; what the
    plant simulates but the identified engine does not model is recorded and refused by ``fit``."""
    from tensegrity_gym.cli import main

    bad = tmp_path / "bad.xml"
    out = tmp_path / "out"
    if case == "no controls":
        bad.write_text(NO_CONTROLS)
        argv = ["train", "--plant", "--xml-file", str(bad), "--timesteps", "64", "--out", str(out)]
        message = "the model has no actuated cables and no actuators: nothing to control"
    elif case in MALFORMED:
        xml, message = MALFORMED[case]
        bad.write_text(xml)
        argv = ["collect", "--model", str(bad), "--episodes", "1", "--steps", "10", "--out", str(out)]
    elif case in UNMODELLED:  # recorded from the plant, refused by the fit
        edit, message = UNMODELLED[case]
        bad.write_text(edit(PRISM))
        data = tmp_path / "d.npz"
        collect = ["collect", "--model", str(bad), "--episodes", "1", "--steps", "10", "--out"]
        if case == "site actuator":  # the plant refuses that one already
            argv = collect + [str(out)]
        else:
            assert main(collect + [str(data), "--quiet"]) == 0
            argv = ["fit", str(data), "--model", str(bad), "--out", str(out), "--quiet"]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tensegrity: error: ") and re.search(message, err[0]), err
    assert not list(tmp_path.glob("out*"))


def test_cli_refuses_in_one_line(tmp_path) -> None:
    bad = tmp_path / "bad.xml"
    bad.write_text(MALFORMED["same rod"][0])
    out = tmp_path / "d.npz"
    r = subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", "collect", "--model", str(bad), "--episodes", "1",
                        "--steps", "10", "--out", str(out)], check=False, capture_output=True, text=True)
    assert r.returncode == 2 and not out.exists()
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "tendon 'loop' joins two sites of rod 'bar1'" in lines[0] and str(bad) in lines[0]


# ---------------------------------------------------------------------- the env on any model
@pytest.mark.parametrize("name", sorted(LAB))
def test_env_passes_the_checkers(name: str) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make("Tensegrity-v0", xml_file=LAB[name])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the unbounded observation Box
        check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=False)
    env.close()


def test_env_actions_are_the_models_controls() -> None:
    """Prism: three motors, action +-1 -> the ends of ctrlrange; the nested 6-bar's observation ends
    with the filter activations, which follow a held command at MuJoCo's first-order rate."""
    env = gym.make("Tensegrity-v0", xml_file=LAB["prism3"]).unwrapped
    assert env.action_space.shape == (3,)
    env.reset(seed=0)
    env.step(np.array([1.0, -1.0, 0.0], dtype=np.float32))
    np.testing.assert_allclose(env.backend.plant.ctrl, [1.0, 0.0, 0.5])
    nested = gym.make("Tensegrity-v0", xml_file=LAB["six_bar_nested"]).unwrapped
    obs, _ = nested.reset(seed=0)
    assert obs.shape == (1 + 18 * 6 + 6,)
    np.testing.assert_allclose(obs[-6:], -1.0)  # activation 0 = low end of ctrlrange
    obs, *_ = nested.step(np.ones(6, dtype=np.float32))
    m = nested.backend.plant.model
    tau = m.actuator_dynprm[:, 0]
    act = 1.0 - (1.0 - m.opt.timestep / tau) ** nested.frame_skip  # Euler's filter, ctrl held at 1
    np.testing.assert_allclose(obs[-6:], 2.0 * act - 1.0, rtol=1e-5)


def test_env_health_derives_from_the_model() -> None:
    env = gym.make("Tensegrity-v0", xml_file=LAB["six_bar_composite"]).unwrapped
    h = float(env.backend.nominal_states().pos.mean(axis=0)[2])
    assert env.healthy_z_range == pytest.approx((0.25 * h, 3.0 * h))
    assert env.backend.nominal_source == "settled for 5 s from qpos0"
    ico = gym.make("TensegrityIco-v0", xml_file=LAB["six_bar_nested"]).unwrapped
    assert ico.healthy_z_range == (0.4, 2.0) and ico.backend.plant.rod_names[0] == "rod_A"


def test_env_without_controls_says_so() -> None:
    no_act = PRISM.split("<actuator>")[0] + "</mujoco>"
    with pytest.raises(ValueError, match="no actuated cables and no actuators: nothing to control"):
        gym.make("Tensegrity-v0", xml_file=no_act)
    with pytest.raises(ValueError, match="needs the robot's MJCF"):
        gym.make("Tensegrity-v0")
    with pytest.raises(ValueError, match="actuator 'motor1' has no ctrlrange"):
        gym.make("Tensegrity-v0", xml_file=PRISM.replace('gear="-6" ctrlrange="0 1"/>', 'gear="-6"/>', 1))


# ---------------------------------------------------------------------- a fit that does not describe its data says so
def test_fit_strict_flags_a_model_that_cannot_describe_its_data(tmp_path) -> None:
    """The same plant twice: rods with their centre of mass at the frame origin are fitted to rounding
    (residual ~1e-13, passes --strict); with every centre of mass 5 cm off the origin (geometry the
    spring-rod equations do not hold) the fit says so in metrics, summary and warnings, and
    ``--strict`` exits with status 2."""
    from identified.model import load_model
    from tensegrity_gym.cli import main

    good = build_model("ico", "paper-uniform")
    bad = good.replace('<inertial pos="0 0 0"', '<inertial pos="0.05 0 0"')
    results = {}
    for name, xml in (("good", good), ("bad", bad)):
        path = tmp_path / f"{name}.xml"
        path.write_text(xml)
        data, out = tmp_path / f"{name}.npz", tmp_path / f"{name}.json"
        assert main(["collect", "--model", str(path), "--episodes", "2", "--steps", "300", "--seed", "1",
                     "--push-every", "50", "--out", str(data)]) == 0
        results[name] = main(["fit", str(data), "--model", str(path), "--out", str(out), "--strict", "--quiet"])
        model = load_model(out)
        results[name + "_res"] = model.metrics["residual"]
        results[name + "_summary"] = model.summary()
    assert results["good"] == 0 and results["good_res"]["relative_one_step"] < 1e-10
    assert not results["good_res"]["large"] and "NOT A DESCRIPTION" not in results["good_summary"]
    assert results["bad"] == 2 and results["bad_res"]["large"] and results["bad_res"]["relative_one_step"] > 1e-2
    assert "NOT A DESCRIPTION OF ITS DATA" in results["bad_summary"]


def test_tensegrity_v0_on_the_twin(tmp_path) -> None:
    """Tensegrity-v0 with backend="identified": the shipped robot model on its MJCF passes the
    checkers, starts from the plant's reset state for the same seed, and derives its health range
    from the MJCF; an MJCF with a MuJoCo actuator the model lacks is refused in one line."""
    from gymnasium.utils.env_checker import check_env

    from tensegrity_gym.backends.identified_backend import default_model_path

    xml = tmp_path / "robot.xml"
    xml.write_text(build_model("ico", "robot"))
    twin = gym.make("Tensegrity-v0", xml_file=str(xml), backend="identified", model=default_model_path(),
                    backend_kwargs={"dtype": "float64", "compile": False})
    plant = gym.make("Tensegrity-v0", xml_file=str(xml))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(twin.unwrapped, skip_render_check=True)
    o_twin, _ = twin.reset(seed=3)
    o_plant, _ = plant.reset(seed=3)
    np.testing.assert_allclose(o_twin, o_plant, rtol=0, atol=1e-6)
    assert twin.unwrapped.healthy_z_range == pytest.approx(plant.unwrapped.healthy_z_range)
    from identified.fit.pipeline import fit_model
    from identified.model import save_model
    from tensegrity_gym.collect import CollectConfig, collect

    # the prism stands on its bottom cables: 10 N pushes in two runs move them enough to separate
    # each cable's stiffness from its rest length (1 x 300 steps of 3 N pushes do not)
    data = collect(LAB["prism3"], CollectConfig(episodes=2, steps=300, seed=0, push_every=20, push_magnitude=10.0))
    prism = tmp_path / "prism.json"
    save_model(prism, fit_model(data, LAB["prism3"]))
    extra = _read(LAB["prism3"]).replace("</actuator>", '<motor name="extra" tendon="top12" gear="-1" '
                                         'ctrlrange="0 1"/></actuator>')
    with pytest.raises(ValueError, match=r"has MuJoCo actuators \['extra'\], which the identified model does not"):
        gym.make("Tensegrity-v0", xml_file=extra, backend="identified", model=str(prism))


def test_env_with_motors_and_actuators_together() -> None:
    """Rest-length motors first, then MuJoCo actuators: one action vector, each part on its own range."""
    xml = _read(LAB["six_bar_composite"]).replace(
        "</tendon>", '</tendon><actuator><motor name="pull" tendon="c1" gear="-1" ctrlrange="0 20"/></actuator>')
    env = gym.make("Tensegrity-v0", xml_file=xml).unwrapped
    assert env.action_space.shape == (7,) and env.observation_space.shape == (1 + 18 * 6 + 7,)
    env.reset(seed=1)
    a = np.zeros(7, dtype=np.float32)
    a[:6], a[6] = -1.0, 0.5
    env.step(a)
    plant = env.backend.plant
    np.testing.assert_allclose(plant.targets, plant.motor.rest_min)
    np.testing.assert_allclose(plant.ctrl, [15.0])
