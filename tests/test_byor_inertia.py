"""Full rigid-body inertia: each rod's mass, centre of mass (rod frame) and inertia tensor, identified
linearly in the ten standard parameters, and stepped by the engine.

The plant is the prism of ``examples/`` without its floor, its bars given a centre of mass off the
frame's origin and a full inertia tensor (``<inertial fullinertia>``) and attachment sites off their
axes (so that every moment shows in the data), on MuJoCo's Euler integrator: the regression's
equations are the plant's exact discretisation, so clean data give every parameter to rounding.
"""

from __future__ import annotations

import json
import os
import re

import mujoco
import numpy as np
import pytest
import torch

from identified import Topology
from identified.engine import SpringRodEngine, SpringRodParams
from identified.engine.actuators import tendon_forces
from identified.fit.checks import pseudo_inertia
from identified.fit.identify import ScaleSpec, identify
from identified.model import IdentifiedModel, inertia_tensor, principal_axes
from identified.twin import params_from_model
from tensegrity_gym.collect import CollectConfig, collect

PRISM = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "prism3.xml")
#: per bar: centre of mass (rod frame), mass, inertia about it (xx yy zz xy xz yz), rod frame
INERTIAL = {"bar1": ((0.03, -0.01, 0.05), 0.25, (0.0070, 0.0072, 0.0006, 0.0001, -0.00005, 0.00008)),
            "bar2": ((-0.02, 0.015, -0.04), 0.28, (0.0080, 0.0075, 0.0007, -0.0002, 0.00006, 0.0001)),
            "bar3": ((0.01, 0.02, 0.03), 0.31, (0.0085, 0.0090, 0.0008, 0.00015, 0.0001, -0.00007))}


def _plant() -> str:
    with open(PRISM, encoding="utf-8") as fh:
        xml = fh.read()
    xml, n = re.subn(r'<geom name="floor"[^>]*/>', "", xml)
    assert n == 1
    for b, (c, m, j) in INERTIAL.items():
        inertial = (f'<inertial pos="{" ".join(map(str, c))}" mass="{m}" fullinertia="{" ".join(map(str, j))}"/>')
        for end, pos in (("bot", "0.02 0 -0.2897"), ("top", "0 0.02 0.2897")):
            old = f'<site name="{b}_{end}" pos="0 0 {"-" if end == "bot" else ""}0.2897"/>'
            assert old in xml
            xml = xml.replace(old, (inertial if end == "bot" else "") + f'<site name="{b}_{end}" pos="{pos}"/>')
    return xml


def _tensor(j: tuple) -> np.ndarray:
    return np.array([[j[0], j[3], j[4]], [j[3], j[1], j[5]], [j[4], j[5], j[2]]])


@pytest.fixture(scope="module")
def plant_and_data():
    xml = _plant()
    data = collect(xml, CollectConfig(episodes=2, steps=300, seed=3, push_every=50))
    return xml, data


def test_ten_inertial_parameters_recovered_to_rounding(plant_and_data):
    xml, data = plant_and_data
    topo = Topology.from_mjcf(xml)
    model = identify(data, topo, inertia="full", scale=ScaleSpec(total_mass=0.84))
    for i, (c, m, j) in enumerate(INERTIAL.values()):
        assert model.mass[i] == pytest.approx(m, rel=1e-10)
        np.testing.assert_allclose(model.com[i], c, atol=1e-10)
        J = inertia_tensor(model.inertia[i:i + 1], model.inertia_frame[i:i + 1])[0]
        np.testing.assert_allclose(J, _tensor(j), atol=1e-10 * 0.009)
        np.testing.assert_allclose(model.inertia[i], principal_axes(_tensor(j))[0], rtol=1e-9)
        # error bars are at rounding and cover the truth
        se_c, se_i = model.stderr["com"][i], model.stderr["inertia"][i]
        assert np.all(se_c < 1e-12) and np.all(se_i < 1e-12)
        assert np.all(np.abs(model.com[i] - c) <= 5 * se_c + 1e-13)  # + rounding of the data
    assert all(e > 0 for e in model.metrics["pseudo_inertia_min_eigenvalue"])
    assert not [w for w in model.metrics["warnings"] if "inertia" in w]
    # the JSON carries them; a round trip steps the same engine
    obj = json.loads(json.dumps(model.to_json()))
    assert obj["rods"][0]["com"] == pytest.approx(list(INERTIAL["bar1"][0]), abs=1e-10)
    assert len(obj["rods"][0]["inertia_frame"]) == 4 and obj["rods"][0]["com_stderr"] is not None
    back = IdentifiedModel.from_json(obj)
    for a, b in zip(params_from_model(back).as_dict().values(), params_from_model(model).as_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-15)


