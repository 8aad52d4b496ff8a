"""The effect library and the loop: plants that hide one effect, clean plants, the robot on its ground.

Truth is built with MuJoCo's own means (fluid viscosity and density in <option>, a gravity the
dataset does not declare, the robot's ground plane); the fit is never told which effect is there.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import re

import numpy as np
import pytest
import torch

from identified.dataset import Dataset
from identified.effects import EFFECTS, effect_from_json, make_effect
from identified.engine import RodState, SpringRodEngine
from identified.fit.identify import identify
from identified.fit.pipeline import fit_model, parse_effects
from identified.model import ModelFileError, load_model, save_model
from identified.predict import rollout_errors
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import preset_parameters, write_model


@pytest.fixture(scope="module")
def ico(tmp_path_factory):
    path = tmp_path_factory.mktemp("ico") / "ico.xml"
    write_model(path, "ico", preset="paper-nonuniform", seed=5)
    return path


def _hidden(ico, tmp_path, option: str, seed: int) -> tuple[str, Dataset]:
    text = ico.read_text()
    key = option.split("=")[0]
    if f' {key}="' in text:
        text = re.sub(rf' {key}="[^"]*"', f" {option}", text)
    else:
        text = text.replace("<option ", f"<option {option} ")
    plant = tmp_path / "plant.xml"
    plant.write_text(text)
    return str(plant), collect(plant, CollectConfig(episodes=4, steps=600, seed=seed, push_every=100))


def _fit_errors(model, data):
    bare = copy.deepcopy(model)
    bare.effects = []
    return rollout_errors(bare, data, horizon=500)["pos_mean"], rollout_errors(model, data, horizon=500)["pos_mean"]


@pytest.mark.parametrize("option,effect,seed", [
    # the search's default-run check is free-joint damping (below); these two run with the benchmarks
    pytest.param('viscosity="1.5"', "linear_drag", 2, marks=pytest.mark.expensive),
    pytest.param('density="60"', "quadratic_drag", 3, marks=pytest.mark.expensive),
])
def test_a_hidden_fluid_effect_is_found_and_removes_the_error(ico, tmp_path, option, effect, seed):
    _, data = _hidden(ico, tmp_path, option, seed)
    model = fit_model(data, ico, effects="auto")  # the fit is given the clean MJCF: no viscosity, no density
    assert [e["name"] for e in model.effects] == [effect]
    assert not model.effects[0]["options"].get("implicit", False)  # fluid drag is explicit
    step = model.loop[0]
    inf = lambda x: np.inf if x is None else x
    assert step["added"] == effect and step["error_after"] * 5 <= inf(step["error_before"])
    test = _hidden(ico, tmp_path, option, seed + 100)[1]
    before, after = _fit_errors(model, test)
    assert after * 5 <= before, (before, after)


def test_free_joint_damping_is_an_implicit_linear_drag(ico, tmp_path):
    """MuJoCo's Euler takes joint damping implicitly: the search picks the implicit variant and
    recovers the damping itself."""
    text = ico.read_text().replace("<freejoint", '<joint type="free" damping="1.5"')
    plant = tmp_path / "damped.xml"
    plant.write_text(text)
    data = collect(plant, CollectConfig(episodes=4, steps=600, seed=12, push_every=100))
    model = fit_model(data, ico, effects="auto")
    assert [(e["name"], e["options"]) for e in model.effects] == [("linear_drag", {"implicit": True})]
    p = model.effects[0]["parameters"]
    np.testing.assert_allclose(p["b_lin"], 1.5, rtol=1e-8)
    np.testing.assert_allclose(p["b_rot"], 1.5, rtol=1e-8)
    assert model.loop[0]["error_after"] < 1e-9 < model.loop[0]["error_before"]


@pytest.mark.expensive
def test_a_gravity_the_dataset_does_not_declare_is_a_constant_force(ico, tmp_path):
    _plant, data = _hidden(ico, tmp_path, 'gravity="0.4 0 -9.81"', 4)
    data = dataclasses.replace(data, gravity=np.array([0.0, 0.0, -9.81]))  # it declares the nominal one
    model = fit_model(data, ico, effects="auto")
    assert [e["name"] for e in model.effects] == ["constant_force"]
    force = np.array(model.effects[0]["parameters"]["force"])  # (R, 3): M_i * (0.4, 0, 0)
    mass = np.array([r["mass"] for r in preset_parameters("ico", "paper-nonuniform", seed=5)["rods"]])
    np.testing.assert_allclose(force[:, 0], 0.4 * mass, rtol=1e-6)
    np.testing.assert_allclose(force[:, 1:], 0.0, atol=1e-6)


def test_declared_cable_slack_on_pull_only_springs_is_exact(ico, tmp_path):
    """The law that reads the rest length, declared (no search): the springs' rest lengths are
    identified with kappa's Gauss-Newton column, and kappa = -K, K and l0 come out exact. In these
    3 x 400 steps springs 10 and 20 never go slack: their kappa is not identifiable (held at 0,
    no error bar, listed), never a number with an error bar that misses the truth."""
    plant = tmp_path / "slack.xml"
    plant.write_text(re.sub(r'springlength="([^" ]+)"', r'springlength="0 \1"', ico.read_text()))
    data = collect(plant, CollectConfig(episodes=3, steps=400, seed=23, push_every=100))
    model = fit_model(data, ico, effects="cable_slack")
    truth = preset_parameters("ico", "paper-nonuniform", seed=5)["springs"]
    K = np.array([s["stiffness"] for s in truth])
    kappa = np.array(model.effects[0]["parameters"]["kappa"])
    se = np.array(model.effects[0]["stderr"]["kappa"], dtype=float)
    seen = np.isfinite(se)
    assert np.flatnonzero(~seen).tolist() == [10, 20] and np.all(kappa[~seen] == 0.0)
    assert [n.split(":")[0] for n in model.metrics["not_identifiable"]] == [
        "cable_slack.spring10.kappa", "cable_slack.spring20.kappa"]
    np.testing.assert_allclose(kappa[seen], -K[seen], rtol=1e-9)
    np.testing.assert_allclose(model.stiffness, K, rtol=1e-9)
    np.testing.assert_allclose(model.rest_length, [s["rest_length"] for s in truth], rtol=0, atol=1e-9)
    assert "(2 not identifiable)" in model.summary()


@pytest.mark.expensive
def test_a_spring_declared_two_sided_that_only_pulls_is_cable_slack(ico, tmp_path):
    """The plant's springs are pull-only cables (MuJoCo's dead band ``springlength="0 L0"``); the fit
    is given them as two-sided springs.  The search adds ``cable_slack`` with kappa = -K on every
    spring (each goes slack in these data), K itself unchanged."""
    plant = tmp_path / "slack.xml"
    plant.write_text(re.sub(r'springlength="([^" ]+)"', r'springlength="0 \1"', ico.read_text()))
    data = collect(plant, CollectConfig(episodes=4, steps=600, seed=23, push_every=100))
    model = fit_model(data, ico, effects="auto")
    assert [e["name"] for e in model.effects] == ["cable_slack"]
    K = np.array([s["stiffness"] for s in preset_parameters("ico", "paper-nonuniform", seed=5)["springs"]])
    # the springs' rest lengths are identified (never read from the data): the slack rows are
    # classified by the estimate, with kappa's Gauss-Newton column in it, until it settles (5e-14)
    np.testing.assert_allclose(model.effects[0]["parameters"]["kappa"], -K, rtol=1e-9)
    np.testing.assert_allclose(model.stiffness, K, rtol=1e-9)
    rest = np.array([s["rest_length"] for s in preset_parameters("ico", "paper-nonuniform", seed=5)["springs"]])
    np.testing.assert_allclose(model.rest_length, rest, rtol=0, atol=1e-9)
    assert model.loop[0]["error_after"] * 1000 <= model.loop[0]["error_before"]


@pytest.mark.parametrize("seed", [6, pytest.param(7, marks=pytest.mark.expensive)])
def test_clean_data_get_nothing_added(ico, seed):
    data = collect(ico, CollectConfig(episodes=4, steps=600, seed=seed, push_every=100))
    model = fit_model(data, ico, effects="auto")
    assert model.effects == [] and model.loop == []
    assert model.metrics["effect_search"]["explained"] is True


def test_declared_effects_fit_to_zero_on_clean_data_and_round_trip(ico, tmp_path):
    data = collect(ico, CollectConfig(episodes=3, steps=400, seed=8, push_every=100))
    model = fit_model(data, ico, effects="linear_drag,quadratic_drag,constant_force,cable_friction")
    for e in model.effects:
        for v in e["parameters"].values():
            assert np.max(np.abs(v)) < 1e-6, (e["name"], v)
    save_model(tmp_path / "m.json", model)
    back = load_model(tmp_path / "m.json")
    assert [e["name"] for e in back.effects] == [e["name"] for e in model.effects]
    for a, b in zip(back.effects, model.effects):
        assert json.dumps(a["parameters"]) == json.dumps(b["parameters"])
    # a loop step whose error before was a diverged free run (null in the JSON) reads as such
    back.loop = [{"added": "linear_drag", "evidence": "free run", "error_before": None, "error_after": 1e-3,
                  "one_step_before": 0.5, "one_step_after": 1e-12}]
    assert "held-out free-run error diverged m -> 0.001 m, one-step 0.5 -> 1e-12" in back.summary()


# ---------------------------------------------------------------------- each effect's wrench, by hand
def _rot(quat: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body -> world of w-x-y-z quaternions, by scipy (not the project's rotation code)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(quat, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(q.shape[:-1] + (3, 3))


def _point_wrench(topo: Topology, pos: np.ndarray, rot: np.ndarray, tension: np.ndarray) -> tuple[np.ndarray, ...]:
    """Force and WORLD torque about each rod's centre of mass (N, R, 3) of a pull ``tension`` (N, S)
    along every spring, applied at its two attachment points: the end on ``end 0`` is pulled toward
    ``end 1`` by ``tension u`` and the other end back, torque ``r x f`` with ``r`` the point's lever."""
    N, R = pos.shape[:2]
    force, torque = np.zeros((N, R, 3)), np.zeros((N, R, 3))
    for j, sp in enumerate(topo.springs):
        pts = [pos[:, i] + rot[:, i] @ np.asarray(sp.offsets[e]) if i >= 0 else np.broadcast_to(sp.offsets[e], (N, 3))
               for e, i in enumerate(sp.rods)]
        u = (pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0], axis=-1, keepdims=True)
        for e, i in enumerate(sp.rods):
            if i < 0:
                continue
            f = (1.0 if e == 0 else -1.0) * tension[:, j, None] * u
            force[:, i] += f
            torque[:, i] += np.cross(pts[e] - pos[:, i], f)
    return force, torque


