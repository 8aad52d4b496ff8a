"""TensegrityIco-v0: API conformance, determinism, reward bookkeeping, and that the env depends on
the backend only through rod states and rest lengths."""

from __future__ import annotations

import sys
import textwrap
import warnings

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the env)
from tensegrity_gym.backends import Backend, MotorSpec, RodState, make_backend
from tensegrity_gym.backends.mujoco_backend import default_robot_xml
from tensegrity_gym.envs.tensegrity_ico_v0 import (
    TensegrityIcoEnv,
    action_to_rest,
    observation,
    observation_names,
    perturb_start,
    rest_to_action,
    structure_com,
)
from tests._render import render_in_subprocess

R, A = 6, 24


# ---------------------------------------------------------------------- a fake backend
class FakeBackend(Backend):
    """A scripted backend: rods in a known pose; each step moves every rod by ``drift`` per
    substep (or returns NaN states after ``nan_after`` steps). Records what the env sent."""

    name = "fake"

    def __init__(self, n_rods: int = 3, n_tendons: int = 4, drift=(0.01, 0.0, 0.0), z: float = 0.7,
                 nan_after: int | None = None) -> None:
        self.rod_names = tuple(f"rod{i}" for i in range(n_rods))
        self.tendon_names = tuple(f"cable{i}" for i in range(n_tendons))
        self.actuated_names = ("cable3", "cable1")  # not in tendon order, on purpose
        self.motor = MotorSpec(self.actuated_names, 0.5, np.array([0.5, 0.6]), np.array([1.5, 1.2]))
        self.drift, self.z, self.nan_after = np.asarray(drift, float), z, nan_after
        self.targets: list[np.ndarray] = []
        self.substeps: list[int] = []

    @property
    def dt(self) -> float:
        return 0.001

    def nominal_states(self) -> RodState:
        n = len(self.rod_names)
        pos = np.stack([np.arange(n, dtype=float), np.zeros(n), np.full(n, self.z)], axis=1)
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        return RodState(pos, quat, np.zeros((n, 3)), np.zeros((n, 3)))

    def nominal_rest_lengths(self) -> np.ndarray:
        return np.array([1.0, 0.9, 1.1, 1.0])

    def reset(self, states: RodState, rest_lengths: np.ndarray) -> None:
        self._s, self._rest, self._n = states.copy(), np.array(rest_lengths, float), 0

    def step(self, target_rest, n_substeps, push_force=None, push_point=None) -> None:
        self.targets.append(np.array(target_rest))
        self.substeps.append(n_substeps)
        self._n += 1
        self._s = self._s._replace(pos=self._s.pos + n_substeps * self.drift)
        self._s.vel[:] = self.drift / self.dt
        self._rest[self.actuated_index] = target_rest  # an infinitely fast motor

    def states(self) -> RodState:
        if self.nan_after is not None and self._n > self.nan_after:
            s = self._s.copy()
            s.pos[0, 0] = np.nan
            return s
        return self._s.copy()

    def rest_lengths(self) -> np.ndarray:
        return self._rest.copy()


def rollout(env: gym.Env, seed: int, n: int, action_seed: int = 0):
    rng = np.random.default_rng(action_seed)
    obs, _ = env.reset(seed=seed)
    out, rewards = [obs], []
    for _ in range(n):
        obs, r, _, _, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        out.append(obs)
        rewards.append(r)
    return np.array(out), np.array(rewards)


@pytest.fixture(scope="module")
def env():
    e = TensegrityIcoEnv()
    yield e
    e.close()


# ---------------------------------------------------------------------- API conformance
# Unbounded observations are deliberate (velocities have no hard bound; Ant-v5 does the same),
# and Gymnasium's checker always mentions them; every other warning of a checker is a failure.
_INF_BOUNDS = "observation space m"  # "... minimum/maximum value is -infinity/infinity"


def _checker_warnings(record) -> list[str]:
    return [str(w.message) for w in record if _INF_BOUNDS not in str(w.message)]


def test_gymnasium_check_env():
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        check_env(TensegrityIcoEnv(), skip_render_check=True)
    assert _checker_warnings(record) == []


def test_sb3_check_env():
    from stable_baselines3.common.env_checker import check_env

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        check_env(TensegrityIcoEnv(), warn=True)
    assert _checker_warnings(record) == []


