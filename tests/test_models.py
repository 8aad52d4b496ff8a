"""MJCF builder and presets: geometry, ground truth, seeding, overrides, conventions, motor spec."""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

from tensegrity_gym.cables import MotorSpec, motor_step, read_motor_spec
from tensegrity_gym.models import (
    build_model,
    closed_faces,
    ico_cable_pairs,
    ico_rod_geometry,
    preset_parameters,
    rod_inertia,
    write_model,
)

ICO_PAPER = ("paper-uniform", "paper-nonuniform")


def _site_world(m: mujoco.MjModel, d: mujoco.MjData, name: str) -> np.ndarray:
    return d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)].copy()


def _compiled(xml: str, key: str | None = None) -> tuple[mujoco.MjModel, mujoco.MjData]:
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    if key is not None:
        mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, key))
    mujoco.mj_forward(m, d)
    return m, d


# ---------------------------------------------------------------------- icosahedron geometry
def test_ico_pairs_are_found_by_distance_not_hard_coded() -> None:
    L = 1.04
    c, a = ico_rod_geometry(L)
    ends = np.stack([c - a * L / 2, c + a * L / 2], axis=1)
    cable = math.sqrt(6) / 4 * L
    pairs = ico_cable_pairs(ends, cable)
    assert len(pairs) == 24
    # every other end-point distance is far from the cable length (the pairs are unambiguous)
    flat = ends.reshape(-1, 3)
    dist = np.linalg.norm(flat[:, None] - flat[None], axis=-1)[np.triu_indices(12, 1)]
    assert np.sum(np.isclose(dist, cable, rtol=1e-6)) == 24
    others = dist[~np.isclose(dist, cable, rtol=1e-6)]
    assert np.min(np.abs(others - cable)) > 0.1
    # parallel rods are L/2 apart; 8 closed cable triangles
    assert np.linalg.norm(c[0] - c[1]) == pytest.approx(L / 2)
    assert len(closed_faces(pairs)) == 8


@pytest.mark.parametrize("preset", ICO_PAPER)
def test_ico_paper_geometry(preset: str) -> None:
    xml = build_model("ico", preset, seed=3)
    m, d = _compiled(xml)
    assert m.nbody - 1 == 6 and m.ntendon == 24
    assert np.allclose(m.opt.gravity, [0, 0, -9.81])
    assert m.opt.timestep == 0.001 and m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    L = 1.04
    # each rod touches exactly 8 springs, each end exactly 4
    touches: dict[str, int] = {}
    for t in range(m.ntendon):
        for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]):
            site = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, m.wrap_objid[w])
            touches[site] = touches.get(site, 0) + 1
    assert sorted(touches) == sorted(f"rod{i}_end{e}" for i in range(6) for e in (0, 1))
    assert set(touches.values()) == {4}
    # rest lengths 0.637 (paper); built lengths sqrt(6)/4 L; plain push-pull springs
    assert np.allclose(m.tendon_lengthspring, 0.637, atol=1e-3)
    assert np.allclose(d.ten_length, math.sqrt(6) / 4 * L, atol=1e-12)
    assert np.allclose(d.ten_length, 0.637, atol=1e-3)
    # rods are L long, along body z, with the COM at the body origin
    for i in range(6):
        e0, e1 = _site_world(m, d, f"rod{i}_end0"), _site_world(m, d, f"rod{i}_end1")
        assert np.linalg.norm(e1 - e0) == pytest.approx(L)
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"rod{i}")
        assert np.allclose(d.xipos[b], (e0 + e1) / 2)
        assert np.allclose(d.xmat[b].reshape(3, 3)[:, 2], (e1 - e0) / L)


def test_ico_uniform_values() -> None:
    pp = preset_parameters("ico", "paper-uniform")
    assert [r["mass"] for r in pp["rods"]] == [10.0] * 6
    assert {s["stiffness"] for s in pp["springs"]} == {100.0}
    assert {s["damping"] for s in pp["springs"]} == {10.0}
    assert {s["rest_length"] for s in pp["springs"]} == {0.637}
    assert not any(s["pull_only"] for s in pp["springs"])
    assert pp["actuated"] == [] and pp["seed"] is None
    I = rod_inertia(10.0, 1.04, 0.05)
    assert pp["rods"][0]["inertia"] == pytest.approx(list(I))
    assert I[0] == pytest.approx(10 * (1.04**2 / 12 + 0.05**2 / 4))
    assert I[2] == pytest.approx(10 * 0.05**2 / 2)


