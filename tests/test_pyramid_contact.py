"""``pyramid_contact`` against the plant's own contact forces (MuJoCo's ``mj_contactForce``), the known
truth: the law with the plant's contact parameters gives MuJoCo's wrench to its solver's tolerance,
and the fit finds those parameters from that wrench alone, from its generic starting values."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from identified.effects import read_contact_geometry
from identified.effects.pyramid_contact import PyramidContact, impedance
from identified.state import RodState
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model
from tensegrity_gym.plant import MujocoPlant

# the robot preset's contact, as MuJoCo's defaults write it: solref (0.02, 1), solimp (0.9, 0.95,
# 0.001, 0.5, 2), friction (0.9, 0.02, 0.002); β = 2 / (d_w τ), κ = 1 / (d_w² τ² ζ²)
TRUTH = np.array([2 / (0.95 * 0.02), 1 / (0.95 ** 2 * 0.02 ** 2), 0.9, 0.95, 1e-3, 0.9, 0.02, 0.002])


@pytest.fixture(scope="module")
def wrenches():
    """MuJoCo's contact wrench (force, torque about the centre of mass, world) on every rod at
    every 12th step of a short pushed run, with the acceleration every other force gives it."""
    torch.set_num_threads(1)
    xml = build_model("ico", "robot")
    data = collect(xml, CollectConfig(episodes=2, steps=800, seed=3, push_every=200))
    plant = MujocoPlant(xml)
    m, d = plant.model, plant.data
    out = {k: [] for k in ("pos", "quat", "vel", "angvel", "lin", "ang", "force", "torque", "episode")}
    for e in range(data.rest_length.shape[0]):
        for t in range(0, data.rest_length.shape[1], 12):
            plant._write_rest(data.rest_length[e, t])
            d.xfrc_applied[:] = 0.0
            d.xfrc_applied[plant._bid] = plant._push_wrench(data.push_force[e, t], data.push_point[e, t])
            plant.set_states(RodState(data.pos[e, t], data.quat[e, t], data.vel[e, t], data.angvel[e, t]))
            f, tau, _ = plant.contact_wrenches()
            for k, v in (("pos", data.pos[e, t]), ("quat", data.quat[e, t]), ("vel", data.vel[e, t]),
                         ("angvel", data.angvel[e, t]), ("lin", d.qacc_smooth[plant._vadr[:, :3]].copy()),
                         ("ang", d.qacc_smooth[plant._vadr[:, 3:]].copy()), ("force", f), ("torque", tau),
                         ("episode", e)):
                out[k].append(v)
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)
    state = RodState(*(t(out[k]) for k in ("pos", "quat", "vel", "angvel")))
    from identified.rotation import quat_to_matrix

    ctx = types.SimpleNamespace(params=types.SimpleNamespace(mass=t(plant.masses),
                                                             inertia=t(m.body_inertia[plant._bid])),
                                rot=t(quat_to_matrix(np.asarray(out["quat"]))), angvel_body=None,
                                base_lin_acc=t(out["lin"]), base_ang_acc_body=t(out["ang"]))
    law = PyramidContact(plant.n_rods, len(plant.tendon_names), options=read_contact_geometry(xml, plant.rod_names))
    force, torque = t(out["force"]), t(out["torque"])
    touching = force.norm(dim=-1) > 0
    assert int(touching.sum()) > 150  # rod-instants in contact
    return law, state, ctx, force, torque, touching, np.asarray(out["episode"])


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b) ** 2).sum() / (a ** 2).sum()) ** 0.5


def test_impedance_curve():
    d = torch.tensor([0.0, 2.5e-4, 5e-4, 7.5e-4, 1e-3, 5e-3])
    # 2x² to the midpoint, 1 - 2(1-x)² after, held beyond the width
    want = 0.9 + 0.05 * torch.tensor([0.0, 2 * 0.25 ** 2, 0.5, 1 - 2 * 0.25 ** 2, 1.0, 1.0])
    assert torch.allclose(impedance(d, 0.9, 0.95, 1e-3), want, atol=1e-15)


def test_law_is_mujocos_contact(wrenches):
    law, state, ctx, force, torque, touching, _ = wrenches
    law.values = TRUTH.copy()
    f, tau = law.wrench(state, ctx)
    # MuJoCo's Newton solver stops at a relative tolerance of 1e-8; its forces are that close
    assert rel(force, f) < 2e-6 and rel(torque, tau) < 2e-6
    assert float(f[~touching].abs().max()) == 0.0  # no force off the ground
    # the contact at the sphere's centre (on the rod's axis) instead of the capsule's surface is off
    # by percents: the surface point is the law's, not a detail
    radius = law.options["radius"]
    law.options["radius"] = [0.0] * len(radius)
    law._cache.clear()
    f0, _ = law.wrench(state, ctx)
    law.options["radius"] = radius
    law._cache.clear()
    assert rel(force, f0) > 0.02


def test_refit_returns_to_the_contact_parameters(wrenches):
    """A refit starts from the values it holds: from every parameter 3 % off, it lands on the truth."""
    law, state, ctx, force, torque, touching, episodes = wrenches
    fresh = PyramidContact(law.n_rods, law.n_springs, options=law.options,
                           values=TRUTH * (1 + 0.03 * np.array([1, -1, -0.01, 0.01, 1, -1, 1, -1])))
    stats = fresh.fit_residual(state, ctx, force, torque, episodes, touching)
    assert stats["explained_variance"] > 1 - 1e-10
    np.testing.assert_allclose(fresh.values, TRUTH, rtol=1e-5)
    assert np.all(np.isfinite(fresh.stderr)) and np.all(fresh.stderr >= 0)


@pytest.mark.expensive
def test_fit_finds_the_contact_parameters(wrenches):
    """From the generic starting values (~70 s)."""
    law, state, ctx, force, torque, touching, episodes = wrenches
    fresh = PyramidContact(law.n_rods, law.n_springs, options=law.options)
    stats = fresh.fit_residual(state, ctx, force, torque, episodes, touching)
    assert stats["explained_variance"] > 1 - 1e-10
    np.testing.assert_allclose(fresh.values, TRUTH, rtol=1e-5)
    assert np.all(np.isfinite(fresh.stderr)) and np.all(fresh.stderr >= 0)


def test_engine_with_the_law_rolls_as_the_plant():
    """The shipped model's springs and rods (identified to rounding) with the plant's contact in this
    law: the engine's free run from a recorded state follows the plant through contact, pushes and
    rolling to rounding -- the law sits in the engine as it does in MuJoCo's step (after every
    other force, on the rods' own M and inertia)."""
    import dataclasses
    from pathlib import Path

    from identified.evaluate import rollout_errors
    from identified.model import load_model

    torch.set_num_threads(1)
    xml = build_model("ico", "robot")
    shipped = load_model(Path(__file__).resolve().parents[1] / "identified" / "data" / "robot.json")
    law = PyramidContact(shipped.topology.n_rods, shipped.topology.n_springs, values=TRUTH,
                         options=read_contact_geometry(xml, shipped.topology.rod_names))
    model = dataclasses.replace(shipped, effects=[law.to_json()])
    data = collect(xml, CollectConfig(episodes=1, steps=200, seed=5, push_every=60))
    from identified.rotation import quat_to_matrix

    state = RodState(*(torch.as_tensor(getattr(data, k)[0]) for k in ("pos", "quat", "vel", "angvel")))
    _, depth = law._end_spheres(state, torch.as_tensor(quat_to_matrix(data.quat[0])))
    caps = (depth > 0).sum((-1, -2))
    assert bool((caps >= 1).all()) and float(caps.double().mean()) >= 2  # end caps on the ground throughout
    err = rollout_errors(model, data, horizon=200)
    assert err["pos_final"] < 1e-9 and err["quat_final"] < 1e-9