@pytest.mark.parametrize("env_id", ["TensegrityIco-v0", "tensegrity_gym:TensegrityIco-v0"])
def test_registration(env_id):
    e = gym.make(env_id)
    assert e.spec.max_episode_steps == 1000
    assert isinstance(e.unwrapped, TensegrityIcoEnv)
    assert e.action_space.shape == (A,) and e.action_space.dtype == np.float32
    assert e.observation_space.shape == (1 + 18 * R + A,) and e.observation_space.dtype == np.float32
    assert e.unwrapped.dt == pytest.approx(0.02) and e.metadata["render_fps"] == 50
    e.reset(seed=0)
    _, reward, terminated, truncated, info = e.step(e.action_space.sample())
    assert truncated is False and terminated is False and np.isfinite(reward)
    keys = ("x_position", "y_position", "x_velocity", "y_velocity", "com", "reward_forward", "reward_ctrl")
    for key in keys:
        assert key in info
    e.close()


def test_make_kwargs_reach_the_env():
    e = gym.make("TensegrityIco-v0", frame_skip=10, ctrl_cost_weight=0.5,
                 exclude_current_positions_from_observation=False, backend_kwargs={"integrator": "rk4"})
    u = e.unwrapped
    assert u.dt == pytest.approx(0.01) and u.ctrl_cost_weight == 0.5
    assert e.observation_space.shape == (3 + 18 * R + A,)
    obs, info = e.reset(seed=1)
    np.testing.assert_allclose(obs[:2], [info["x_position"], info["y_position"]], atol=1e-6)
    import mujoco

    assert u.backend.plant.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4


def test_model_from_a_file(tmp_path):
    path = tmp_path / "robot.xml"
    path.write_text(default_robot_xml())
    e = gym.make("TensegrityIco-v0", model=str(path))
    o_file, _ = e.reset(seed=4)
    o_default, _ = gym.make("TensegrityIco-v0").reset(seed=4)
    np.testing.assert_array_equal(o_file, o_default)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="unknown backend 'nope'"):
        TensegrityIcoEnv(backend="nope")
    with pytest.raises(ValueError, match="frame_skip"):
        TensegrityIcoEnv(backend=FakeBackend(), frame_skip=0)
    with pytest.raises(ValueError, match="render_mode"):
        TensegrityIcoEnv(backend=FakeBackend(), render_mode="video")
    e = TensegrityIcoEnv(backend=FakeBackend())
    with pytest.raises(gym.error.ResetNeeded):
        e.step(np.zeros(2, np.float32))
    e.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        e.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="finite"):
        e.step(np.array([np.nan, 0.0], np.float32))


# ---------------------------------------------------------------------- determinism
def test_same_seed_same_trajectory(env):
    o1, r1 = rollout(env, seed=7, n=25)
    o2, r2 = rollout(env, seed=7, n=25)  # the same env again
    fresh = TensegrityIcoEnv()
    o3, r3 = rollout(fresh, seed=7, n=25)  # a new env
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(o1, o3)
    np.testing.assert_array_equal(r1, r3)
    assert np.abs(o1[-1] - o1[0]).max() > 1e-3  # it did move


def test_different_seeds_differ(env):
    a, _ = env.reset(seed=1)
    b, _ = env.reset(seed=2)
    assert np.abs(a - b).max() > 1e-4
    # and the noise is what reset_noise_scale says: none at 0
    quiet = TensegrityIcoEnv(reset_noise_scale=0.0)
    q1, _ = quiet.reset(seed=1)
    q2, _ = quiet.reset(seed=2)
    np.testing.assert_array_equal(q1, q2)
    b = quiet.backend
    expected = observation(b.nominal_states(), b.nominal_rest_lengths(), b.actuated_index,
                           b.motor.rest_min, b.motor.rest_max)
    np.testing.assert_allclose(q1, expected.astype(np.float32), rtol=0, atol=1e-6)


def test_reset_noise_is_uniform_and_bounded():
    nominal = FakeBackend(n_rods=50).nominal_states()
    s = perturb_start(nominal, np.random.default_rng(0), 0.02)
    d = s.pos - nominal.pos
    assert np.abs(d).max() <= 0.02 and np.abs(d).max() > 0.015 and np.abs(s.vel).max() <= 0.02
    np.testing.assert_allclose(np.linalg.norm(s.quat, axis=1), 1.0, atol=1e-12)
    # rotation angle <= |rotvec| <= sqrt(3) * scale
    angle = 2 * np.arccos(np.clip(np.abs(s.quat[:, 0]), 0, 1))
    assert angle.max() <= np.sqrt(3) * 0.02 + 1e-12 and angle.max() > 0


