"""The windows' reduced (Schur-complement) system (identified.fit.window_solve) against the full
stacked normal equations solved densely: windows w with their own nuisances x_w, parameters p shared."""

from __future__ import annotations

import numpy as np
import torch

from identified.fit.bound import window_information
from identified.fit.window_solve import window_schur


def _stacked(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The full normal matrix of (x_1 .. x_W, p): block-diagonal A_w, cross blocks B_w, C."""
    W, nx, P = B.shape
    N = np.zeros((W * nx + P, W * nx + P))
    for w in range(W):
        N[w * nx:(w + 1) * nx, w * nx:(w + 1) * nx] = A[w]
        N[w * nx:(w + 1) * nx, W * nx:] = B[w]
        N[W * nx:, w * nx:(w + 1) * nx] = B[w].T
    N[W * nx:, W * nx:] = C
    return N


def test_reduced_step_and_back_substitution_solve_the_stacked_system():
    """The parameter step from the reduced system and every window's back-substituted nuisance step
    equal the dense solution of the stacked normal equations (each window's normal matrix with a
    damping diagonal added, as the fits add); the Schur complement is the inverse of the stacked
    inverse's parameter block; without a diagonal it is the windows' information of
    identified.fit.bound.  A dropped ``B_wᵀ A_w⁻¹ B_w`` (the planted bug) misses the solution."""
    rng = np.random.default_rng(0)
    W, m, nx, P = 5, 14, 4, 3
    Jx, Jp, r = rng.normal(size=(W, m, nx)), rng.normal(size=(W, m, P)), rng.normal(size=(W, m))
    A = Jx.transpose(0, 2, 1) @ Jx + np.stack([np.diag(d) for d in rng.uniform(0.1, 1.0, (W, nx))])
    B = Jx.transpose(0, 2, 1) @ Jp
    C = (Jp.transpose(0, 2, 1) @ Jp).sum(0)
    gx = Jx.transpose(0, 2, 1) @ r[..., None]  # (W, nx, 1)
    gp = (Jp.transpose(0, 2, 1) @ r[..., None]).sum(0)  # (P, 1)
    N = _stacked(A, B, C)
    want = np.linalg.solve(N, -np.concatenate([gx.reshape(-1), gp[:, 0]]))

    t = torch.as_tensor
    sc = window_schur(t(A), t(B), t(C))
    Aig, gs = sc.reduce(t(gx), t(gp))
    dp = -torch.linalg.solve(sc.S, gs)
    dx = sc.back_substitute(Aig, dp)
    scale = np.abs(want).max()
    np.testing.assert_allclose(dp.numpy()[:, 0], want[W * nx:], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(dx.numpy().reshape(-1), want[:W * nx], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(np.linalg.inv(sc.S.numpy()), np.linalg.inv(N)[W * nx:, W * nx:], rtol=1e-10)
    assert torch.equal(sc.S, sc.S.T)

    plain = window_schur(t(Jx.transpose(0, 2, 1) @ Jx), t(B), t(C))  # A_w = J_xᵀ J_x: the information
    np.testing.assert_allclose(plain.S.numpy(), window_information(Jx, Jp), rtol=1e-10, atol=1e-12 * np.abs(C).max())

    bug = -np.linalg.solve(C, gs.numpy())  # the parameters' block without the windows' elimination
    assert np.abs(bug[:, 0] - want[W * nx:]).max() > 1e-2 * scale
