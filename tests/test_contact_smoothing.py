"""The ground's contact law smoothed over a depth (``PyramidContact.smoothing``), which a marker
fit's first steps follow: it tends to the exact law (MuJoCo's) as the width goes to zero, its
wrench is continuous where a contact makes (the exact one jumps), its Newton iterations solve
its own problem (the edges' curvature is their force's derivative), and the compiled step's
component algebra gives the dense one's wrench."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from identified.effects.pyramid_contact import SMOOTHED_ITERATIONS, smoothstep, soft_positive
from identified.state import RodState

from .test_pyramid_contact import TRUTH, rel, wrenches  # noqa: F401  (the fixture)


@pytest.fixture()
def law(wrenches):  # noqa: F811
    law = wrenches[0]
    law.values = TRUTH.copy()
    yield law
    law.smoothing = 0.0


def test_soft_positive_and_smoothstep():
    """h(v) = w log(1 + e^(v/w)): h(0) = w log 2, h -> max(0, v) away from 0, h' and h'' its
    derivatives (autograd); the smooth step 3x² - 2x³ is 0, 1/2, 1 at 0, 1/2, 1 and flat at both ends."""
    v = torch.tensor([-1.0, -0.01, 0.0, 0.003, 1.0], dtype=torch.float64, requires_grad=True)
    h, h1, h2 = soft_positive(v, 0.01)
    hd = h.detach()
    assert float(hd[2]) == pytest.approx(0.01 * np.log(2), rel=1e-15)
    assert float(hd[0]) < 1e-40 and float(hd[4]) == pytest.approx(1.0, rel=1e-15)
    g1 = torch.autograd.grad(h.sum(), v, create_graph=True)[0]
    g2 = torch.autograd.grad(g1.sum(), v)[0]
    torch.testing.assert_close(g1, h1, rtol=1e-12, atol=0)
    torch.testing.assert_close(g2, h2, rtol=1e-12, atol=1e-30)
    x = torch.tensor([-0.5, 0.0, 0.5, 1.0, 2.0], dtype=torch.float64)
    assert smoothstep(x).tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]


def test_smoothed_law_tends_to_mujocos(wrenches, law):  # noqa: F811
    """On the plant run's rod-instants the smoothed law's force departs from MuJoCo's less the
    narrower its width, and tends to it (measured relative RMS: 0.26, 0.19, 0.011, 6.7e-7 at 1 mm,
    0.1 mm, 10 µm, 1 µm; the exact law 2e-6 or less, MuJoCo's solver tolerance)."""
    _, state, ctx, force, *_ = wrenches
    errs = []
    for eps in (1e-3, 1e-4, 1e-5, 1e-6):
        law.smoothing = eps
        errs.append(rel(force, law.wrench(state, ctx)[0]))
    assert errs == sorted(errs, reverse=True)
    assert errs[-1] < 5e-6 and errs[0] > 0.1


def _lifted(wrenches, law, lifts):  # noqa: F811
    """The plant run's first instant with a rod in contact, every rod moving down at 0.2 m/s and
    lifted so that that rod's deepest end sphere is ``lifts`` (m) above the surface (negative: into
    the ground), one row per lift; and that rod's index."""
    _, state, ctx, _, _, touching, _ = wrenches
    k = int(np.flatnonzero(touching.any(-1).numpy())[0])
    rod = int(np.flatnonzero(touching[k].numpy())[0])
    n = len(lifts)
    pick = lambda x: x[k:k + 1].expand((n,) + x.shape[1:]).clone()
    pos, vel = pick(state.pos), pick(state.vel)
    depth = law._end_spheres(RodState(pos, pick(state.quat), vel, pick(state.angvel)), pick(ctx.rot))[1]
    pos[..., 2] += depth[:, rod].amax(-1, keepdim=True) + torch.as_tensor(lifts, dtype=pos.dtype)[:, None]
    vel[..., 2] = -0.2
    c = types.SimpleNamespace(params=ctx.params, rot=pick(ctx.rot), angvel_body=None,
                              base_lin_acc=pick(ctx.base_lin_acc), base_ang_acc_body=pick(ctx.base_ang_acc_body))
    return RodState(pos, pick(state.quat), vel, pick(state.angvel)), c, rod


def test_smoothed_wrench_is_continuous_where_a_contact_makes(wrenches, law):  # noqa: F811
    """A rod coming down at 0.2 m/s: the exact law's normal force jumps as its end sphere touches
    (the damping's β v at zero depth: measured 217 N between lifts 1 µm apart); smoothed over 1 mm
    it changes by at most 0.87 N a µm, and is 0 above ε/2."""
    lifts = np.linspace(-2e-3, 1e-3, 3001)
    s, c, rod = _lifted(wrenches, law, lifts)
    exact = law.wrench(s, c)[0][:, rod, 2]
    law.smoothing = 1e-3
    smooth = law.wrench(s, c)[0][:, rod, 2]
    jump_exact = float(exact.diff().abs().max())
    jump_smooth = float(smooth.diff().abs().max())
    assert float(exact[lifts > 0].abs().max()) == 0.0 and float(smooth[lifts > 0.5e-3 + 1e-9].abs().max()) == 0.0
    assert float(exact[lifts < 0].min()) > 0 and jump_exact > 100 * jump_smooth


def test_newton_solves_the_smoothed_problem(wrenches, law, monkeypatch):  # noqa: F811
    """The smoothed edges' curvature is their force's derivative, so the Newton iterations converge
    on the smooth problem as on the exact one: NEWTON_ITERATIONS of them give what 30 give, on
    every rod-instant of the plant run, to 3e-12 of the largest force (a curvature of the exact law's
    form, D·1(v > 0), planted, leaves 1 N of 500)."""
    import identified.effects.pyramid_contact as pc

    _, state, ctx, *_ = wrenches
    law.smoothing = 1e-3
    got = law.wrench(state, ctx)
    monkeypatch.setattr(pc, "SMOOTHED_ITERATIONS", 30)
    want = law.wrench(state, ctx)
    for a, w in zip(got, want):
        torch.testing.assert_close(a, w, rtol=0, atol=1e-11 * float(w.abs().max()))
    assert SMOOTHED_ITERATIONS < 30


def test_smoothed_component_algebra_equals_the_dense_one(wrenches, law, monkeypatch):  # noqa: F811
    """What a compiled step runs (components) gives the dense form's smoothed wrench (measured: to
    5.7e-10 of the largest force; the exact law's to 1e-10)."""
    import identified.effects.pyramid_contact as pc

    _, state, ctx, *_ = wrenches
    law.smoothing = 1e-3
    want = law.wrench(state, ctx)
    monkeypatch.setattr(pc, "_dense_algebra", lambda: False)
    got = law.wrench(state, ctx)
    for a, w in zip(got, want):
        torch.testing.assert_close(a, w, rtol=0, atol=2e-9 * float(w.abs().max()))