# ---------------------------------------------------------------------- reward
def test_reward_is_sum_of_terms(env):
    env.reset(seed=3)
    rng = np.random.default_rng(3)
    x_before = structure_com(env.backend.states())[0]
    for _ in range(15):
        a = rng.uniform(-1, 1, A).astype(np.float32)
        _, reward, _, _, info = env.step(a)
        assert reward == pytest.approx(info["reward_forward"] + info["reward_ctrl"], rel=1e-12, abs=1e-12)
        x_after = structure_com(env.backend.states())[0]
        assert info["x_velocity"] == pytest.approx((x_after - x_before) / env.dt, rel=1e-9, abs=1e-12)
        assert info["reward_forward"] == pytest.approx(env.forward_reward_weight * info["x_velocity"])
        ctrl = -env.ctrl_cost_weight * float(np.sum(a.astype(float) ** 2))
        assert info["reward_ctrl"] == pytest.approx(ctrl)
        assert info["x_position"] == pytest.approx(x_after)
        x_before = x_after


def test_reward_with_known_motion():
    # FakeBackend moves every rod +0.01 m in x per substep: 0.2 m per 20-substep step = 10 m/s
    e = TensegrityIcoEnv(backend=FakeBackend(), forward_reward_weight=2.0, ctrl_cost_weight=0.1)
    e.reset(seed=0)
    _, reward, _, _, info = e.step(np.array([1.0, -0.5], np.float32))
    assert info["x_velocity"] == pytest.approx(10.0)
    assert info["reward_forward"] == pytest.approx(20.0)
    assert info["reward_ctrl"] == pytest.approx(-0.1 * 1.25)
    assert reward == pytest.approx(20.0 - 0.125)
    assert e.backend.substeps == [20]


# ---------------------------------------------------------------------- observation from states alone
def test_observation_is_the_pure_function_of_backend_states(env):
    env.reset(seed=5)
    rng = np.random.default_rng(5)
    b = env.backend
    for _ in range(5):
        obs, *_ = env.step(rng.uniform(-1, 1, A).astype(np.float32))
        expected = observation(b.states(), b.rest_lengths(), b.actuated_index,
                               b.motor.rest_min, b.motor.rest_max)
        np.testing.assert_array_equal(obs, expected.astype(np.float32))


def test_observation_of_known_states():
    fb = FakeBackend(n_rods=3, drift=(0.0, 0.0, 0.0), z=0.7)
    e = TensegrityIcoEnv(backend=fb, reset_noise_scale=0.0, terminate_when_unhealthy=False)
    obs, _ = e.reset(seed=0)
    names = observation_names(fb.rod_names, fb.actuated_names)
    assert len(names) == obs.size == 1 + 18 * 3 + 2 == e.observation_space.shape[0]
    o = dict(zip(names, obs.tolist()))
    assert o["z_com"] == pytest.approx(0.7)
    # rods at x = 0, 1, 2: relative to the centre x = 1
    assert [o[f"rod{i}_rel_x"] for i in range(3)] == pytest.approx([-1.0, 0.0, 1.0])
    assert o["rod1_rel_y"] == pytest.approx(0.0, abs=1e-12)
    assert o["rod2_rel_z"] == pytest.approx(0.0, abs=1e-12)
    # identity orientation
    assert [o[f"rod0_R{i}{j}"] for i in range(3) for j in range(3)] == pytest.approx(np.eye(3).ravel())
    # rest lengths of cable3 = 1.0 in [0.5, 1.5] -> 0.0; cable1 = 0.9 in [0.6, 1.2] -> 0.0
    assert o["cable3_rest"] == pytest.approx(0.0) and o["cable1_rest"] == pytest.approx(0.0)

    # a rotated rod: 90 degrees about z maps body x to world y
    s = fb.nominal_states()
    s.quat[2] = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]
    s.vel[1] = [0.1, 0.2, 0.3]
    s.angvel[0] = [-1.0, 0.0, 2.0]
    fb.reset(s, fb.nominal_rest_lengths())
    v = dict(zip(names, observation(fb.states(), fb.rest_lengths(), fb.actuated_index,
                                    fb.motor.rest_min, fb.motor.rest_max).tolist()))
    rot = np.array([[v[f"rod2_R{i}{j}"] for j in range(3)] for i in range(3)])
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert [v[f"rod1_vel_{c}"] for c in "xyz"] == pytest.approx([0.1, 0.2, 0.3])
    assert [v[f"rod0_angvel_{c}"] for c in "xyz"] == pytest.approx([-1.0, 0.0, 2.0])

    # after a step the env's observation follows the new states and the new rest lengths
    obs, *_ = e.step(np.array([1.0, -1.0], np.float32))
    o = dict(zip(names, obs.tolist()))
    assert o["cable3_rest"] == pytest.approx(1.0) and o["cable1_rest"] == pytest.approx(-1.0)