# ---------------------------------------------------------------------- simple system
def test_simple_paper_values_and_rest_pose() -> None:
    xml = build_model("simple", "paper")
    m, d = _compiled(xml)
    pp = preset_parameters("simple")
    assert pp["preset"] == "paper" and m.nbody - 1 == 1 and m.ntendon == 2
    assert np.allclose(m.opt.gravity, 0)
    assert m.body_mass[1] == 10.0
    assert np.allclose(m.tendon_stiffness, 100) and np.allclose(m.tendon_damping, 10)
    assert np.allclose(m.tendon_lengthspring, [[1.0, 1.0], [1.414, 1.414]])
    # the rod is 2 m long and both springs start at their rest lengths (an equilibrium)
    rod = _site_world(m, d, "rod0_end1") - _site_world(m, d, "rod0_end0")
    assert np.linalg.norm(rod) == pytest.approx(2.0)
    assert np.allclose(d.ten_length, [1.0, 1.414], atol=1e-12)
    assert set(pp["anchors"]) == {"anchor0", "anchor1"}
    for s in pp["springs"]:
        assert s["sites"][1].startswith("anchor")


# ---------------------------------------------------------------------- the robot
def test_robot_model_conventions_and_motor_spec(tmp_path) -> None:
    xml = build_model("ico", "robot")
    root = ET.fromstring(xml)
    for i in range(6):
        body = root.find(f"./worldbody/body[@name='rod{i}']")
        assert body is not None and body.find("freejoint").get("name") == f"rod{i}_free"
        inertial = body.find("inertial")
        assert inertial.get("pos") == "0 0 0" and len(inertial.get("diaginertia").split()) == 3
        sites = {s.get("name"): s.get("pos") for s in body.findall("site")}
        assert set(sites) == {f"rod{i}_end0", f"rod{i}_end1"}
        geom = body.find("geom")
        assert geom.get("contype") == "1" and geom.get("conaffinity") == "0"  # ground only
    spatials = root.findall("./tendon/spatial")
    assert len(spatials) == 24 and all(len(s.findall("site")) == 2 for s in spatials)
    assert all(s.get("name") == f"cable{j}" for j, s in enumerate(spatials))
    assert all(s.get("springlength").split()[0] == "0" for s in spatials)  # pull-only dead-band
    ground = root.find("./worldbody/geom[@name='ground']")
    assert float(ground.get("friction").split()[0]) == pytest.approx(0.9)
    assert root.find("./keyframe/key[@name='nominal']") is not None

    pp = preset_parameters("ico", "robot")
    spec = read_motor_spec(xml)
    assert spec.names == tuple(pp["actuated"]) and spec.n == 24
    assert spec.speed == pp["motor"]["speed"] > 0
    assert np.allclose(spec.rest_min, pp["motor"]["rest_min"])
    rest = np.array([s["rest_length"] for s in pp["springs"]])
    assert np.all(spec.rest_min < rest) and np.all(rest < spec.rest_max)
    # pretension: rest shorter than the nominal sqrt(6)/4 L by 100 N / K
    K = np.array([s["stiffness"] for s in pp["springs"]])
    assert np.allclose(K * (math.sqrt(6) / 4 * 1.7 - rest), 100.0)
    # the same spec from a file path and from the compiled model
    path = tmp_path / "robot.xml"
    path.write_text(xml)
    for other in (read_motor_spec(path), read_motor_spec(mujoco.MjModel.from_xml_string(xml))):
        assert other.names == spec.names and other.speed == spec.speed
        assert np.allclose(other.rest_min, spec.rest_min) and np.allclose(other.rest_max, spec.rest_max)
    assert read_motor_spec(build_model("simple")).n == 0


def test_robot_keyframe_is_a_standing_pose() -> None:
    m, d = _compiled(build_model("ico", "robot"), key="nominal")
    ends = np.array([[_site_world(m, d, f"rod{i}_end{e}") for e in (0, 1)] for i in range(6)])
    low = ends[..., 2] < 0.05
    assert low.sum() == 3  # three end points (one closed triangle) on the ground
    nominal = math.sqrt(6) / 4 * 1.7
    assert np.all(np.abs(d.ten_length / nominal - 1) < 0.05)
    assert np.all(d.ten_length > m.tendon_lengthspring[:, 1])  # every cable taut


# ---------------------------------------------------------------------- truth as data, seeding, overrides
def test_preset_parameters_match_the_mjcf() -> None:
    for system, preset in (("simple", "paper"), ("ico", "paper-nonuniform"), ("ico", "robot")):
        pp = preset_parameters(system, preset, seed=7)
        m = mujoco.MjModel.from_xml_string(build_model(system, preset, seed=7))
        for r in pp["rods"]:
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, r["name"])
            assert m.body_mass[b] == pytest.approx(r["mass"], rel=1e-12)
            assert np.allclose(m.body_inertia[b], r["inertia"], rtol=1e-12)
        for s in pp["springs"]:
            t = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, s["name"])
            assert m.tendon_stiffness[t] == pytest.approx(s["stiffness"], rel=1e-12)
            assert m.tendon_damping[t] == pytest.approx(s["damping"], rel=1e-12)
            assert m.tendon_lengthspring[t, 1] == pytest.approx(s["rest_length"], rel=1e-12)
            assert (m.tendon_lengthspring[t, 0] == 0) == s["pull_only"]


def _draws(seed: int) -> np.ndarray:
    pp = preset_parameters("ico", "paper-nonuniform", seed=seed)
    return np.concatenate([
        [r["mass"] / 10 for r in pp["rods"]],
        [s["stiffness"] / 100 for s in pp["springs"]],
        [s["damping"] / 10 for s in pp["springs"]],
    ])