def _stretch(topo: Topology, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(N, S) each spring's length, from its attachment points."""
    out = []
    for sp in topo.springs:
        pts = [pos[:, i] + rot[:, i] @ np.asarray(sp.offsets[e]) if i >= 0 else np.asarray(sp.offsets[e])
               for e, i in enumerate(sp.rods)]
        out.append(np.linalg.norm(pts[1] - pts[0], axis=-1))
    return np.stack(out, -1)


def _hand_wrench(eff, topo: Topology, s: RodState, rest: np.ndarray, ctx) -> tuple[np.ndarray, np.ndarray]:
    """The effect's force and WORLD torque on each rod from its law as its module docstring writes it."""
    pos, vel, angvel = (np.asarray(x) for x in (s.pos, s.vel, s.angvel))
    rot = _rot(np.asarray(s.quat))
    N, R = pos.shape[:2]
    th = eff.values
    if eff.name == "linear_drag":  # f = -b_lin v, tau = -b_rot w
        b = th.reshape(R, 2)
        return -b[:, 0, None] * vel, -b[:, 1, None] * angvel
    if eff.name == "quadratic_drag":  # rod frame, per axis: f_k = -d_k |v_k| v_k, tau_k = -e_k |w_k| w_k
        d, e = th.reshape(R, 2, 3)[:, 0], th.reshape(R, 2, 3)[:, 1]
        vb = np.einsum("nrji,nrj->nri", rot, vel)
        wb = np.einsum("nrji,nrj->nri", rot, angvel)
        return (np.einsum("nrij,nrj->nri", rot, -d * np.abs(vb) * vb),
                np.einsum("nrij,nrj->nri", rot, -e * np.abs(wb) * wb))
    if eff.name == "constant_force":
        return np.broadcast_to(th.reshape(R, 3), (N, R, 3)), np.zeros((N, R, 3))
    if eff.name == "cable_slack":  # tension kappa min(L - L0, 0); springs declared pull-only held at 0
        kappa = np.where(topo.pull_only, 0.0, th)
        return _point_wrench(topo, pos, rot, kappa * np.minimum(_stretch(topo, pos, rot) - rest, 0.0))
    if eff.name == "cable_friction":  # the force r resisting lengthening pulls both ends together
        return _point_wrench(topo, pos, rot, eff.cable_forces(s, ctx).numpy())
    if eff.name == "ground_contact":  # contact forces in (n, along, across) at the end-sphere centres
        _, local = eff.contact_forces(s, ctx)
        local = local.numpy()
        n = np.asarray(eff.options["normal"], dtype=float)
        axis = rot[..., :, 2]
        along = axis - (axis @ n)[..., None] * n
        along /= np.linalg.norm(along, axis=-1, keepdims=True)
        across = np.cross(n, along)
        force, torque = np.zeros((N, R, 3)), np.zeros((N, R, 3))
        for e in range(2):
            lever = np.einsum("nrij,rj->nri", rot, np.asarray(eff.options["segment"], dtype=float)[:, e])
            f = local[..., e, 0, None] * n + local[..., e, 1, None] * along + local[..., e, 2, None] * across
            force += f
            torque += np.cross(lever, f)
        # torsional and rolling friction: against the spin about the normal and the rolling, each
        # saturating at mu f_n (f_n the rod's total normal force) over the angular speed omega_slip
        mu_t, mu_r, w_s = eff.values[9:12]
        fn = local[..., :, 0].sum(-1)
        w = s.angvel.numpy()
        w_n = w @ n
        w_t = w - w_n[..., None] * n
        t = np.linalg.norm(w_t, axis=-1)
        torque += -(mu_t * fn * np.tanh(w_n / w_s))[..., None] * n
        torque += -(mu_r * fn * np.tanh(t / w_s) / np.maximum(t, 1e-300))[..., None] * w_t
        return force, torque
    raise AssertionError(f"no hand law for {eff.name}")


def _wrench_case(mjcf, name: str, values, seed: int = 1):
    topo = Topology.from_mjcf(mjcf)
    data = collect(mjcf, CollectConfig(episodes=1, steps=60, seed=seed, push_every=10))
    s = RodState(*(torch.as_tensor(getattr(data, k)[0, 10:50]) for k in ("pos", "quat", "vel", "angvel")))
    rest = data.rest_length[0, 10:50]
    eff = make_effect(name, topo, str(mjcf))
    eff.values = values(eff)
    params = {"stiffness": 100.0, "damping": 1.0, "mass": 10.0, "inertia": [1.0, 1.0, 0.1]}
    ctx = SpringRodEngine(topo, params, data.dt, effects=[eff]).dynamics(s, rest).ctx
    return eff, topo, s, rest, ctx


@pytest.mark.parametrize("name", ["linear_drag", "quadratic_drag", "constant_force", "cable_slack",
                                  "cable_friction"])
def test_each_effects_wrench_force_and_torque_is_its_law_by_hand(ico, name):
    """Force AND torque the engine adds, against the law computed independently (scipy rotations,
    forces at the attachment points, torque r x f): the base class's contraction of the columns
    (drags, constant force, cable slack) and cable friction's own ``wrench``."""
    rng = np.random.default_rng(0)

    def values(eff):
        if name == "cable_friction":
            S = eff.n_springs
            return np.stack([rng.uniform(0.5, 3.0, S), rng.uniform(0.05, 0.5, S), rng.uniform(2.0, 30.0, S)], 1).ravel()
        return rng.normal(size=eff.n_params) * (50.0 if name == "cable_slack" else 1.0)

    eff, topo, s, rest, ctx = _wrench_case(ico, name, values)
    f, tau = eff.wrench(s, ctx)
    f_hand, tau_hand = _hand_wrench(eff, topo, s, rest, ctx)
    assert np.abs(tau_hand).max() > 1e-3 or name == "constant_force"  # a torque to check
    np.testing.assert_allclose(f.numpy(), f_hand, rtol=1e-9, atol=1e-9 * np.abs(f_hand).max())
    np.testing.assert_allclose(tau.numpy(), tau_hand, rtol=1e-9, atol=1e-9 * max(np.abs(tau_hand).max(), 1.0))


def test_ground_contacts_wrench_force_and_torque_is_its_law_by_hand(tmp_path):
    """Ground contact overrides ``wrench``: its force and torque are the contact forces at the
    end-sphere centres, in the (normal, along the rod's shadow, across) frame, with torque r x f, plus
    the torsional and rolling friction torques (against the spin about the normal and the rolling)."""
    path = tmp_path / "robot.xml"
    write_model(path, "ico", preset="robot")
    theta = np.array([2000.0, 40.0, 1.0, 5.0, 0.9, 5.0, 0.7, 0.6, 0.05, 0.02, 0.004, 0.7])
    eff, topo, s, rest, ctx = _wrench_case(path, "ground_contact", lambda e: theta)
    f, tau = eff.wrench(s, ctx)
    f_hand, tau_hand = _hand_wrench(eff, topo, s, rest, ctx)
    assert np.abs(f_hand).max() > 1.0  # rods on the ground
    np.testing.assert_allclose(f.numpy(), f_hand, rtol=1e-9, atol=1e-9 * np.abs(f_hand).max())
    np.testing.assert_allclose(tau.numpy(), tau_hand, rtol=1e-9, atol=1e-9 * np.abs(tau_hand).max())


def test_twin_cable_friction_is_the_fit_law_at_the_accelerations_it_makes(ico):
    """The twin solves the box problem; the fit's columns are the law at recorded accelerations.
    One formula: the twin's force equals the fit's columns contracted, at the twin's own
    accelerations, and every force is within its bound (sticking) or at it (slipping)."""
    from identified.engine.forces import endpoint_kinematics, spring_geometry
    from identified.fit.features import step_context

    topo = Topology.from_mjcf(ico)
    data = collect(ico, CollectConfig(episodes=1, steps=50, seed=1, push_every=10))
    s = RodState(*(torch.as_tensor(getattr(data, k)[0, :40]) for k in ("pos", "quat", "vel", "angvel")))
    eff = make_effect("cable_friction", topo, str(ico))
    S = topo.n_springs
    rng = np.random.default_rng(3)
    eff.values = np.stack([rng.uniform(0.5, 3.0, S), rng.uniform(0.05, 0.5, S), rng.uniform(2.0, 30.0, S)], 1).reshape(-1)
    params = {"stiffness": 100.0, "damping": 1.0, "mass": 10.0, "inertia": [1.0, 1.0, 0.1]}
    eng = SpringRodEngine(topo, params, data.dt, effects=[eff])
    rest = data.rest_length[0, :40]
    terms = eng.dynamics(s, rest)
    f, _ = eff.wrench(s, terms.ctx)
    # the fit's context at the twin's accelerations
    chunk = type("C", (), {})()
    chunk.pos, chunk.acc, chunk.alpha_body, chunk.angvel_body = s.pos, terms.lin_acc, terms.ang_acc_body, terms.ctx.angvel_body
    chunk.rest = torch.as_tensor(rest)
    rot = terms.ctx.rot
    ends = endpoint_kinematics(topo, s.pos, s.quat, s.vel, s.angvel, rot=rot)
    ctx = step_context(topo, chunk, rot, ends, spring_geometry(ends))
    cols = eff.end_features(s, ctx)  # (N, S, 2, 3, 3)
    from identified.engine.accelerations import rod_wrench

    th = torch.as_tensor(eff.values).view(S, 1, 3, 1)
    f2, _ = rod_wrench(ctx.graph, (cols * th).sum(-2), ctx.ends.lever)
    torch.testing.assert_close(f, f2, rtol=1e-7, atol=1e-9)
    r = eff.cable_forces(s, terms.ctx)
    F = torch.as_tensor(eff.values.reshape(S, 3)[:, 0])
    stuck, _ = eff.classify(eff._length_acceleration(ctx, eff._length_rows(ctx), terms.lin_acc, terms.ang_acc_body),
                            ctx.geometry.rate)
    assert 0 < stuck.float().mean() < 1  # both regimes occur
    assert torch.all(r.abs() <= F * (1 + 1e-12))
    torch.testing.assert_close(r.abs()[~stuck], F.expand_as(r)[~stuck])


@pytest.mark.parametrize("size,seed", [(5.0, 21), pytest.param(1.5, 22, marks=pytest.mark.expensive)])
def test_tendon_frictionloss_is_identified_exactly_as_sticking_cable_friction(ico, tmp_path, size, seed):
    """MuJoCo's tendon frictionloss (a soft box constraint): the slip force is recovered to the
    solver's tolerance, the stick law's virtual mass is 1 / R (R = (1 - d) / d x invweight0 at
    MuJoCo's default friction impedance d = 0.9) and its rate b = 2 / (dmax timeconst), and the
    twin then runs the plant's free runs to nanometres."""
    import mujoco

    plant = tmp_path / "friction.xml"
    plant.write_text(ico.read_text().replace("<spatial ", f'<spatial frictionloss="{size}" '))
    data = collect(plant, CollectConfig(episodes=4, steps=600, seed=seed, push_every=100))
    model = fit_model(data, ico, effects="cable_friction")
    p = {k: np.array(v) for k, v in model.effects[0]["parameters"].items()}
    np.testing.assert_allclose(p["force"], size, rtol=1e-4)
    truth = mujoco.MjModel.from_xml_path(str(plant))
    np.testing.assert_allclose(p["stick_mass"], 9.0 / truth.tendon_invweight0, rtol=1e-4)
    np.testing.assert_allclose(p["stick_damping"] / p["stick_mass"], 2 / (0.95 * 0.02), rtol=1e-4)
    test = collect(plant, CollectConfig(episodes=2, steps=600, seed=seed + 100, push_every=100))
    before, after = _fit_errors(model, test)
    assert after * 1000 <= before, (before, after)


# 17 s: with the benchmarks; the default run's cable friction fits (the tendon frictionloss check) run
# the kept rows and are checked against the plant's exact slip force
@pytest.mark.expensive
def test_classification_passes_keep_their_rows_and_find_the_same_values(ico, tmp_path, monkeypatch):
    """The classification's passes keep each chunk's rows but the friction's columns between them
    (identify._cached_runs): the same fit, value for value, as one that builds every pass's rows
    afresh, and the same slip force as the plant's."""
    from identified.fit import identify as I

    plant = tmp_path / "friction.xml"
    plant.write_text(ico.read_text().replace("<spatial ", '<spatial frictionloss="5.0" '))
    data = collect(plant, CollectConfig(episodes=3, steps=400, seed=21, push_every=100))
    kept = fit_model(data, ico, effects="cable_friction")
    monkeypatch.setattr(I, "CACHE_BYTES", 0)
    fresh = fit_model(data, ico, effects="cable_friction")
    np.testing.assert_array_equal(kept.stiffness, fresh.stiffness)
    np.testing.assert_array_equal(kept.mass, fresh.mass)
    a, b = (np.array(m.effects[0]["parameters"]["force"]) for m in (kept, fresh))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a, 5.0, rtol=1e-4)