def test_diagonal_fit_is_the_special_case(plant_and_data):
    """The diagonal model leaves the com and products out; on this plant it cannot describe the
    data and its own residual says so, the full one at rounding."""
    xml, data = plant_and_data
    topo = Topology.from_mjcf(xml)
    diag = identify(data, topo, inertia="diagonal", scale=ScaleSpec(total_mass=0.84))
    assert diag.com is None and diag.inertia_frame is None and not diag.full_inertia
    assert "com" not in diag.stderr
    assert diag.to_json()["rods"][0]["com"] == [0.0, 0.0, 0.0]
    assert diag.metrics["equation_residual_rms"]["rotation"] > 1e3 * identify(
        data, topo, inertia="full", scale=ScaleSpec(total_mass=0.84)).metrics["equation_residual_rms"]["rotation"]
    with pytest.raises(ValueError, match="inertia must be one of"):
        identify(data, topo, inertia="principal")


def test_engine_steps_an_off_centre_rod_as_mujoco(plant_and_data):
    """The engine, given the plant's true parameters (centre of mass, inertia tensor about it), follows
    the plant's own states over 200 steps: one place for the physics of an off-centre rod."""
    xml, data = plant_and_data
    m = mujoco.MjModel.from_xml_string(xml)
    topo = Topology.from_mjcf(xml)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    J = np.stack([_tensor(j) for _, _, j in INERTIAL.values()])
    params = SpringRodParams.from_values(
        m.tendon_stiffness[tid], m.tendon_damping[tid], [x[1] for x in INERTIAL.values()],
        np.einsum("rii->ri", J), 1.0, m.opt.gravity, com=[x[0] for x in INERTIAL.values()],
        inertia_products=J[:, [0, 0, 1], [1, 2, 2]], n_rods=3, n_springs=9)
    engine = SpringRodEngine(topo, params, m.opt.timestep)
    acts = [{"name": f"motor{k}", "tendon": f"vert{k}", "dynamics": "none", "gain": -6.0, "bias": 0.0}
            for k in (1, 2, 3)]
    T = 200
    force = tendon_forces(data.ctrl[:1, :T], data.dt, data.actuator_names, acts, topo.spring_names)[0]
    s0 = [x[0, 0] for x in (data.pos, data.quat, data.vel, data.angvel)]
    out = engine.rollout(engine.state(*s0), data.rest_length[0, :T], data.push_force[0, :T], data.push_point[0, :T],
                         force)
    err = np.abs(out.pos.numpy() - data.pos[0, :T + 1]).max()
    assert err < 1e-9
    assert np.abs(out.angvel.numpy() - data.angvel[0, :T + 1]).max() < 1e-7
    # and the same engine with the centre of mass forgotten does not
    flat = SpringRodEngine(topo, SpringRodParams.from_values(params.stiffness, params.damping, params.mass,
                                                             params.inertia, 1.0, m.opt.gravity), m.opt.timestep)
    off = flat.rollout(flat.state(*s0), data.rest_length[0, :T], data.push_force[0, :T], data.push_point[0, :T], force)
    assert np.abs(off.pos.numpy() - data.pos[0, :T + 1]).max() > 1e3 * max(err, 1e-12)