def test_law_does_not_depend_on_where_the_rod_frame_is(wrenches):
    """The same rods described from frames shifted off their centres of mass (the model's ``com``):
    the law's force is the same and its torque about the new origins is the old torque plus the
    lever's (rigid-body kinematics: the origin's velocity and acceleration carry the shift).  A law
    that took the origin's motion for the centre of mass's is percents off here."""
    from identified.engine.smallmat import mat, unvec, vec
    from identified.rotation import matrix_apply

    law, state, ctx, _, _, touching, _ = wrenches
    th = torch.as_tensor(TRUTH)
    p = ctx.params
    force0, torque0 = (unvec(x) for x in law._law(th, vec(state.pos), vec(state.vel), vec(state.angvel), mat(ctx.rot),
                                                  vec(ctx.base_lin_acc), vec(ctx.base_ang_acc_body), p.mass,
                                                  vec(p.inertia), None, None))
    c = torch.as_tensor(np.random.default_rng(4).normal(0, 0.05, (law.n_rods, 3)))  # com in the new frames
    rot = ctx.rot
    rc = matrix_apply(rot, c)  # new origin -> centre of mass, world
    w = state.angvel
    w_b = torch.einsum("...ji,...j->...i", rot, w)
    alpha_b = ctx.base_ang_acc_body
    lin = ctx.base_lin_acc - matrix_apply(rot, torch.linalg.cross(alpha_b, c.expand_as(alpha_b))
                                          + torch.linalg.cross(w_b, torch.linalg.cross(w_b, c.expand_as(w_b))))
    shifted = PyramidContact(law.n_rods, law.n_springs, options={
        **law.options, "segment": (np.asarray(law.options["segment"]) + c.numpy()[:, None, :]).tolist()})
    force1, torque1 = (unvec(x) for x in shifted._law(
        th, vec(state.pos - rc), vec(state.vel - torch.linalg.cross(w, rc)), vec(w), mat(rot), vec(lin), vec(alpha_b),
        p.mass, vec(p.inertia), vec(c), None))
    assert float(force0[touching].norm(dim=-1).max()) > 10  # N: rods pressed into the ground
    scale = float(force0.abs().max())
    torch.testing.assert_close(force1, force0, rtol=0, atol=1e-9 * scale)
    torch.testing.assert_close(torque1, torque0 + torch.linalg.cross(rc, force0), rtol=0, atol=1e-9 * scale)