def test_nonuniform_seeding() -> None:
    a, b = _draws(1), _draws(2)
    assert a.size == 54
    assert np.array_equal(a, _draws(1)) and build_model("ico", "paper-nonuniform", seed=1) == build_model(
        "ico", "paper-nonuniform", seed=1)
    assert not np.allclose(a, b)
    assert preset_parameters("ico", "paper-nonuniform")["seed"] == 0  # None means seed 0
    pool = np.concatenate([_draws(s) for s in range(40)])  # 2160 factors 1 + 0.2 N(0, 1)
    assert abs(pool.mean() - 1) < 0.03 and abs(pool.std() - 0.2) < 0.03
    assert pool.min() >= 0.2
    # inertia follows the drawn mass
    pp = preset_parameters("ico", "paper-nonuniform", seed=5)
    for r in pp["rods"]:
        assert r["inertia"] == pytest.approx(list(rod_inertia(r["mass"], 1.04, 0.05)))


def test_overrides_rescale() -> None:
    base = preset_parameters("ico", "paper-uniform")
    o = preset_parameters("ico", "paper-uniform",
                          overrides={"stiffness_scale": 2.0, "mass_scale": 0.5, "damping_scale": 3.0,
                                     "gravity": (0, 0, 0)})
    for r0, r1 in zip(base["rods"], o["rods"]):
        assert r1["mass"] == pytest.approx(0.5 * r0["mass"])
        assert r1["inertia"] == pytest.approx([0.5 * x for x in r0["inertia"]])
    for s0, s1 in zip(base["springs"], o["springs"]):
        assert s1["stiffness"] == pytest.approx(2 * s0["stiffness"])
        assert s1["damping"] == pytest.approx(3 * s0["damping"])
        assert s1["rest_length"] == s0["rest_length"]
    assert o["gravity"] == [0, 0, 0]
    m = mujoco.MjModel.from_xml_string(
        build_model("ico", "paper-uniform", overrides={"stiffness_scale": 2.0}))
    assert np.allclose(m.tendon_stiffness, 200.0)
    with pytest.raises(ValueError, match="valid overrides are"):
        build_model("simple", overrides={"stifness_scale": 2.0})
    with pytest.raises(ValueError, match="mass_scale"):
        build_model("simple", overrides={"mass_scale": -1})


# ---------------------------------------------------------------------- errors, integrator, file
def test_bad_system_preset_integrator_raise() -> None:
    with pytest.raises(ValueError, match="valid systems are: simple, ico"):
        build_model("cube")
    with pytest.raises(ValueError, match="valid presets are: paper-uniform, paper-nonuniform, robot"):
        build_model("ico", "paper")
    with pytest.raises(ValueError, match="valid presets are: paper$"):
        preset_parameters("simple", "robot")
    with pytest.raises(ValueError, match="valid integrators"):
        build_model("simple", integrator="verlet")


@pytest.mark.parametrize("name,value", [("euler", mujoco.mjtIntegrator.mjINT_EULER),
                                        ("rk4", mujoco.mjtIntegrator.mjINT_RK4),
                                        ("implicitfast", mujoco.mjtIntegrator.mjINT_IMPLICITFAST)])
def test_integrator_keyword(name: str, value: int) -> None:
    assert mujoco.MjModel.from_xml_string(build_model("simple", integrator=name)).opt.integrator == value


def test_write_model_is_atomic_and_complete(tmp_path) -> None:
    path = tmp_path / "m.xml"
    path.write_text("old")
    xml = write_model(path, "ico", "paper-uniform")
    assert path.read_text() == xml == build_model("ico", "paper-uniform")
    assert os.listdir(tmp_path) == ["m.xml"]  # no temporary left behind
    with pytest.raises(ValueError):
        write_model(path, "ico", "nope")
    assert path.read_text() == xml  # a failed build leaves the old file untouched
    with pytest.raises(OSError):
        write_model(tmp_path / "missing-dir" / "m.xml", "simple")


# ---------------------------------------------------------------------- the motor model
def test_motor_step_rate_and_bounds() -> None:
    rest = np.array([1.0, 1.0, 1.0, 0.6])
    target = np.array([0.0, 1.0005, 2.0, 1.0])
    lo, hi = np.full(4, 0.5), np.full(4, 1.2)
    nxt = motor_step(rest, target, 0.3, 0.01, lo, hi)
    assert np.allclose(nxt, [0.997, 1.0005, 1.003, 0.603])
    out = rest.copy()
    for _ in range(1000):
        out = motor_step(out, target, 0.3, 0.01, lo, hi)
    assert np.allclose(out, [0.5, 1.0005, 1.2, 1.0])
    spec = MotorSpec(("a", "b"), 0.3, 0.5, 1.2)  # scalar bounds broadcast
    assert np.allclose(spec.rest_min, [0.5, 0.5])
    with pytest.raises(ValueError):
        MotorSpec(("a",), 0.3, [1.0], [0.5])