def test_refinement_moves_effect_parameters_back_to_the_truth(ico, tmp_path):
    """Refinement works on the effects' parameters too: a drag put 30 % off moves back toward the
    exact (regression) value while the free-run loss falls.  (L-BFGS over ~100 parameters and the
    windows' initial velocities converges slowly: measured, 30 iterations of 50-step windows
    leave the drag 1-17 % off, 80 of 100-step windows 0.3-7 %.)"""
    from identified.fit.refine import refine

    _, data = _hidden(ico, tmp_path, 'viscosity="1.5"', 31)
    model = fit_model(data, ico, effects="linear_drag")
    exact = np.concatenate([np.array(v) for v in model.effects[0]["parameters"].values()])
    off = copy.deepcopy(model)
    off.effects[0]["parameters"] = {k: (1.3 * np.array(v)).tolist() for k, v in model.effects[0]["parameters"].items()}
    out = refine(off, data.select(episodes=slice(0, 2)), horizon=50, max_windows=16, iterations=30)
    got = np.concatenate([np.array(v) for v in out.effects[0]["parameters"].values()])
    assert np.median(np.abs(got / exact - 1)) < 0.2  # from 0.3
    assert out.metrics["refine"]["loss_after"] * 100 < out.metrics["refine"]["loss_before"]
    assert out.effects[0]["stderr"] is None


