"""The Cramér-Rao bound (identified.fit.bound) against linear-Gaussian problems whose bound is known
in closed form: y_w = A_w x_w + B_w θ + σ ε, a nuisance x_w per window, θ shared."""

from __future__ import annotations

import numpy as np
import pytest

from identified.fit.bound import constrained_bound, window_gradient, window_information


def _toy(seed: int = 0, W: int = 6, m: int = 9, nx: int = 3, P: int = 4):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(W, m, nx)), rng.normal(size=(W, m, P))


def _joint_inverse(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The θ block of the inverse of the joint information of (x_1 .. x_W, θ): the textbook bound
    with every nuisance estimated jointly."""
    W, m, nx = A.shape
    X = np.zeros((W * m, W * nx + B.shape[2]))
    for w in range(W):
        X[w * m:(w + 1) * m, w * nx:(w + 1) * nx] = A[w]
        X[w * m:(w + 1) * m, W * nx:] = B[w]
    return np.linalg.inv(X.T @ X)[W * nx:, W * nx:]


def test_schur_information_equals_the_joint_bound():
    """Eliminating each window's nuisance by projection gives the joint inverse's θ block; the
    information without the elimination (the planted bug) is larger, its bound too small."""
    A, B = _toy()
    sigma = 0.01
    F = window_information(A / sigma, B / sigma)
    want = sigma ** 2 * _joint_inverse(A, B)
    np.testing.assert_allclose(np.linalg.inv(F), want, rtol=1e-9)
    naive = sum(b.T @ b for b in B) / sigma ** 2  # nuisances known: not this problem's bound
    assert np.max(np.abs(np.linalg.inv(naive) - want) / np.abs(want).max()) > 0.05
    cr = constrained_bound(F, [f"p{i}" for i in range(4)], np.ones(4))
    np.testing.assert_allclose(cr.rel_se, np.sqrt(np.diag(want)), rtol=1e-9)
    assert cr.finite.all()


def test_profiled_gradient_steps_to_the_joint_least_squares_solution():
    """Linear windows, residuals ``r = y - A x - B θ`` at an arbitrary point: ``θ - F⁻¹ g`` with the
    nuisances eliminated is the joint least-squares θ exactly (the nuisances never stepped); the
    gradient without the projection (the planted bug) lands elsewhere."""
    A, B = _toy(3)
    W, m, nx = A.shape
    rng = np.random.default_rng(5)
    y = rng.normal(size=(W, m))
    X = np.zeros((W * m, W * nx + 4))
    for w in range(W):
        X[w * m:(w + 1) * m, w * nx:(w + 1) * nx] = A[w]
        X[w * m:(w + 1) * m, W * nx:] = B[w]
    best = np.linalg.lstsq(X, y.ravel(), rcond=None)[0][W * nx:]
    x, theta = rng.normal(size=(W, nx)), rng.normal(size=4)
    r = y - np.einsum("wmn,wn->wm", A, x) - B @ theta
    # the residual's Jacobians are -A, -B; the step is -F⁻¹ g with g = Σ Jpᵀ (I - P) r
    g = window_gradient(-A, -B, r)
    np.testing.assert_allclose(theta - np.linalg.solve(window_information(A, B), g), best, rtol=1e-9, atol=1e-12)
    naive = sum(-b.T @ rw for b, rw in zip(B, r))
    assert np.abs(theta - np.linalg.solve(window_information(A, B), naive) - best).max() > 1e-3


def test_least_squares_attains_the_bound():
    """Monte Carlo: the joint least-squares estimate of θ (efficient in a linear-Gaussian problem)
    scatters as the bound says (4000 draws: the variances within 10 %)."""
    A, B = _toy(1)
    sigma, theta = 0.5, np.array([1.0, -2.0, 0.5, 3.0])
    cov = np.linalg.inv(window_information(A / sigma, B / sigma))
    rng = np.random.default_rng(2)
    W, m, nx = A.shape
    X = np.zeros((W * m, W * nx + 4))
    for w in range(W):
        X[w * m:(w + 1) * m, w * nx:(w + 1) * nx] = A[w]
        X[w * m:(w + 1) * m, W * nx:] = B[w]
    x = rng.normal(size=W * nx)
    y0 = X @ np.concatenate([x, theta])
    Y = y0[:, None] + sigma * rng.normal(size=(W * m, 4000))
    est = np.linalg.lstsq(X, Y, rcond=None)[0][W * nx:]
    np.testing.assert_allclose(np.var(est, axis=1, ddof=1), np.diag(cov), rtol=0.1)


def test_rank_deficient_nuisance_and_a_blind_parameter():
    """A nuisance column no residual sees projects nothing out (the bound as without it); a
    parameter no residual sees has no bound (not identifiable), and the others keep theirs."""
    A, B = _toy(3)
    F = window_information(A, B)
    A0 = np.concatenate([A, np.zeros(A.shape[:2] + (1,))], axis=2)
    np.testing.assert_allclose(window_information(A0, B), F, rtol=1e-10)
    B0 = np.concatenate([B, np.zeros(B.shape[:2] + (1,))], axis=2)
    cr = constrained_bound(window_information(A, B0), list("abcde"), np.ones(5))
    assert not cr.finite[4] and np.isinf(cr.rel_se[4])
    assert "not identifiable" in cr.describe(4)
    np.testing.assert_allclose(cr.rel_se[:4], np.sqrt(np.diag(np.linalg.inv(F))), rtol=1e-9)
    assert cr.identifiable(max_rel=np.inf)[:4].all()


def test_constrained_bound_with_a_gauge():
    """The global scale of the marker problem: θ -> θ + t 1 leaves every residual unchanged
    (information singular along 1); a known linear combination w·θ (the total mass) fixes it.
    The bound equals the bordered (KKT) inverse's block, and is zero along the constraint."""
    A, B = _toy(4)
    B = B - B.mean(axis=2, keepdims=True)  # every residual blind to the all-ones direction
    F = window_information(A, B)
    assert np.abs(F @ np.ones(4)).max() < 1e-9
    w = np.array([0.0, 0.0, 0.3, 0.7])
    cr = constrained_bound(F, list("abcd"), np.ones(4), constraints=w[None])
    kkt = np.linalg.inv(np.block([[F, w[:, None]], [w[None], np.zeros((1, 1))]]))[:4, :4]
    np.testing.assert_allclose(cr.cov, kkt, rtol=1e-8, atol=1e-12)
    assert cr.finite.all()
    assert abs(w @ cr.cov @ w) < 1e-12
    unconstrained = constrained_bound(F, list("abcd"), np.ones(4))
    assert not unconstrained.finite.any()  # every parameter moves along the gauge


def test_bad_shapes_are_one_clear_line():
    A, B = _toy()
    with pytest.raises(ValueError, match="want"):
        window_information(A[0], B[0])
    with pytest.raises(ValueError, match="sizes differ"):
        constrained_bound(np.eye(3), ["a", "b"], np.ones(3))