# ---------------------------------------------------------------------- actions
def test_action_scaling():
    lo, hi = np.array([0.5, 0.6]), np.array([1.5, 1.2])
    np.testing.assert_allclose(action_to_rest(-np.ones(2), lo, hi), lo)
    np.testing.assert_allclose(action_to_rest(np.ones(2), lo, hi), hi)
    np.testing.assert_allclose(action_to_rest(np.zeros(2), lo, hi), (lo + hi) / 2)
    np.testing.assert_allclose(action_to_rest(np.array([-7.0, 3.0]), lo, hi), [0.5, 1.2])  # clipped
    a = np.array([-0.3, 0.8])
    np.testing.assert_allclose(rest_to_action(action_to_rest(a, lo, hi), lo, hi), a)

    fb = FakeBackend()
    e = TensegrityIcoEnv(backend=fb)
    e.reset(seed=0)
    e.step(-np.ones(2, np.float32))
    e.step(np.ones(2, np.float32))
    np.testing.assert_allclose(fb.targets[0], fb.motor.rest_min)
    np.testing.assert_allclose(fb.targets[1], fb.motor.rest_max)


def test_action_scaling_on_the_plant(env):
    env.reset(seed=0)
    plant = env.backend.plant
    env.step(-np.ones(A, np.float32))
    np.testing.assert_allclose(plant.targets, plant.motor.rest_min)
    env.step(np.ones(A, np.float32))
    np.testing.assert_allclose(plant.targets, plant.motor.rest_max)
    # the motors move the actual rest lengths toward the target at their speed limit
    before = env.backend.rest_lengths()[env.actuated_index]
    env.step(np.ones(A, np.float32))
    moved = env.backend.rest_lengths()[env.actuated_index] - before
    np.testing.assert_allclose(moved, plant.motor.speed * env.dt, rtol=1e-9)


# ---------------------------------------------------------------------- termination
def test_non_finite_state_terminates_with_finite_observation():
    fb = FakeBackend(nan_after=1)
    e = TensegrityIcoEnv(backend=fb)
    e.reset(seed=0)
    obs1, _, term1, _, info1 = e.step(np.zeros(2, np.float32))
    assert not term1 and "termination_reason" not in info1
    obs2, r2, term2, trunc2, info2 = e.step(np.zeros(2, np.float32))
    assert term2 and not trunc2 and info2["termination_reason"] == "non-finite state"
    assert np.all(np.isfinite(obs2)) and np.isfinite(r2)
    np.testing.assert_array_equal(obs2, obs1)  # the last finite observation
    assert info2["reward_forward"] == 0.0
    assert r2 == pytest.approx(info2["reward_forward"] + info2["reward_ctrl"])
    assert all(np.all(np.isfinite(v)) for v in info2.values() if not isinstance(v, str))


def test_plant_divergence_terminates(env):
    env.reset(seed=0)
    s = env.backend.states()
    s.vel[0] = 1e11  # beyond MuJoCo's limit: it warns and resets its data
    env.backend.plant.set_states(s)
    obs, reward, terminated, _, info = env.step(np.zeros(A, np.float32))
    assert terminated and info["termination_reason"] == "non-finite state"
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    obs, *_ = env.reset(seed=0)  # and reset recovers
    assert np.all(np.isfinite(env.backend.states().pos))


def test_collapse_terminates_when_unhealthy():
    e = TensegrityIcoEnv(backend=FakeBackend(z=0.2, drift=(0, 0, 0)))
    e.reset(seed=0)
    *_, terminated, _, info = e.step(np.zeros(2, np.float32))
    assert terminated and info["termination_reason"] == "collapsed"
    e = TensegrityIcoEnv(backend=FakeBackend(z=0.2, drift=(0, 0, 0)), terminate_when_unhealthy=False)
    e.reset(seed=0)
    *_, terminated, _, info = e.step(np.zeros(2, np.float32))
    assert not terminated and "termination_reason" not in info