def test_effect_names_and_bad_input(ico, tmp_path):
    assert set(EFFECTS) | {"actuator_lag"} == {"ground_contact", "pyramid_contact", "linear_drag", "quadratic_drag",
                                               "cable_friction", "cable_slack", "constant_force", "actuator_lag"}
    with pytest.raises(ValueError, match="unknown effect 'drag'"):
        parse_effects("drag")
    with pytest.raises(ValueError, match="ground plane"):
        make_effect("ground_contact", Topology.from_mjcf(ico), str(ico))
    with pytest.raises(ValueError, match="unknown effect"):
        effect_from_json({"name": "wind", "parameters": {}}, 6, 24)
    data = collect(ico, CollectConfig(episodes=1, steps=50, seed=1))
    model = identify(data, Topology.from_mjcf(ico))
    save_model(tmp_path / "m.json", model)
    obj = json.loads((tmp_path / "m.json").read_text())
    obj["effects"] = [{"name": "linear_drag", "parameters": {"b_lin": [1.0] * 5, "b_rot": [0.0] * 6}}]
    (tmp_path / "bad.json").write_text(json.dumps(obj))
    with pytest.raises(ModelFileError, match="b_lin"):
        load_model(tmp_path / "bad.json")


# ---------------------------------------------------------------------- the robot on its ground
@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = tmp_path_factory.mktemp("robot") / "robot.xml"
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=6, steps=1000, seed=0, push_every=200))
    return path, data