def test_component_form_agrees_with_the_tensor_form():
    """The twin's fused step (component form) and ``step`` give the same state with a com offset."""
    topo = Topology.from_mjcf(_plant())
    rng = np.random.default_rng(0)
    J = np.stack([_tensor(j) for _, _, j in INERTIAL.values()])
    params = SpringRodParams.from_values(rng.uniform(200, 300, 9), rng.uniform(2, 3, 9), [0.25, 0.28, 0.31],
                                         np.einsum("rii->ri", J), com=[x[0] for x in INERTIAL.values()],
                                         inertia_products=J[:, [0, 0, 1], [1, 2, 2]], n_rods=3, n_springs=9)
    engine = SpringRodEngine(topo, params, 1e-3)
    q = rng.normal(size=(4, 3, 4))
    s = engine.state(rng.normal(size=(4, 3, 3)), q / np.linalg.norm(q, axis=-1, keepdims=True),
                     rng.normal(size=(4, 3, 3)), rng.normal(size=(4, 3, 3)))
    rest = torch.full((4, 9), 0.3, dtype=torch.float64)
    a = engine.step(s, rest)
    b = engine.step_components(*(tuple(x.unbind(-1)) for x in s), rest)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, torch.stack(y, -1), rtol=1e-12, atol=1e-12)


def test_pseudo_inertia_tells_a_rigid_body_from_none():
    """Positive principal moments that keep the triangle inequality: a positive-definite pseudo-inertia;
    moments that break it: not."""
    c = np.array([0.01, -0.02, 0.03])
    assert np.linalg.eigvalsh(pseudo_inertia(0.3, c, np.diag([0.007, 0.0072, 0.0006])))[0] > 0
    assert np.linalg.eigvalsh(pseudo_inertia(0.3, c, np.diag([0.007, 0.0072, 0.0001])))[0] < 0  # 0.0072 > 0.007 + 0.0001
    with pytest.raises(ValueError, match="implicit integrator"):
        SpringRodEngine(Topology.from_mjcf(_plant()), SpringRodParams.from_values(
            np.ones(9), np.ones(9), np.ones(3), np.ones((3, 3)), com=np.zeros((3, 3)), n_rods=3, n_springs=9),
            1e-3, integrator="implicit")


def test_a_fit_that_is_no_rigid_body_is_constrained_to_one():
    """Ten parameters whose tensor about the centre of mass is not positive definite: that rod's
    products are held at 0 and the problem solved again, with a warning naming it."""
    from identified.fit.checks import constrain_rigid_bodies
    from identified.fit.layout import ParameterLayout
    from identified.fit.regression import Solution

    topo = Topology.from_mjcf(_plant())
    layout = ParameterLayout.for_topology(topo, full_inertia=True)
    theta = np.zeros(layout.n_full)
    for i in range(3):
        theta[layout.m(i)] = 0.3
        theta[[layout.inertia(i, a) for a in range(3)]] = [0.007, 0.0072, 0.0006]
        theta[layout.first_moment(i, 0)] = 0.3 * 0.01
    theta[layout.product(1, 0)] = 0.02  # rod 1: Jxy larger than its moments allow
    def resolve(f: dict[int, float]) -> Solution:  # the same "fit" with the held values put in
        th = theta.copy()
        th[list(f)] = list(f.values())
        return Solution(th, None, [], 1.0, 0, 0)

    fixed: dict[int, float] = {}
    out, notes, held = constrain_rigid_bodies(Solution(theta, None, [], 1.0, 0, 0), resolve, layout, fixed)
    assert len(notes) == 1 and notes[0].startswith("bar2:") and held == []
    assert set(fixed) == {layout.product(1, k) for k in range(3)}  # the centre of mass is kept
    assert out.theta[layout.product(1, 0)] == 0.0 and out.theta[layout.first_moment(1, 0)] == 0.3 * 0.01
    # a consistent solution is returned as it is
    theta[layout.product(1, 0)] = 0.0
    assert constrain_rigid_bodies(Solution(theta, None, [], 1.0, 0, 0), None, layout, {})[1] == []


