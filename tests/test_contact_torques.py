"""Ground contact's torsional and rolling friction torques: the law against its formula by hand,
the twin's component form against the fit's form, and the fit recovering known coefficients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from identified.effects import effect_from_json, make_effect
from identified.effects.ground_contact import EPSILONS, MU_GRID, OMEGA_GRID, _friction_torque
from identified.engine import RodState, SpringRodEngine
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model

FORCE_LAW = [1500.0, 30.0, 0.95, 4.0, 0.9, 6.0, 0.7, float(MU_GRID[20]), EPSILONS[2]]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """The robot preset rolling on its ground: a short collection, its states with the rods' end
    caps on the ground, and the context of a spring-rod engine (the accelerations under every force
    but the contact's)."""
    xml = tmp_path_factory.mktemp("robot") / "robot.xml"
    write_model(xml, "ico", preset="robot")
    data = collect(xml, CollectConfig(episodes=2, steps=300, seed=3, push_every=50))
    topo = Topology.from_mjcf(xml)
    take = lambda k: torch.as_tensor(getattr(data, k)[:, 20:300].reshape((-1,) + getattr(data, k).shape[2:]))
    s = RodState(take("pos"), take("quat"), take("vel"), take("angvel"))
    s.angvel.add_(torch.as_tensor(np.random.default_rng(0).normal(0, 2.0, s.angvel.shape)))  # spin and roll
    rest = data.rest_length[:, 20:300].reshape(-1, data.rest_length.shape[-1])
    params = {"stiffness": 300.0, "damping": 2.0, "mass": 3.5, "inertia": [0.3, 0.3, 0.002]}
    t = SpringRodEngine(topo, params, data.dt).dynamics(s, rest)
    ctx = t.ctx._replace(base_lin_acc=t.lin_acc, base_ang_acc_body=t.ang_acc_body)
    groups = np.repeat(np.arange(2), s.pos.shape[0] // 2)
    return xml, topo, s, ctx, groups


def test_friction_torque_by_hand_spin_and_roll():
    """One rod pressed with 50 N: spinning at 2 rad/s about the normal it feels
    -mu_t 50 tanh(2 / omega_s) about the normal; rolling at 3 rad/s about x, -mu_r 50 tanh(3 / omega_s)
    about x; a rod at rest feels none; no normal force, none."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    fn = torch.tensor([50.0, 50.0, 50.0, 0.0], dtype=torch.float64)
    w = torch.tensor([[0, 0, 2.0], [3.0, 0, 0], [0, 0, 0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    tau = _friction_torque(fn, w, n, 0.02, 0.004, 0.5).numpy()
    np.testing.assert_allclose(tau[0], [0, 0, -0.02 * 50 * np.tanh(4.0)], rtol=1e-14)
    np.testing.assert_allclose(tau[1], [-0.004 * 50 * np.tanh(6.0), 0, 0], rtol=1e-14)
    np.testing.assert_array_equal(tau[2:], 0.0)
    # saturation: never above mu f_n, and slope mu f_n / omega_s at rest
    fast = _friction_torque(fn[:1], torch.tensor([[0.0, 0, 1e3]], dtype=torch.float64), n, 0.02, 0.0, 0.5)
    assert float(fast[0, 2]) == pytest.approx(-0.02 * 50, rel=1e-12)
    slow = _friction_torque(fn[:1], torch.tensor([[1e-6, 0, 0.0]], dtype=torch.float64), n, 0.0, 0.004, 0.5)
    assert float(slow[0, 0]) == pytest.approx(-0.004 * 50 * 1e-6 / 0.5, rel=1e-9)


def test_old_model_file_loads_with_no_contact_torque(robot):
    """A model file written before the torques (nine parameters) loads with mu_t = mu_r = 0."""
    xml, topo, *_ = robot
    eff = make_effect("ground_contact", topo, str(xml))
    names = ("kappa", "beta_n", "gamma_n", "beta_a", "gamma_a", "beta_p", "gamma_p", "mu", "epsilon")
    obj = {"name": "ground_contact", "parameters": dict(zip(names, FORCE_LAW)),
           "stderr": dict(zip(names, [0.1] * 9)), "options": eff.options}
    e = effect_from_json(obj, topo.n_rods, topo.n_springs)
    np.testing.assert_array_equal(e.values, [*FORCE_LAW, 0.0, 0.0, 1.0])
    assert np.isnan(e.stderr[9:]).all() and (e.stderr[:7] == 0.1).all()


def test_component_form_equals_fit_form_with_torques(robot):
    """The twin's component form carries the same friction torques as the fit's form (float64)."""
    from identified.engine.smallmat import mat, unvec, vec

    xml, topo, s, ctx, _ = robot
    eff = make_effect("ground_contact", topo, str(xml))
    eff.values = np.array([*FORCE_LAW, 0.03, 0.005, 1.0])
    f0, t0 = eff.wrench(s, ctx)
    f1, t1 = (unvec(x) for x in eff.wrench_components(
        vec(s.pos), vec(s.vel), vec(s.angvel), mat(ctx.rot), vec(ctx.base_lin_acc), vec(ctx.base_ang_acc_body),
        ctx.params.mass, vec(ctx.params.inertia)))
    eff.values = np.array([*FORCE_LAW, 0.0, 0.0, 1.0])
    _, t_none = eff.wrench(s, ctx)
    assert float((t0 - t_none).abs().max()) > 0.05  # the torques are there
    scale = float(f0.abs().max())
    torch.testing.assert_close(f1, f0, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(t1, t0, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("torques", [(0.02, 0.003, OMEGA_GRID[1]), (0.01, 0.0, OMEGA_GRID[0])])
def test_fit_recovers_known_torsional_and_rolling_friction(robot, torques):
    """A synthetic plant of the law itself: the residual wrench is the law's own wrench with known
    coefficients (the profiled one on its grid): the fit recovers the torques' coefficients
    exactly, a zero rolling coefficient included (held at its bound, no standard error), explains
    all of the torque about the contact point, and fits the force law exactly as it does on the
    same data without the torques (the torques leave nothing in the force law's rows)."""
    xml, topo, s, ctx, groups = robot
    truth = np.array([*FORCE_LAW, *torques])
    law = make_effect("ground_contact", topo, str(xml))
    law.values = truth
    force, torque = law.wrench(s, ctx)
    eff = make_effect("ground_contact", topo, str(xml))
    stats = eff.fit_residual(s, ctx, force, torque, groups, eff.rows_affected(s, ctx))
    assert stats["rows"] > 300
    np.testing.assert_allclose(eff.values[9:], torques, rtol=1e-9, atol=1e-12)
    assert stats["torque_explained_variance"] > 1 - 1e-12
    assert np.isnan(eff.stderr[10]) == (torques[1] == 0.0)
    law.values = np.array([*FORCE_LAW, 0.0, 0.0, 1.0])
    f0, t0 = law.wrench(s, ctx)
    assert float((t0 - torque).abs().max()) > 0.05  # the torques were there
    bare = make_effect("ground_contact", topo, str(xml))
    bare.fit_residual(s, ctx, f0, t0, groups, bare.rows_affected(s, ctx))
    np.testing.assert_allclose(eff.values[:9], bare.values[:9], rtol=1e-9)
    np.testing.assert_array_equal(bare.values[9:11], 0.0)