def test_robot_contact_leaves_springs_and_rods_exact_and_explains_the_ground(robot):
    path, data = robot
    model = fit_model(data, path, effects="ground_contact")
    truth = preset_parameters("ico", "robot")
    K = np.array([s["stiffness"] for s in truth["springs"]])
    M = np.array([r["mass"] for r in truth["rods"]])
    I = np.array([r["inertia"] for r in truth["rods"]])
    # the rods' equations away from the ground are contact-free: the spring-rod part is exact
    np.testing.assert_allclose(model.stiffness, K, rtol=1e-8)
    np.testing.assert_allclose(model.mass, M, rtol=1e-8)
    np.testing.assert_allclose(model.inertia, I, rtol=1e-6)
    gc = model.effects[0]["parameters"]
    assert 0.8 < gc["gamma_n"] < 1.2  # the contact cancels what pushes the rod into the ground
    assert model.metrics["residual_stage"]["ground_contact"]["explained_variance"] > 0.7
    test = collect(path, CollectConfig(episodes=3, steps=1000, seed=50))
    before, after = _fit_errors(model, test)
    assert after * 10 <= before, (before, after)


@pytest.mark.expensive
def test_air_drag_on_the_robot_is_found_beside_its_contact_law(robot, tmp_path):
    """Viscous air on the robot: the search adds the exact contact law (``pyramid_contact``) and
    the drag, which halves the held-out free run and comes out as MuJoCo's own drag.  (The search's
    one-step evidence, for an effect whose free-run gain hides under an approximate law's error, is
    checked on its own numbers in tests/test_search_rules.py.)"""
    import mujoco

    path, _ = robot
    viscosity = 1.0
    plant = tmp_path / "viscous.xml"
    plant.write_text(path.read_text().replace("<option ", f'<option viscosity="{viscosity}" '))
    data = collect(plant, CollectConfig(episodes=6, steps=1000, seed=21, push_every=200))
    model = fit_model(data, path, effects="auto")  # the fit sees the MJCF without viscosity
    assert [s["added"] for s in model.loop] == ["pyramid_contact", "linear_drag"], model.loop
    step = model.loop[1]
    assert step["evidence"] == "free run" and step["one_step_after"] < 1e-9 < step["one_step_before"]
    assert step["error_after"] <= step["error_before"]
    # MuJoCo's inertia-box fluid model: force -3π D μ v, torque -π D³ μ ω, D the mean side of the
    # box with the body's mass and inertia
    m = mujoco.MjModel.from_xml_path(str(plant))
    bodies = [m.body(i) for i in range(m.nbody) if m.body(i).jntnum[0] > 0]
    side = np.array([[np.sqrt(6 * max(b.inertia[(k + 1) % 3] + b.inertia[(k + 2) % 3] - b.inertia[k], 0.0)
                              / b.mass[0]) for k in range(3)] for b in bodies])
    D = side.mean(1)
    drag = next(e for e in model.effects if e["name"] == "linear_drag")["parameters"]
    np.testing.assert_allclose(np.ravel(drag["b_lin"]), 3 * np.pi * D * viscosity, rtol=1e-6)
    np.testing.assert_allclose(np.ravel(drag["b_rot"]), np.pi * D**3 * viscosity, rtol=1e-6)


