"""Quaternion helpers (identified.rotation) against scipy's Rotation, w-x-y-z."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from identified.rotation import (
    matrix_apply,
    matrix_apply_transpose,
    quat_conjugate,
    quat_exp,
    quat_integrate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_rotate_inverse,
    quat_to_matrix,
)

N = 64


def _rand_quats(seed: int, n: int = N) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_quat(scalar_first=True)


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.array(x), dtype=torch.float64)


def _same_rotation(q1: np.ndarray, q2: np.ndarray, tol: float = 1e-13) -> None:
    """Quaternions equal up to the double cover (q ~ -q)."""
    sign = np.sign(np.sum(q1 * q2, axis=-1, keepdims=True))
    np.testing.assert_allclose(q1, sign * q2, atol=tol, rtol=0)


def test_to_matrix_matches_scipy():
    q = _rand_quats(0)
    np.testing.assert_allclose(quat_to_matrix(_t(q)).numpy(), Rotation.from_quat(q, scalar_first=True).as_matrix(),
                               atol=1e-14, rtol=0)


def test_to_matrix_of_non_unit_quaternion_is_that_of_the_normalised_one():
    q = _rand_quats(1)
    scaled = q * np.random.default_rng(1).uniform(0.5, 2.0, (N, 1))
    np.testing.assert_allclose(quat_to_matrix(_t(scaled)).numpy(), quat_to_matrix(_t(q)).numpy(), atol=1e-14, rtol=0)


def test_multiply_composes_rotations_like_scipy():
    q1, q2 = _rand_quats(2), _rand_quats(3)
    ours = quat_multiply(_t(q1), _t(q2)).numpy()
    ref = (Rotation.from_quat(q1, scalar_first=True) * Rotation.from_quat(q2, scalar_first=True)).as_quat(
        scalar_first=True)
    _same_rotation(ours, ref)
    # Hamilton product: R(q1 ⊗ q2) = R(q1) R(q2)
    np.testing.assert_allclose(quat_to_matrix(_t(ours)).numpy(),
                               quat_to_matrix(_t(q1)).numpy() @ quat_to_matrix(_t(q2)).numpy(), atol=1e-14)


def test_conjugate_is_inverse():
    q = _rand_quats(4)
    ours = quat_conjugate(_t(q)).numpy()
    _same_rotation(ours, Rotation.from_quat(q, scalar_first=True).inv().as_quat(scalar_first=True))
    ident = quat_multiply(_t(q), _t(ours)).numpy()
    _same_rotation(ident, np.tile([1.0, 0, 0, 0], (N, 1)))


def test_rotate_and_inverse_rotate_match_scipy():
    q = _rand_quats(5)
    v = np.random.default_rng(5).normal(size=(N, 3))
    rot = Rotation.from_quat(q, scalar_first=True)
    np.testing.assert_allclose(quat_rotate(_t(q), _t(v)).numpy(), rot.apply(v), atol=1e-14)
    np.testing.assert_allclose(quat_rotate_inverse(_t(q), _t(v)).numpy(), rot.inv().apply(v), atol=1e-14)
    m = quat_to_matrix(_t(q))
    np.testing.assert_allclose(matrix_apply(m, _t(v)).numpy(), rot.apply(v), atol=1e-14)
    np.testing.assert_allclose(matrix_apply_transpose(m, _t(v)).numpy(), rot.inv().apply(v), atol=1e-14)


def test_normalize():
    q = np.random.default_rng(6).normal(size=(N, 4)) * 3
    n = quat_normalize(_t(q)).numpy()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(n, q / np.linalg.norm(q, axis=-1, keepdims=True), atol=1e-15)
    assert torch.isnan(quat_normalize(torch.zeros(4, dtype=torch.float64))).all()  # no exception


@pytest.mark.parametrize("scale", [3.0, 1e-3, 1e-7, 0.0])
def test_exp_matches_scipy_rotvec(scale):
    theta = np.random.default_rng(7).normal(size=(N, 3)) * scale
    ours = quat_exp(_t(theta)).numpy()
    np.testing.assert_allclose(np.linalg.norm(ours, axis=-1), 1.0, atol=1e-15)
    _same_rotation(ours, Rotation.from_rotvec(theta).as_quat(scalar_first=True), tol=1e-15)


def test_exp_is_continuous_and_differentiable_at_zero():
    for theta0 in (torch.zeros(3), torch.full((3,), 1e-8), torch.tensor([1e-4, -2e-4, 3e-4]), torch.tensor([0.7, -0.2, 1.1])):
        theta = theta0.to(torch.float64).requires_grad_(True)
        assert torch.autograd.gradcheck(quat_exp, (theta,), eps=1e-6, atol=1e-9)
        assert torch.autograd.gradgradcheck(quat_exp, (theta,), eps=1e-6, atol=1e-7)
    # the derivative at 0 is d/dθ (cos(|θ|/2), θ/2) = [0; I/2]
    jac = torch.autograd.functional.jacobian(quat_exp, torch.zeros(3, dtype=torch.float64))
    np.testing.assert_allclose(jac.numpy(), np.vstack([np.zeros(3), 0.5 * np.eye(3)]), atol=1e-15)


def test_integrate_is_body_frame_exponential_then_normalise():
    q = _rand_quats(8)
    rng = np.random.default_rng(8)
    w_b = rng.normal(size=(N, 3)) * 5
    dt = 1e-2
    ours = quat_integrate(_t(q), _t(w_b), dt).numpy()
    ref = (Rotation.from_quat(q, scalar_first=True) * Rotation.from_rotvec(w_b * dt)).as_quat(scalar_first=True)
    _same_rotation(ours, ref)
    np.testing.assert_allclose(np.linalg.norm(ours, axis=-1), 1.0, atol=1e-15)
    # zero angular velocity keeps the orientation (and normalises)
    np.testing.assert_allclose(quat_integrate(_t(2 * q), torch.zeros(N, 3, dtype=torch.float64), dt).numpy(), q,
                               atol=1e-15)


def test_float32_and_broadcasting():
    q = torch.as_tensor(_rand_quats(9, 6), dtype=torch.float32).reshape(2, 3, 4)
    v = torch.randn(3, 3)  # broadcasts over the leading 2
    out = quat_rotate(q, v)
    assert out.dtype == torch.float32 and out.shape == (2, 3, 3)
    ref = Rotation.from_quat(q.reshape(-1, 4).double().numpy(), scalar_first=True).apply(
        np.tile(v.double().numpy(), (2, 1)))
    np.testing.assert_allclose(out.reshape(-1, 3).numpy(), ref, atol=1e-5)
    assert quat_exp(torch.zeros(3, dtype=torch.float32)).dtype == torch.float32
