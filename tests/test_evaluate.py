"""The evaluation module against hand computations: free-run, window, k-step and one-step errors
by explicit loops over the engine, and the residual wrench of a model whose one mass is 10 % off
(its missing force is exactly 1/11 of that rod's inertial force under the model; every other rod's is 0)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from identified import Topology
from identified.evaluate import (
    k_step_errors,
    one_step_state_errors,
    quat_distance,
    recorded_samples,
    relative_one_step_errors,
    residual_wrench,
    rollout_errors,
    window_error,
)
from identified.fit.identify import identify
from identified.twin import engine_from_model
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model
from tests._data import GROUND


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """Clean data of a paper icosahedron, its exact fit, and the fit with rod 0's mass 10 % high."""
    xml = str(tmp_path_factory.mktemp("evaluate") / "ico.xml")
    write_model(xml, "ico", preset="paper-nonuniform", seed=3)
    data = collect(xml, CollectConfig(episodes=3, steps=60, seed=2, push_every=20))
    exact = identify(data, Topology.from_mjcf(xml))
    mass = exact.mass.copy()
    mass[0] *= 1.1
    return data, exact, replace(exact, mass=mass)


def _run(model, data, e: int, t: int, k: int):
    eng = engine_from_model(model)
    s = eng.state(data.pos[e, t], data.quat[e, t], data.vel[e, t], data.angvel[e, t])
    pos, quat = [s.pos.numpy()], [s.quat.numpy()]
    with torch.no_grad():
        for j in range(t, t + k):
            s = eng.step(s, data.rest_length[e, j], data.push_force[e, j], data.push_point[e, j])
            pos.append(s.pos.numpy())
            quat.append(s.quat.numpy())
    return np.array(pos), np.array(quat)


def test_free_run_curves_and_means(case):
    data, _, wrong = case
    H = 40
    fr = rollout_errors(wrong, data, H)
    runs = [_run(wrong, data, e, 0, H) for e in range(data.n_episodes)]
    pe = np.mean([np.linalg.norm(p - data.pos[e, : H + 1], axis=-1).mean(-1) for e, (p, _) in enumerate(runs)], 0)
    qe = np.mean([quat_distance(q, data.quat[e, : H + 1]).mean(-1) for e, (_, q) in enumerate(runs)], 0)
    assert fr["per_step"]["pos"] == pytest.approx(pe, rel=1e-9, abs=1e-15)
    assert fr["per_step"]["quat"] == pytest.approx(qe, rel=1e-9, abs=1e-15)
    assert fr["per_step"]["pos"][0] == 0.0 and fr["pos_final"] == pytest.approx(pe[-1], rel=1e-9)
    assert fr["pos_mean"] == pytest.approx(pe.mean(), rel=1e-9)  # steps 0..H
    assert fr["pos_mean_after_start"] == pytest.approx(pe[1:].mean(), rel=1e-9)  # steps 1..H
    assert fr["quat_mean"] == pytest.approx(qe.mean(), rel=1e-9) and fr["horizon"] == H
    assert fr["pos_mean"] > 1e-6  # the wrong mass shows


def test_window_error_is_the_mean_over_every_window(case):
    data, _, wrong = case
    steps, stride = 5, 11  # the last window starts at 55 = T - steps
    errs = [np.linalg.norm(_run(wrong, data, e, s, steps)[0] - data.pos[e, s: s + steps + 1], axis=-1).mean()
            for e in range(data.n_episodes) for s in range(0, data.n_steps - steps + 1, stride)]
    assert window_error(wrong, data, steps, stride) == pytest.approx(np.mean(errs), rel=1e-9)
    assert window_error(wrong, data, data.n_steps + 1) == np.inf


def test_k_step_errors_from_every_start(case):
    data, _, wrong = case
    out = k_step_errors(wrong, data, ks=(1, 5, 61), max_starts=10**6)
    assert out["61"] is None  # longer than the episodes
    for k in (1, 5):
        pe, qe = [], []
        for e in range(data.n_episodes):
            for t in range(data.n_steps - k + 1):
                p, q = _run(wrong, data, e, t, k)
                pe.append(np.linalg.norm(p[-1] - data.pos[e, t + k], axis=-1).mean())
                qe.append(quat_distance(q[-1], data.quat[e, t + k]).mean())
        assert out[str(k)]["starts"] == len(pe)
        assert out[str(k)]["pos"] == pytest.approx(np.mean(pe), rel=1e-9)
        assert out[str(k)]["quat"] == pytest.approx(np.mean(qe), rel=1e-9)
    assert k_step_errors(wrong, data, ks=(1,), max_starts=7)["1"]["starts"] == 7