def test_each_env_its_own_contact_parameters(wrenches):
    """Parameters bound per environment (N, 1, P), as the randomized twin binds them: each env's
    wrench is the law's with its own parameters."""
    from identified.engine.smallmat import mat, unvec, vec

    law, state, ctx, _, _, _, _ = wrenches
    p = ctx.params
    k = 3
    sl = lambda x: x[:k]
    thetas = torch.as_tensor(np.stack([TRUTH, TRUTH * [1.3, 0.7, 1, 1, 2, 0.5, 1.5, 0.8],
                                       TRUTH * [0.8, 1.2, 0.99, 1, 0.5, 1.1, 0.5, 2]]))
    args = lambda j: (vec(sl(state.pos)[j]), vec(sl(state.vel)[j]), vec(sl(state.angvel)[j]), mat(sl(ctx.rot)[j]),
                      vec(sl(ctx.base_lin_acc)[j]), vec(sl(ctx.base_ang_acc_body)[j]), p.mass, vec(p.inertia), None, None)
    batch = [unvec(x) for x in law._law(thetas.unsqueeze(1), *args(slice(None)))]
    for j in range(k):
        one = [unvec(x) for x in law._law(thetas[j], *args(j))]
        for b, o in zip(batch, one):
            torch.testing.assert_close(b[j], o, rtol=1e-12, atol=1e-12)
    at_truth = unvec(law._law(thetas[0], *args(1))[0])
    assert float((batch[0][1] - at_truth).abs().max()) > 1.0  # N: the parameters matter here


def test_twin_steps_the_law_in_its_fused_form():
    """An engine holding the law is fused (the twin's compiled substep steps it in component form),
    and its component step equals its tensor step on robot states pressed into the ground, pushed."""
    import dataclasses
    from pathlib import Path

    from identified.engine.smallmat import unvec, vec
    from identified.model import load_model
    from identified.twin import engine_from_model

    xml = build_model("ico", "robot")
    shipped = load_model(Path(__file__).resolve().parents[1] / "identified" / "data" / "robot.json")
    law = PyramidContact(shipped.topology.n_rods, shipped.topology.n_springs, values=TRUTH,
                         options=read_contact_geometry(xml, shipped.topology.rod_names))
    e = engine_from_model(dataclasses.replace(shipped, effects=[law.to_json()]))
    assert e.fused
    data = collect(xml, CollectConfig(episodes=1, steps=120, seed=8, push_every=30))
    s = e.state(*(getattr(data, k)[0, :-1] for k in ("pos", "quat", "vel", "angvel")))
    s.pos[..., 2] -= 0.004  # 4 mm deeper: every contact's impedance on its rising part
    rest, push = torch.as_tensor(data.rest_length[0]), torch.as_tensor(data.push_force[0])
    want = e.step(s, rest, push)
    got = e.step_components(vec(s.pos), tuple(s.quat.unbind(-1)), vec(s.vel), vec(s.angvel), rest, push)
    for a, w in zip(got, want):
        torch.testing.assert_close(unvec(a), w, rtol=1e-12, atol=1e-12 * float(w.abs().max()))


def test_component_algebra_equals_the_dense_one(wrenches, monkeypatch):
    """The Hessian and its solve in components (what a compiled step runs: sparse products, a
    written-out Cholesky) give the wrench of the dense (..., 6, 6) form, which is MuJoCo's (above),
    to rounding, on every rod-instant of the plant run, per-env parameters included."""
    import identified.effects.pyramid_contact as pc

    law, state, ctx, force, *_ = wrenches
    law.values = TRUTH.copy()
    want = law.wrench(state, ctx)
    monkeypatch.setattr(pc, "_dense_algebra", lambda: False)
    got = law.wrench(state, ctx)
    for a, w in zip(got, want):
        torch.testing.assert_close(a, w, rtol=0, atol=1e-10 * float(w.abs().max()))
    assert rel(force, got[0]) < 2e-6  # and both are MuJoCo's