def test_plant_collapses_with_slack_cables(env):
    # all cables at their longest go slack: the robot falls flat, which the env reports
    env.reset(seed=0)
    for _ in range(150):
        *_, terminated, _, info = env.step(np.ones(A, np.float32))
        if terminated:
            break
    assert terminated and info["termination_reason"] == "collapsed"
    assert info["com_height"] < env.healthy_z_range[0]


# ---------------------------------------------------------------------- rendering
_RENDER_SCRIPT = textwrap.dedent(
    """
    import json, numpy as np, gymnasium as gym, tensegrity_gym
    from tensegrity_gym.backends.mujoco_backend import MujocoBackend, default_robot_xml
    try:
        env = gym.make("TensegrityIco-v0", render_mode="rgb_array", width=160, height=120)
        env.reset(seed=0)
        img = env.render()
    except RuntimeError as exc:
        if "offscreen rendering is not available" in str(exc):
            print(json.dumps({"unavailable": str(exc)})); raise SystemExit(0)
        raise
    for _ in range(3):
        env.step(env.action_space.sample())
    img2 = env.render()

    # the twin's route: a non-MuJoCo backend draws its rod states through drawing_model()
    class Twin(MujocoBackend):
        name = "twin-like"
        def render(self, *a, **k):
            from tensegrity_gym.backends.base import Backend
            return Backend.render(self, *a, **k)
    twin = gym.make("TensegrityIco-v0", backend=Twin(), render_mode="rgb_array", width=160, height=120)
    twin.reset(seed=0)
    img3 = twin.render()
    print(json.dumps({"shape": list(img.shape), "dtype": str(img.dtype), "std": float(img.std()),
                      "shape2": list(img2.shape), "moved": float(np.abs(img2.astype(int) - img).mean()),
                      "shape3": list(img3.shape), "std3": float(img3.std()),
                      "same_as_plant": float(np.abs(img3.astype(int) - img).mean())}))
    """
)


def test_render_rgb_array():
    r = render_in_subprocess(_RENDER_SCRIPT)
    assert r["shape"] == [120, 160, 3] and r["dtype"] == "uint8" and r["std"] > 5.0
    assert r["shape2"] == [120, 160, 3] and r["moved"] > 0.0
    # drawing rod states in a MuJoCo model (the twin's hook) gives the plant's picture
    assert r["shape3"] == [120, 160, 3] and r["std3"] > 5.0 and r["same_as_plant"] < 1.0


def test_human_render_without_display_is_a_clear_error(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the headless check is Linux-specific")
    e = TensegrityIcoEnv(render_mode="human")
    with pytest.raises(RuntimeError, match="needs a display"):
        e.reset(seed=0)


def test_make_backend_by_name():
    b = make_backend("mujoco", default_robot_xml())
    assert b.name == "mujoco" and b.motor.n == A and len(b.rod_names) == R
    assert b.dt == pytest.approx(0.001)
    np.testing.assert_array_equal(b.actuated_index, np.arange(A))


def test_backend_step_with_a_push():
    b = make_backend("mujoco")
    hold = b.nominal_rest_lengths()[b.actuated_index]
    b.reset(b.nominal_states(), b.nominal_rest_lengths())
    b.step(hold, 10)
    still = b.states()
    b.reset(b.nominal_states(), b.nominal_rest_lengths())
    force = np.zeros((R, 3))
    force[1, 0] = 100.0  # N, +x on rod1 (an upper rod, off the ground) at its centre, for 10 ms
    b.step(hold, 10, push_force=force)
    pushed = b.states()
    # the impulse, 1 N s, is the momentum the structure gains (the ground takes a little)
    momentum = (b.plant.masses[:, None] * (pushed.vel - still.vel)).sum(axis=0)
    np.testing.assert_allclose(momentum, [1.0, 0.0, 0.0], atol=0.05)
    assert 0.2 < pushed.vel[1, 0] - still.vel[1, 0] < 1.0 / 3.5  # most of it in the pushed rod
    with pytest.raises(ValueError, match="push_force"):
        b.step(hold, 1, push_force=np.zeros((R + 1, 3)))