def test_full_inertia_without_cables_to_classify():
    """Push-pull springs and motors without filters: no rest-length classification to iterate, and the
    centre of mass and products are still released after the first (diagonal) solve."""
    xml = _plant().replace('springlength="0 ', 'springlength="')
    data = collect(xml, CollectConfig(episodes=1, steps=300, seed=4, push_every=50))
    model = identify(data, Topology.from_mjcf(xml), inertia="full", scale=ScaleSpec(total_mass=0.84))
    np.testing.assert_allclose(model.com, [c for c, _, _ in INERTIAL.values()], atol=1e-10)


def test_auto_gives_composite_rods_the_full_model():
    """``inertia="auto"``: all ten parameters for a topology with composite rods (several bodies),
    the diagonal model for rods of one body."""
    with open(os.path.join(os.path.dirname(PRISM), "six_bar_composite.xml"), encoding="utf-8") as fh:
        composite = re.sub(r'<geom name="ground"[^>]*/>', "", fh.read())  # in the air: no contact to model
    for xml, full in ((composite, True), (re.sub(r'<geom name="floor"[^>]*/>', "", _read_prism()), False)):
        data = collect(xml, CollectConfig(episodes=1, steps=300, seed=1, push_every=50))
        model = identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(total_mass=1.0))
        assert model.full_inertia is full and (model.com is not None) is full


def _read_prism() -> str:
    with open(PRISM, encoding="utf-8") as fh:
        return fh.read()


def test_fit_command_takes_the_inertia_model(plant_and_data, tmp_path, monkeypatch):
    """``tensegrity fit --inertia full`` on the off-centre prism (single-body rods, which ``auto``
    fits diagonally) writes every rod's centre of mass to rounding; a wrong choice is one line."""
    from identified.dataset import save_dataset
    from identified.model import load_model
    from tests._fuzz import run_cli

    xml, data = plant_and_data
    monkeypatch.chdir(tmp_path)
    (tmp_path / "p.xml").write_text(xml)
    save_dataset("d.npz", data)
    rc, _, err = run_cli(["fit", "d.npz", "--model", "p.xml", "--total-mass", "0.84", "--inertia", "full",
                          "--out", "f.json", "--quiet"])
    assert rc == 0, err
    com = load_model("f.json").com
    np.testing.assert_allclose(com, [c for c, _, _ in INERTIAL.values()], rtol=0, atol=1e-9)
    rc, _, err = run_cli(["fit", "d.npz", "--model", "p.xml", "--inertia", "principal", "--out", "g.json"])
    assert rc == 2 and "--inertia" in err and not os.path.exists("g.json")


# ---------------------------------------------------------------------- ground contact, full tensor
_BAR = ('<mujoco><worldbody><body name="bar" pos="0.1 -0.2 0.25" quat="0.8 0.3 -0.4 0.33"><freejoint/>'
        '<inertial pos="0.03 -0.01 0.05" mass="0.25" fullinertia="0.0070 0.0072 0.0006 0.0001 -0.00005 0.00008"/>'
        '<geom type="capsule" fromto="0 0 -0.2897 0 0 0.2897" size="0.01"/></body></worldbody></mujoco>')
_SEGMENT = [[0.0, 0.0, -0.2897], [0.0, 0.0, 0.2897]]
#: a contact law: κ, β_n, γ_n, β_a, γ_a, β_p, γ_p, μ, ε, μ_torsion, μ_rolling, ω_slip
_LAW = [4000.0, 60.0, 0.95, 40.0, 0.9, 30.0, 0.7, 0.8, 0.05, 0.004, 0.002, 1.0]


def _contact_bar(full: bool = True):
    """The bar's MuJoCo model and data, its ground contact law and the engine's view of its rigid
    body: the true centre of mass and inertia tensor (``full``) or the principal moments alone."""
    from types import SimpleNamespace

    from identified.effects.ground_contact import GroundContact

    m = mujoco.MjModel.from_xml_string(_BAR)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    J = inertia_tensor(m.body_inertia[1:2], m.body_iquat[1:2])[0]
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=float))
    params = SimpleNamespace(mass=t([m.body_mass[1]]), inertia=t([np.diag(J)]) if full else t(m.body_inertia[1:2]),
                             com=t(m.body_ipos[1:2]) if full else None,
                             inertia_products=t([J[[0, 0, 1], [1, 2, 2]]]) if full else None)
    gc = GroundContact(1, 0, values=_LAW, options={"radius": [0.01], "segment": [_SEGMENT], "ground_height": 0.0,
                                                   "normal": [0.0, 0.0, 1.0]})
    return m, d, gc, params