@pytest.mark.expensive
@pytest.mark.parametrize("size,seed", [
    (20.0, 74), (10.0, 81),
    # the exact contact law screens best in the first round here, and beside it the friction's
    # refit does not halve the free run: the search ends with pyramid_contact alone
    pytest.param(30.0, 101, marks=pytest.mark.xfail(strict=True, reason="pyramid_contact chosen first; the "
                                                    "friction round beside it does not pass")),
])
def test_cable_friction_on_the_robot_is_found_beside_its_ground_contact(tmp_path, size, seed):
    """Tendon frictionloss on the robot (20 N moves the rods 2.5 cm over 1 s, 10 N 1.3 cm): the
    search adds ``ground_contact`` first, then ``cable_friction``, exact (F, K, M), and nothing else.
    What made this work: the friction candidate's classification settled without contact is only
    one start of its next round's search; the search's part grows when a rod never leaves the
    ground in it, or when the cables stick too rarely in it to tell each one's law (10 N: ~2 % of
    the time); candidates the short-window screen cannot tell apart are ranked by their free run
    (10 N, seed 81: a constant force screened best and was added in place of contact); with no
    sharp sticking signature (30 N, seed 101: one start) the part grows as well.  2-4 min each."""
    clean = tmp_path / "robot.xml"
    write_model(clean, "ico", preset="robot", seed=seed)
    plant = tmp_path / "plant.xml"
    plant.write_text(clean.read_text().replace("<spatial ", f'<spatial frictionloss="{size}" '))
    data = collect(plant, CollectConfig(episodes=8, steps=3000, seed=seed, push_every=200))
    model = fit_model(data, clean, effects="auto")
    assert [s["added"] for s in model.loop] == ["ground_contact", "cable_friction"]
    p = {e["name"]: e["parameters"] for e in model.effects}
    np.testing.assert_allclose(p["cable_friction"]["force"], size, rtol=1e-6)
    np.testing.assert_allclose(model.stiffness, 2000.0, rtol=1e-6)
    np.testing.assert_allclose(model.mass, 3.5, rtol=1e-6)