def test_one_step_state_errors(case):
    data, exact, wrong = case
    sq = {k: [] for k in ("pos", "vel", "angvel", "quat")}
    eng = engine_from_model(wrong)
    for e in range(data.n_episodes):
        for t in range(data.n_steps):
            s = eng.state(data.pos[e, t], data.quat[e, t], data.vel[e, t], data.angvel[e, t])
            with torch.no_grad():
                n = eng.step(s, data.rest_length[e, t], data.push_force[e, t], data.push_point[e, t])
            for k in ("pos", "vel", "angvel"):
                sq[k].append(np.sum((getattr(n, k).numpy() - getattr(data, k)[e, t + 1]) ** 2, -1))
            sq["quat"].append(quat_distance(n.quat.numpy(), data.quat[e, t + 1]) ** 2)
    got = one_step_state_errors(wrong, data)
    for k, v in sq.items():
        assert got[k] == pytest.approx(np.sqrt(np.mean(v)), rel=1e-9), k
    assert max(one_step_state_errors(exact, data).values()) < 1e-12


def test_residual_wrench_of_a_wrong_mass(case):
    data, exact, wrong = case
    ch, n_ep, point = recorded_samples(data, "forward")
    assert n_ep == data.n_episodes and ch.pos.shape[0] == data.n_episodes * data.n_steps
    rw = residual_wrench(engine_from_model(wrong), ch, point)
    scale = rw.inertial_force.abs().max().item()
    # M' (a - F / M' - g) = (M' - M) (a - g) = M' (a - g) / 11 for M' = 1.1 M
    assert torch.allclose(rw.force[:, 0], rw.inertial_force[:, 0] / 11, rtol=0, atol=1e-9 * scale)
    assert rw.force[:, 1:].abs().max().item() < 1e-9 * scale
    assert rw.torque_body.abs().max().item() < 1e-9 * rw.inertial_torque_body.abs().max().item()
    f, t = rw.missing_world()  # the recorded inertial wrench less the model's forces (unchanged)
    assert torch.allclose(f[:, 0], rw.inertial_force[:, 0] / 11, rtol=0, atol=1e-9 * scale)
    assert t.abs().max().item() < 1e-9 * rw.inertial_torque_body.abs().max().item()
    # relative one-step error: the RMS of rod 0's missing force over the RMS of the whole wrench
    ref = torch.cat((rw.inertial_force, rw.inertial_torque_body), -1)
    want = (rw.inertial_force[:, 0] / 11).square().sum().sqrt() / ref.square().sum().sqrt()
    errs = relative_one_step_errors([exact, wrong, None], data)
    assert errs[0] < 1e-11 and errs[2] == np.inf
    assert errs[1] == pytest.approx(want.item(), rel=1e-8)


def test_quat_distance_is_sign_invariant():
    q = np.array([0.5, 0.5, 0.5, 0.5])
    assert quat_distance(q, -q) == 0.0 and quat_distance(q, q) == 0.0
    assert quat_distance(q, np.array([1.0, 0, 0, 0])) == pytest.approx(1.0)


def test_relative_one_step_errors_leave_out_the_contact_rows(tmp_path):
    """On the robot, ``ground_contact``'s law is not exact (tens of percent on the rods in
    contact) while everything else is: the one-step error on the other rods is at rounding level,
    and on all the rods it is not."""
    from identified.model import load_model
    from identified.twin import effects_from_model

    xml = str(tmp_path / "robot.xml")
    write_model(xml, "ico", preset="robot")
    data = collect(xml, CollectConfig(episodes=1, steps=300, seed=3, push_every=50))
    model = load_model(GROUND)
    (err,) = relative_one_step_errors([model], data)
    ch, _, point = recorded_samples(data, "forward")
    rw = residual_wrench(engine_from_model(model), ch, point)
    from identified.engine.integration import RodState

    rows = effects_from_model(model)[0].rows_affected(RodState(ch.pos, ch.quat, ch.vel, ch.angvel), rw.terms.ctx)
    assert 0 < rows.float().mean() < 1
    res = torch.cat((rw.force, rw.torque_body), -1)
    ref = torch.cat((rw.inertial_force, rw.inertial_torque_body), -1)
    free = (res[~rows].square().mean().sqrt() / ref[~rows].square().mean().sqrt()).item()
    everywhere = (res.square().mean().sqrt() / ref.square().mean().sqrt()).item()
    assert err == pytest.approx(free, rel=1e-9) and err < 1e-8 and everywhere > 0.01
