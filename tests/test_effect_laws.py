"""Effect laws on hand-made cases: implicit damping on rods whose axes differ (transverse and
axial inertia), and what the cable friction's fit holds for cables the data never showed sticking
or slipping."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from identified import Topology
from identified.effects import make_effect
from identified.engine import SpringRodEngine
from identified.engine.integration import RodState
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def ico(tmp_path_factory):
    path = tmp_path_factory.mktemp("laws") / "ico.xml"
    write_model(path, "ico", preset="paper-nonuniform", seed=3)
    return str(path)


def test_implicit_drag_solves_the_damped_equations_per_axis(ico):
    """MuJoCo's Euler takes joint damping implicitly: ``(M + dt b) a = F + M g - b v`` and, per
    rod-frame axis k, ``(I_k + dt b_rot) α_k = τ_k - (ω × I ω)_k - b_rot ω_k`` -- with the
    transverse and axial inertias (and the rods' masses and drags) all different."""
    topo = Topology.from_mjcf(ico)
    data = collect(ico, CollectConfig(episodes=1, steps=30, seed=4, push_every=10))
    s = RodState(*(torch.as_tensor(getattr(data, k)[0, 5:25]) for k in ("pos", "quat", "vel", "angvel")))
    rest = data.rest_length[0, 5:25]
    R = topo.n_rods
    rng = np.random.default_rng(1)
    mass = rng.uniform(2.0, 12.0, R)
    inertia = np.stack([rng.uniform(0.5, 2.0, R), rng.uniform(0.5, 2.0, R), rng.uniform(0.01, 0.1, R)], 1)
    b = np.stack([rng.uniform(1.0, 40.0, R), rng.uniform(0.5, 20.0, R)], 1)
    params = {"stiffness": 100.0, "damping": 1.0, "mass": mass, "inertia": inertia}
    dt = 0.05  # large, so that the implicit factor differs from 1 by a lot
    drag = make_effect("linear_drag:implicit", topo)
    drag.values = b.reshape(-1)
    plain = SpringRodEngine(topo, params, dt).dynamics(s, rest)  # no drag
    damped = SpringRodEngine(topo, params, dt, effects=[drag]).dynamics(s, rest)
    M, I = torch.as_tensor(mass)[:, None], torch.as_tensor(inertia)
    b_lin, b_rot = torch.as_tensor(b[:, :1]), torch.as_tensor(b[:, 1:])
    w_b = plain.ctx.angvel_body
    torch.testing.assert_close((M + dt * b_lin) * damped.lin_acc, M * plain.lin_acc - b_lin * s.vel,
                               rtol=1e-12, atol=1e-10)
    torch.testing.assert_close((I + dt * b_rot) * damped.ang_acc_body, I * plain.ang_acc_body - b_rot * w_b,
                               rtol=1e-12, atol=1e-10)
    assert (I[:, 0] != I[:, 2]).all() and (damped.ang_acc_body - plain.ang_acc_body).abs().max() > 1e-2


def test_cable_friction_holds_what_the_data_never_showed(ico):
    """A cable seen sticking fewer than ``min_rows`` times: its stick law (m, d) held at 0; seen
    slipping fewer times: its slip force held at the largest stick force seen and its d at 0."""
    topo = Topology.from_mjcf(ico)
    eff = make_effect("cable_friction", topo)
    S = topo.n_springs
    stuck = np.full(S, 500)
    stuck[0], stuck[1], stuck[2], stuck[3] = 0, 99, 100, 1000  # of 1000 rows
    qmax = np.arange(S, dtype=float) + 0.5
    eff.observe(stuck, 1000, qmax, min_rows=100)
    assert eff.unseen() == {"never_stuck": [0, 1], "never_slipped": [3]}
    pinned = eff.pinned().reshape(S, 3)  # (F, m, d) per cable
    assert pinned[0].tolist() == [False, True, True] and pinned[1].tolist() == [False, True, True]
    assert pinned[2].tolist() == [False, False, False] and pinned[4].tolist() == [False, False, False]
    assert pinned[3].tolist() == [True, False, True]
    vals = eff.pinned_values().reshape(S, 3)
    assert vals[:, 0].tolist() == qmax.tolist() and not vals[:, 1:].any()
    assert eff.partly_unseen() and not eff.inert()
    eff.observe(np.zeros(S), 1000, qmax)
    assert eff.inert() and not eff.partly_unseen()
    eff.observe(np.full(S, 1000), 1000, qmax)
    assert not eff.inert() and not eff.partly_unseen() and eff.unseen()["never_slipped"] == list(range(S))


def test_cable_friction_classifies_stick_and_slip_by_its_law(ico):
    """With fitted values a cable sticks where ``|m L̈ + d L̇| < F``, else slips against the sign of
    ``m L̈ + d L̇``."""
    topo = Topology.from_mjcf(ico)
    eff = make_effect("cable_friction", topo)
    S = topo.n_springs
    F, m, d = 2.0, 0.5, 3.0
    eff.values = np.tile([F, m, d], S)
    acc = torch.linspace(-10.0, 10.0, 7 * S, dtype=torch.float64).view(7, S)
    rate = torch.full_like(acc, 0.2)
    stick, direction = eff.classify(acc, rate)
    q = m * acc + d * rate
    assert torch.equal(stick, q.abs() < F) and 0 < stick.float().mean() < 1
    assert torch.equal(direction, torch.sign(q))


def test_implicit_drag_columns_use_the_recorded_end_velocity(ico):
    """In the fit, the implicit drag's columns are the velocities at the step's end from the
    recorded accelerations: ``-(v + dt a)`` and ``-R (ω_b + dt α_b)``; the explicit variant's are
    the velocities at its start."""
    from types import SimpleNamespace

    from identified.rotation import matrix_apply, quat_to_matrix

    topo = Topology.from_mjcf(ico)
    rng = np.random.default_rng(5)
    N, R = 4, topo.n_rods
    q = torch.as_tensor(rng.normal(size=(N, R, 4)))
    q = q / q.norm(dim=-1, keepdim=True)
    t = lambda *shape: torch.as_tensor(rng.normal(size=shape))
    s = RodState(t(N, R, 3), q, t(N, R, 3), t(N, R, 3))
    rot = quat_to_matrix(q)
    ctx = SimpleNamespace(dt=0.01, rot=rot, angvel_body=t(N, R, 3), recorded_lin_acc=t(N, R, 3),
                          recorded_ang_acc_body=t(N, R, 3))
    force, torque = make_effect("linear_drag:implicit", topo).features(s, ctx)
    torch.testing.assert_close(force[..., 0, :], -(s.vel + 0.01 * ctx.recorded_lin_acc))
    torch.testing.assert_close(torque[..., 1, :],
                               -matrix_apply(rot, ctx.angvel_body + 0.01 * ctx.recorded_ang_acc_body))
    assert not force[..., 1, :].any() and not torque[..., 0, :].any()
    force, torque = make_effect("linear_drag", topo).features(s, ctx)
    torch.testing.assert_close(force[..., 0, :], -s.vel)
    torch.testing.assert_close(torque[..., 1, :], -s.angvel)
