"""Blocks of a recording's windows fitted on their own and combined (identified.fit.marker_blocks),
against known truth: for a model linear in its unknowns the combination is the least-squares
estimate of all the data at once, its covariance that estimate's, exactly (with and without a
constraint); the blocks' chi-square is the analytic one for a known shift and follows its
distribution under noise; the blocks of window_problem partition its windows; and a marker fit in
two blocks brings a start off the truth back from clean markers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.special import expit, logit

from identified.fit.bound import constrained_bound
from identified.fit.marker_blocks import combine, combine_fits
from identified.fit.marker_fit import MarkerFit
from identified.fit.marker_model import MarkerRefineConfig, refine_recording
from identified.fit.output_error import window_problem
from identified.recording import RecordingError

from .test_marker_refine import floorless  # noqa: F401 -- a fixture, shared


def _blocks(rng, P=6, rows=(30, 45, 25), sigma=0.1):
    """Blocks of a linear model ``y = X θ* + σ ε``: their designs, data and information."""
    theta = rng.normal(size=P)
    X = [rng.normal(size=(n, P)) for n in rows]
    y = [x @ theta + sigma * rng.normal(size=len(x)) for x in X]
    return theta, X, y, [x.T @ x / sigma ** 2 for x in X]


@pytest.mark.parametrize("constrained", [False, True])
def test_combined_blocks_are_the_least_squares_estimate_of_all_the_data(constrained):
    rng = np.random.default_rng(5)
    theta, X, y, info = _blocks(rng)
    P = theta.size
    a = np.array([[0.0, 0.0, 0.3, 0.7, 0.0, 0.0]]) if constrained else np.zeros((0, P))
    p0 = a.T @ np.linalg.solve(a @ a.T, a @ theta) if constrained else np.zeros(P)  # meets a θ = a θ*
    U = sla.null_space(a) if constrained else np.eye(P)

    def lsq(xs, ys):
        xu = np.vstack(xs) @ U
        return p0 + U @ np.linalg.lstsq(xu, np.concatenate(ys) - np.vstack(xs) @ p0, rcond=None)[0]

    each = [lsq([x], [v]) for x, v in zip(X, y)]
    got, cov, agree = combine(each, info, a if constrained else None)
    np.testing.assert_allclose(got, lsq(X, y), rtol=0, atol=1e-12)
    Xall = np.vstack(X)
    want_cov = U @ np.linalg.inv(U.T @ Xall.T @ Xall @ U / 0.1 ** 2) @ U.T
    np.testing.assert_allclose(cov, want_cov, rtol=1e-10, atol=1e-16)
    assert agree.dof == 2 * U.shape[1]
    if constrained:
        np.testing.assert_allclose(a @ got, a @ theta, rtol=1e-12)


def test_the_chi_square_of_a_shifted_block_is_the_analytic_one():
    rng = np.random.default_rng(2)
    theta, _, _, info = _blocks(rng, P=4, rows=(20, 30, 40))
    d = np.array([0.3, -0.2, 0.0, 0.1])
    got, _, agree = combine([theta + d, theta, theta], info)
    # θ̄ = θ + C I₀ d; χ² = (d - C I₀ d)ᵀ I₀ (d - C I₀ d) + Σ_{b>0} (C I₀ d)ᵀ I_b (C I₀ d) = dᵀ (I₀ - I₀ C I₀) d
    C = np.linalg.inv(sum(info))
    np.testing.assert_allclose(got, theta + C @ info[0] @ d, rtol=1e-12)
    assert agree.chi2 == pytest.approx(d @ (info[0] - info[0] @ C @ info[0]) @ d, rel=1e-10)
    assert agree.dof == 8
    same = combine([theta, theta, theta], info)[2]
    assert same.chi2 == pytest.approx(0.0, abs=1e-12) and same.p == pytest.approx(1.0)


def test_the_chi_square_under_noise_has_its_degrees_of_freedom_as_mean():
    """400 draws of 3 blocks' estimates from their own covariance: the chi-square's mean is its
    degrees of freedom (8) within 3 standard errors of the mean (sqrt(2 * 8 / 400) * 3 = 0.6), and
    4-6 % of the p values fall below 0.05 (binomial sd 1.1 %: within 3 of them)."""
    rng = np.random.default_rng(9)
    theta, _, _, info = _blocks(rng, P=4, rows=(20, 30, 40))
    chi, ps = [], []
    for _ in range(400):
        est = [rng.multivariate_normal(theta, np.linalg.inv(i)) for i in info]
        a = combine(est, info)[2]
        chi.append(a.chi2)
        ps.append(a.p)
    assert abs(np.mean(chi) - 8) < 0.6
    assert abs(np.mean(np.array(ps) < 0.05) - 0.05) < 0.033


def test_a_direction_no_block_sees_keeps_their_mean_and_has_no_bound():
    info = [np.diag([4.0, 9.0, 0.0]), np.diag([1.0, 1.0, 0.0])]
    got, cov, agree = combine([np.array([1.0, 2.0, 3.0]), np.array([2.0, 0.0, 5.0])], info)
    np.testing.assert_allclose(got, [(4 * 1 + 2) / 5, (9 * 2 + 0) / 10, 4.0], rtol=1e-12)
    np.testing.assert_allclose(cov, np.diag([1 / 5, 1 / 10, 0.0]), atol=1e-14)
    assert agree.dof == 2


def _fake_fit(rng, names, total=10.0) -> MarkerFit:
    """A marker fit of the unknowns ``names`` (masses ``M[..]`` at the total mass, a logit impedance)."""
    P = len(names)
    msl = np.array([n.startswith("M[") for n in names])
    theta = rng.normal(size=P)
    theta[msl] += np.log(total) - np.log(np.exp(theta[msl]).sum())
    row = np.zeros(P)
    row[msl] = np.exp(theta[msl]) / np.exp(theta[msl]).sum()
    A = rng.normal(size=(3 * P, P))
    info = A.T @ A
    natural = np.where([n.startswith("law[imp_") for n in names], expit(theta), np.exp(theta))
    natural = np.where([n.startswith("gain[") for n in names], -40.0 * natural, natural)  # a gain: its start's times
    cov = constrained_bound(info, names, natural, constraints=row[None])
    step = cov.cov @ rng.normal(size=P)  # a Gauss-Newton step keeps the total mass, as -C g does
    return MarkerFit(cov, 7, 30, 0.011, [3.0, 2.0], 5.0, True, step / cov.rel_se, 200.0, theta, info, row)


def test_a_fit_combined_with_itself_is_itself_with_half_the_covariance():
    rng = np.random.default_rng(4)
    names = ["K[a]", "K[b]", "M[r0]", "M[r1]", "M[r2]", "gain[m0]", "law[beta]", "law[imp_min]"]
    f = _fake_fit(rng, names)
    g = combine_fits([f, f])
    np.testing.assert_allclose(g.theta, f.theta, atol=1e-12)
    np.testing.assert_allclose(g.cov.cov, f.cov.cov / 2, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(g.cov.values, f.cov.values, rtol=1e-12)
    assert g.cov.values[-1] == pytest.approx(expit(f.theta[-1]), rel=1e-12)  # the impedance from its logit
    assert g.cov.values[5] == pytest.approx(-40.0 * np.exp(f.theta[5]), rel=1e-12)  # the gain from its start's
    np.testing.assert_allclose(g.to_minimum, f.to_minimum * np.sqrt(2), rtol=1e-9)  # same step, bars sqrt(2) smaller
    assert np.exp(g.theta[2:5]).sum() == pytest.approx(10.0, rel=1e-14)
    assert g.agreement.chi2 == pytest.approx(0.0, abs=1e-10) and g.agreement.dof == len(names) - 1
    assert (g.windows, g.available, g.dof, g.residual_rms) == (14, 30, 400.0, pytest.approx(0.011))
    assert g.blocks == [f, f] and g.converged
    assert logit(g.cov.values[-1]) == pytest.approx(f.theta[-1], rel=1e-12)
    with pytest.raises(ValueError, match="same parameters"):
        combine_fits([f, dataclasses.replace(f, theta=None)])


def test_the_blocks_of_window_problem_partition_its_windows(floorless):  # noqa: F811 -- the imported fixture
    from identified.fit.markers import states_from_recording

    _, rec, truth = floorless
    ms = states_from_recording(rec, truth.topology, truth.dt)

    def windows(block):
        win = window_problem(truth, rec, ms.data, ms.starts, None, 1e-3, ms.unobservable, frames=6, max_windows=7,
                             block=block)[0]
        return win.obs.numpy()

    whole = windows((0, 1))
    parts = [windows((b, 3)) for b in range(3)]
    assert [len(p) for p in parts] == [3, 2, 2] and len(whole) == 7
    for b, p in enumerate(parts):
        np.testing.assert_array_equal(p, whole[b::3])
    with pytest.raises(RecordingError, match="4 blocks of windows need at least two windows each; the fit has 7"):
        windows((0, 4))


def test_two_blocks_bring_a_start_off_the_truth_back(floorless):  # noqa: F811 -- the imported fixture
    """K 3 % off and the masses 3 % off at the right total; 4 windows of 10 clean 100 Hz frames in
    two blocks of two, 1 state + 2 joint steps each (measured: K 0.13 %, M 0.11 % off).  Still
    moving at the noise's scale of clean markers, the blocks disagree by far more than their error
    bars (measured chi-square 237 over 59), and the combined fit says so and gives none."""
    path, rec, truth = floorless
    start = dataclasses.replace(truth, stiffness=truth.stiffness * 1.03,
                                mass=truth.mass * (1 + 0.03 * np.array([1, -1, 1, -1, 1, -1])))
    m = refine_recording(rec, path, start, total_mass=float(truth.mass.sum()),
                         config=MarkerRefineConfig(windows=4, frames=10, step=0.005, state_iterations=1, iterations=2,
                                                   blocks=2))
    oe = m.metrics["output_error"]
    assert oe["windows"] == 4 and oe["blocks"]["windows"] == [2, 2] and len(oe["cost_per_residual"]) == 2
    assert m.mass.sum() == pytest.approx(truth.mass.sum(), rel=1e-12)
    assert np.abs(m.stiffness / truth.stiffness - 1).max() < 0.005
    assert np.abs(m.mass / truth.mass - 1).max() < 0.005
    assert oe["blocks"]["agreement_dof"] == 59 and oe["blocks"]["agreement_p"] < 1e-3
    assert "2 blocks of windows disagree" in m.metrics["warnings"][-1] and np.isnan(m.stderr["mass"]).all()