def test_contact_effective_mass_is_mujocos_for_an_off_centre_rod():
    """The contact law's inverse effective-mass matrix of a rod whose centre of mass is 5 cm off its
    frame's origin, with a full inertia tensor (both end spheres, in the contact directions)
    equals MuJoCo's ``J M⁻¹ Jᵀ`` at the same points to rounding; the principal moments alone with
    the lever from the frame's origin (the diagonal model) miss it by far."""
    from types import SimpleNamespace

    m, d, gc, params = _contact_bar()
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    rot = d.xmat[1].reshape(3, 3)
    jac = []
    for end in _SEGMENT:
        jacp = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jacp, None, d.xpos[1] + rot @ np.array(end), 1)
        jac.append(jacp)
    jac = np.concatenate(jac)
    truth = jac @ np.linalg.solve(M, jac.T)  # (6, 6): (end, world axis)
    state = SimpleNamespace(pos=torch.as_tensor(d.xpos[1:2].copy()))
    for full in (True, False):
        params = _contact_bar(full)[3]
        c = gc.contacts(state, SimpleNamespace(rot=torch.as_tensor(rot[None].copy()), params=params))
        D = np.zeros((6, 6))  # world -> (end, contact direction)
        D[:3, :3], D[3:, 3:] = c["dirs"][0, 0].numpy(), c["dirs"][0, 1].numpy()
        want = D @ truth @ D.T
        if full:
            np.testing.assert_allclose(c["A"][0].numpy(), want, rtol=0, atol=1e-12 * np.abs(want).max())
        else:
            assert np.abs(c["A"][0].numpy() - want).max() > 0.05 * np.abs(want).max()


def test_contact_component_form_agrees_for_an_off_centre_rod():
    """The twin's component form of the contact law (:meth:`GroundContact.wrench_components`) equals
    the fit's tensor form with a centre of mass off the frame and products of inertia, on moving
    states with an end sphere in the ground."""
    from types import SimpleNamespace

    from identified.engine.smallmat import mat, unvec, vec
    from identified.rotation import quat_to_matrix

    _, _, gc, p = _contact_bar()
    rng = np.random.default_rng(3)
    n = 48
    quat = torch.as_tensor(rng.normal(size=(n, 1, 4)))
    quat = quat / quat.norm(dim=-1, keepdim=True)
    rot = quat_to_matrix(quat)
    pos = torch.as_tensor(np.concatenate([rng.normal(0, 0.3, (n, 1, 2)), rng.uniform(0.0, 0.3, (n, 1, 1))], -1))
    r = lambda s: torch.as_tensor(rng.normal(0, s, (n, 1, 3)))
    state = SimpleNamespace(pos=pos, vel=r(0.5), angvel=r(1.0))
    ctx = SimpleNamespace(rot=rot, params=p, base_lin_acc=r(5.0), base_ang_acc_body=r(20.0))
    c, f = gc.contact_forces(state, ctx)
    force0, torque0 = gc._to_wrench(c, f)
    torque0 = torque0 + gc.contact_torque(state, f, gc.theta(pos))
    force, torque = (unvec(x) for x in gc.wrench_components(
        vec(pos), vec(state.vel), vec(state.angvel), mat(rot), vec(ctx.base_lin_acc), vec(ctx.base_ang_acc_body),
        p.mass, vec(p.inertia), vec(p.com), vec(p.inertia_products)))
    assert 10 < int(c["active"].sum()) < c["active"].numel()
    scale = float(force0.abs().max())
    torch.testing.assert_close(force, force0, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(torque, torque0, rtol=0, atol=1e-12 * scale)
