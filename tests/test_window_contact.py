"""The output-error windows through the ground's contact law (``window_problem(..., contact=...)``)
against known truth: the plant's own states, its parameters and its contact (``pyramid_contact``
at MuJoCo's solref/solimp/friction) predict its clean markers to rounding through every contact,
where the free ground wrench does not; the forward-mode Jacobian goes through the law's Newton
iterations (finite differences); a wrong sign of the law's wrench is caught."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from identified.effects.pyramid_contact import START, PyramidContact
from identified.fit.output_error import _law_transform, window_problem
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model

from .test_pyramid_contact import TRUTH
from .test_record_output_error import _truth

HELD = [(i, 2) for i in range(6)]  # end caps on the rods' axes: the axial spin is not seen


@pytest.fixture(scope="module")
def resting(tmp_path_factory):
    """The robot on its ground, 0.8 s of random commands, clean 30 Hz markers, none missing (and
    the same at 100 Hz, for short windows)."""
    torch.set_num_threads(1)
    path = str(tmp_path_factory.mktemp("wc") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=1, steps=800, seed=3))
    rec = record_markers(data, path, RecordConfig(rate=30, noise_pos=0.0, dropout=0.0), seed=3)
    fast = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.0, dropout=0.0), seed=3)
    return path, data, rec, _truth(path), fast


def _law(path: str, truth, values: np.ndarray) -> PyramidContact:
    law = PyramidContact.for_system(truth.topology, path)
    law.values = np.asarray(values, dtype=float).copy()
    return law


def _rms(prob, dx) -> float:
    with torch.no_grad():
        return float(prob.residuals(prob.theta0, dx).square().mean().sqrt())


def test_law_windows_predict_the_plant_where_the_free_wrench_does_not(resting):
    """At the truth, from the plant's own states, the windows through the law leave the clean
    markers at rounding (measured 1e-10 m over 0.27 s windows with rods on the ground); the free
    wrench at its start (the weight carried) misses them by centimetres; the law with its wrench's
    sign flipped (a planted bug) by more; without its spring (κ = 0) by millimetres."""
    path, data, rec, truth, _ = resting
    sigma = 1e-3
    win, _, prob, dx, acts = window_problem(truth, rec, data, [0.0], path, sigma, HELD, frames=9, max_windows=2,
                                            contact=_law(path, truth, TRUTH))
    assert win.n_windows == 2 and bool(win.free.all()) and prob.n_x == 12 and bool((acts == 1).all())
    # the windows hold contacts: some end sphere of some rod in the ground during each
    depth = prob.contact._end_spheres(type("S", (), {"pos": win.states[..., 0:3]})(),
                                      _rot(win.states[..., 3:7]))[1]
    assert bool((depth > 0).flatten(1).any(1).all())
    assert _rms(prob, dx) * sigma < 1e-8
    _, _, free, dxf, _ = window_problem(truth, rec, data, [0.0], path, sigma, HELD, frames=9, max_windows=2, order=3)
    assert _rms(free, dxf) * sigma > 0.01

    class Flipped(PyramidContact):
        def wrench(self, state, ctx):
            f, t = super().wrench(state, ctx)
            return -f, -t

    bug = Flipped.for_system(truth.topology, path)
    bug.values = TRUTH.copy()
    _, _, bad, dxb, _ = window_problem(truth, rec, data, [0.0], path, sigma, HELD, frames=9, max_windows=2,
                                       contact=bug)
    assert not _rms(bad, dxb) * sigma < 0.05  # (measured: the windows blow up, NaN)
    soft = TRUTH.copy()
    soft[1] = 0.0
    _, _, nok, dxn, _ = window_problem(truth, rec, data, [0.0], path, sigma, HELD, frames=9, max_windows=2,
                                       contact=_law(path, truth, soft))
    assert _rms(nok, dxn) * sigma > 1e-3


def _rot(quat: torch.Tensor) -> torch.Tensor:
    from identified.rotation import quat_to_matrix

    return quat_to_matrix(quat)


def test_free_law_parameters_round_trip_and_bad_names(resting):
    """The law's free parameters enter as logarithms (logits for the impedances) and come back
    exactly; the held ones keep their values; a name the law lacks, or a start that cannot be
    transformed, is one clear line."""
    path, data, rec, truth, _ = resting
    free = ("beta", "imp_min", "mu")
    _, _, prob, _, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=1,
                                      contact=_law(path, truth, TRUTH), law_free=free)
    assert prob.law_names == list(free) and prob.theta0.numel() == prob.n_spring_rod + 3
    np.testing.assert_allclose(prob.law_theta(prob.theta0).numpy(), TRUTH, rtol=1e-12)
    x = _law_transform(list(free), TRUTH[[0, 2, 5]])
    np.testing.assert_allclose(x, [np.log(TRUTH[0]), np.log(0.9 / 0.1), np.log(0.9)], rtol=1e-12)
    with pytest.raises(ValueError, match="has no parameter stiffness"):
        window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=1,
                       contact=_law(path, truth, TRUTH), law_free=("stiffness",))
    zero = TRUTH.copy()
    zero[6] = 0.0
    with pytest.raises(ValueError, match="must start positive"):
        window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=1,
                       contact=_law(path, truth, zero), law_free=("mu_torsion",))


def test_jacobian_through_the_law_matches_finite_differences(resting):
    """Forward mode through the law's Newton iterations (torch.where, the line search): the
    Jacobian in K, c, M, I, the law's free parameters and a window's initial state against central
    differences, from the generic START (a law away from the plant's, contacts active)."""
    path, data, _, truth, fast = resting
    _, _, prob, dx, _ = window_problem(truth, fast, data, [0.0], path, 1e-3, HELD, frames=2, max_windows=1,
                                         contact=_law(path, truth, np.array(list(START.values()))),
                                         law_free=("beta", "kappa", "imp_max", "mu"))
    theta = prob.theta0.clone()
    r, Jx, Jp = prob.jacobians(theta, dx)
    h = 1e-6
    P = theta.numel()
    for k in (0, 30, 49, P - 4, P - 3, P - 2, P - 1):  # a stiffness, a damping, a mass, the law's four
        e = torch.zeros_like(theta)
        e[k] = h
        with torch.no_grad():
            fd = (prob.residuals(theta + e, dx) - prob.residuals(theta - e, dx)).reshape(r.shape) / (2 * h)
        assert float(fd.abs().max()) > 1e-3  # each moves the markers
        np.testing.assert_allclose(Jp[..., k].numpy(), fd.numpy(), rtol=1e-4, atol=1e-5 * float(fd.abs().max()))
    for rod, comp in ((0, 2), (3, 4), (5, 7), (1, 9)):  # height, rotation, velocity, angular velocity
        e = torch.zeros_like(dx)
        e[:, rod, comp] = h
        with torch.no_grad():
            fd = (prob.residuals(theta, dx + e) - prob.residuals(theta, dx - e)).reshape(r.shape) / (2 * h)
        np.testing.assert_allclose(Jx[..., rod * 12 + comp].numpy(), fd.numpy(), rtol=1e-4,
                                   atol=1e-5 * float(fd.abs().max()) + 1e-9)
    _, Jx2, none = prob.jacobians(theta, dx, params=False)
    assert none is None and torch.equal(Jx2, Jx)


def test_a_trial_step_that_breaks_the_law_is_rejected(resting):
    """A joint step whose windows break the law's solve (a singular system, as a step from states
    40 mm off did at 10 Hz) costs infinity and is not taken: the parameters end where they started,
    instead of raising."""
    from identified.fit.marker_fit import fit_markers

    path, data, _, truth, fast = resting
    start = np.array(list(START.values()))

    class Breaks(PyramidContact):
        def wrench(self, state, ctx):
            if not torch.is_grad_enabled() and abs(float(self.theta(state.pos)[0]) / start[0] - 1) > 1e-9:
                raise torch.linalg.LinAlgError("singular")
            return super().wrench(state, ctx)

    law = Breaks.for_system(truth.topology, path)
    law.values = start.copy()
    fit = fit_markers(truth, fast, data, [0.0], path, 1e-3, HELD, frames=2, max_windows=1, state_iters=0,
                      joint_iters=1, contact=law, law_free=("beta",))
    # the parameters are where they started; only the windows' states step after it moved
    assert fit.group("law")[0][0] == pytest.approx(start[0], rel=1e-12)
    assert fit.group("K")[0] == pytest.approx(truth.stiffness, rel=1e-12)
    assert fit.history[-1] <= fit.history[0]


def test_smoothed_jacobians_step_the_exact_cost(resting):
    """``_Problem.with_smoothing``: a copy whose law is smoothed (the problem's own law untouched:
    its residuals the same to the bit), whose residuals differ; a state step on its Jacobians
    reports and lowers the exact law's cost (from the plant's states moved 2 mm); at width 0 the
    problem itself."""
    from identified.fit.marker_bound import nuisance_step

    path, data, _, truth, fast = resting
    _, _, prob, dx, acts = window_problem(truth, fast, data, [0.0], path, 1e-3, HELD, frames=6, max_windows=1,
                                          contact=_law(path, truth, TRUTH))
    assert prob.with_smoothing(0.0) is prob
    gen = torch.Generator().manual_seed(0)
    dx = dx + 2e-3 * torch.randn(dx.shape, generator=gen, dtype=dx.dtype) * acts.reshape(dx.shape)
    before = prob.window_residuals(prob.theta0, dx)
    smooth = prob.with_smoothing(1e-3)
    assert smooth.contact.smoothing == 1e-3 and prob.contact.smoothing == 0.0
    assert torch.equal(prob.window_residuals(prob.theta0, dx), before)
    assert float((smooth.window_residuals(prob.theta0, dx) - before).abs().max()) > 0.1  # 0.1 sigma
    new, r, cost, _, moved = nuisance_step(prob, prob.theta0, dx, acts, 1e-3, jac=smooth)
    exact = prob.window_residuals(prob.theta0, new)
    assert moved and torch.equal(r, exact) and cost == pytest.approx(float(exact.square().sum()), rel=1e-12)
    assert cost < 0.5 * float(before.square().sum())