def test_the_classification_search_grows_its_part_only_while_it_is_too_small(monkeypatch):
    """A larger part when the starts disagree (the classification matters) or there is one, the
    best one is not settled (residual above rounding) and it sees some cables stick and others not."""
    from identified.fit import classification as I

    monkeypatch.setattr(I, "prepare", lambda effect, data, topology, **kw: None)

    class Seen:  # a classification effect whose classification sees some cables or all or none
        def __init__(self, partly: bool) -> None:
            self.partly, self.values = partly, None

        def partly_unseen(self) -> bool:
            return self.partly

    v = [np.zeros(3)]
    assert I._part_too_small([Seen(True)], v, None, None, [0.19, 0.19, 1.7, 1.7], 1e-3)
    assert not I._part_too_small([Seen(False)], v, None, None, [0.19, 0.19, 1.7, 1.7], 1e-3)  # all seen
    assert not I._part_too_small([Seen(True)], v, None, None, [3.64, 3.63, 3.64], 1e-3)  # starts agree
    assert I._part_too_small([Seen(True)], v, None, None, [0.19], 1e-3)  # one start (no sharp signature)
    assert not I._part_too_small([Seen(True)], v, None, None, [1e-9, 1.7], 1e-9)  # settled


def test_candidates_the_screen_cannot_tell_apart_are_ranked_by_their_free_run(monkeypatch):
    """The robot hiding 10 N of cable friction (seed 81): a constant force screened 0.0226 m and
    ground contact 0.0242 m; their free runs, 0.60 and 0.36 m, decide.  A candidate screened 2x
    worse than the best, or not better than the model without it, gets no free run."""
    from identified.fit import pipeline as P

    free = {"constant_force": 0.60, "ground_contact": 0.36, "linear_drag": 0.01, "cable_slack": 0.001}
    asked = []
    monkeypatch.setattr(P, "_free_run", lambda m, ctx: asked.append(m) or free[m])
    fits = {n: n for n in free}
    screens = {"constant_force": 0.0226, "ground_contact": 0.0242, "linear_drag": 0.0453, "cable_slack": 0.054}
    assert P._judge(screens, 0.054, fits, None, 2.0) == ("ground_contact",
                                                         {"constant_force": 0.60, "ground_contact": 0.36})
    assert sorted(asked) == ["constant_force", "ground_contact"]
    asked.clear()
    same = {n: 0.0014 for n in free}  # clean data after contact: nothing moves the screen
    assert P._judge(same, 0.0014, fits, None, 2.0)[0] in free and len(asked) == 1


