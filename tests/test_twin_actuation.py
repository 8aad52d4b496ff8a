"""The batched twin with only some cables actuated: the motors move those cables' rest lengths
and no other, the engine steps with them in their places (an explicit loop of motor steps and
engine steps is the truth), and targets are clipped into the motors' bounds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from identified.twin import engine_from_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend
from tensegrity_gym.backends.twin_physics import TwinPhysics
from tensegrity_gym.cables import MotorSpec, motor_step

ACT = np.array([2, 5, 11, 17, 23])  # 5 of the robot's 24 cables, not the first ones


@pytest.fixture(scope="module")
def backend():
    return IdentifiedBackend(None, dtype="float64", compile=False)


def _subset_motor(b: IdentifiedBackend) -> MotorSpec:
    m = b.motor
    return MotorSpec(tuple(m.names[i] for i in ACT), m.speed, m.rest_min[ACT], m.rest_max[ACT])


@pytest.mark.parametrize("batch", [None, 3])
def test_only_the_actuated_cables_move_and_the_engine_sees_them(backend, batch):
    b = backend
    motor = _subset_motor(b)
    engine = engine_from_model(b.model)
    ph = TwinPhysics(engine, motor, ACT, batch=batch, compile=False)
    s0 = b.nominal_states()
    rest0 = b.nominal_rest_lengths() * (1.0 + 0.02 * np.arange(24) / 24)  # every cable its own
    shape = () if batch is None else (batch,)
    tile = lambda x: np.broadcast_to(x, shape + np.shape(x)).copy()
    ph.reset(tile(s0.pos), tile(s0.quat), tile(s0.vel), tile(s0.angvel), tile(rest0))
    rng = np.random.default_rng(2)
    target = motor.rest_min + rng.uniform(0, 1, shape + (len(ACT),)) * (motor.rest_max - motor.rest_min)
    ph.set_targets(target)
    n = 40
    ph.step(n)
    # the truth: n times (motors on the actuated cables, then one engine step)
    state = engine.state(tile(s0.pos), tile(s0.quat), tile(s0.vel), tile(s0.angvel))
    rest = torch.as_tensor(tile(rest0))
    act = torch.as_tensor(ACT)
    lo, hi = torch.as_tensor(motor.rest_min), torch.as_tensor(motor.rest_max)
    tgt = torch.as_tensor(target)
    with torch.no_grad():
        for _ in range(n):
            ra = motor_step(rest[..., act], tgt, motor.speed, engine.dt, lo, hi)
            rest = rest.clone()
            rest[..., act] = ra
            state = engine.step(state, rest)
    got_rest = ph.rest_numpy()
    np.testing.assert_allclose(got_rest, rest.numpy(), rtol=0, atol=1e-12)
    others = np.setdiff1d(np.arange(engine.n_springs), ACT)
    assert np.array_equal(got_rest[..., others], tile(rest0)[..., others])  # unactuated: untouched
    moved = np.abs(got_rest[..., ACT] - tile(rest0)[..., ACT])
    assert moved.max() > 0.5 * motor.speed * engine.dt * n  # the motors did move
    assert np.all(moved <= motor.speed * engine.dt * n * (1 + 1e-12))  # at their speed at most
    pos, quat, vel, angvel = ph.states_numpy()
    np.testing.assert_allclose(pos, state.pos.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(vel, state.vel.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(quat, state.quat.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(angvel, state.angvel.numpy(), rtol=0, atol=1e-8)


def test_targets_are_clipped_into_the_motor_bounds(backend):
    b = backend
    motor = _subset_motor(b)
    ph = TwinPhysics(engine_from_model(b.model), motor, ACT, batch=2, compile=False)
    ph.set_targets(np.stack([motor.rest_min - 1.0, motor.rest_max + 1.0]))
    assert np.array_equal(ph.target.numpy(), np.stack([motor.rest_min, motor.rest_max]))