def test_the_free_run_evidence_needs_a_gain_from_above_rounding():
    """An exact model's held-out free run is rounding (3e-16 to 1e-15 m); among the candidates
    judged by their free run one halved it by chance (cable_slack's exact model got quadratic_drag
    on the paper plant, seed 16).  Below the floor no ratio is evidence."""
    from identified.fit.pipeline import FREE_RUN_FLOOR, halves

    assert halves(0.0297, 1.05e-15) and halves(1.97, 0.357) and halves(0.357, 0.13)
    assert not halves(1.05e-15, 4.0e-16)  # rounding halved by chance
    assert not halves(0.0401, 0.0401) and not halves(1.97, float("inf")) and not halves(float("inf"), float("inf"))
    assert halves(float("inf"), 0.5)  # a base model that diverged, a candidate that does not
    assert not halves(FREE_RUN_FLOOR / 2, 0.0)


def test_the_classification_search_grows_its_part_of_the_data():
    from identified.fit.classification import SEARCH_STEPS, _search_parts

    def shape(T: int, E: int) -> list[tuple[int, int]]:
        d = Dataset(0.01, np.zeros(3), ("r",), ("s",), ("s",), *(np.zeros((E, T + 1, 1, k)) for k in (3, 4, 3, 3)),
                    *(np.zeros((E, T, 1)) for _ in range(2)), np.zeros((E, T, 1, 3)), np.zeros((E, T, 1, 3)))
        return [(p.n_episodes, p.n_steps) for p in _search_parts(d)]

    assert shape(1000, 20) == [(4, 1000), (8, 1000), (16, 1000), (20, 1000)]
    assert shape(3000, 8) == [(1, 3000), (2, 3000), (4, 3000), (8, 3000)]
    assert shape(600, 4) == [(4, 600)]
    assert shape(2 * SEARCH_STEPS, 3) == [(1, SEARCH_STEPS), (2, SEARCH_STEPS), (3, SEARCH_STEPS)]


@pytest.mark.expensive
def test_robot_twin_stands_like_the_plant(robot, tmp_path):
    """~27 s (a fit and a compiled twin env); the default run keeps its parts cheaply:
    test_robot_contact_leaves_springs_and_rods_exact_and_explains_the_ground (the fit on the robot)
    and tests/test_randomize.py (the compiled twin env steps as the engine); benchmarks/bench_robot_twin.py
    measures the standing."""
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401
    from tensegrity_gym.envs.tensegrity_ico_v0 import rest_to_action

    path, data = robot
    model = fit_model(data, path, effects="ground_contact")
    save_model(tmp_path / "robot.json", model)
    heights = []
    for kw in ({}, {"backend": "identified", "model": str(tmp_path / "robot.json")}):
        env = gym.make("TensegrityIco-v0", max_episode_steps=1000, **kw)
        _, info = env.reset(seed=3)
        u = env.unwrapped
        a = rest_to_action(u.backend.nominal_rest_lengths(), u.rest_min, u.rest_max)
        for _ in range(250):  # 5 s
            _, _, term, _, info = env.step(a)
            assert not term
        heights.append((info["com_height"], info["com"][:2].copy()))
    (hp, xyp), (ht, xyt) = heights
    assert abs(hp - ht) < 0.05 and np.linalg.norm(xyp - xyt) < 0.05


def _roll(env, cable: str | None, seed: int = 0) -> np.ndarray:
    """Contract ``cable`` fully for 2 s, then hold neutral 2.5 s; the centre of mass's (x, y) move."""
    from tensegrity_gym.envs.tensegrity_ico_v0 import rest_to_action

    _, info = env.reset(seed=seed)
    u = env.unwrapped
    names = list(u.backend.actuated_names)
    neutral = rest_to_action(u.backend.nominal_rest_lengths(), u.rest_min, u.rest_max)
    start = info["com"][:2].copy()
    for k in range(225):
        a = neutral.copy()
        if k < 100 and cable is not None:
            a[names.index(cable)] = -1.0
        _, _, term, _, info = env.step(a)
        assert not term
    return info["com"][:2] - start


@pytest.mark.expensive
def test_shipped_twin_rolls_like_the_plant():
    """The shipped model (scripts/make_shipped_model.sh, --effects auto): contracting an edge of the
    base triangle rolls plant and twin onto the same face; another cable rolls neither."""
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401

    plant = gym.make("TensegrityIco-v0", max_episode_steps=1000)
    twin = gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=1000)
    dp, dt = _roll(plant, "cable2"), _roll(twin, "cable2")
    assert np.linalg.norm(dp) > 0.6  # a roll onto the next face
    assert np.linalg.norm(dt - dp) < 0.3 * np.linalg.norm(dp), (dp, dt)
    dp, dt = _roll(plant, "cable1"), _roll(twin, "cable1")
    assert np.linalg.norm(dp) < 0.1 and np.linalg.norm(dt) < 0.1, (dp, dt)
