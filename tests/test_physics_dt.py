"""The twin integrated at a coarser step (``physics_dt``): the same physics as a model whose ``dt``
is that step, the env's control period unchanged, bad values refused in the option's words."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from identified.model import load_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend, coarsening, default_model_path

EAGER64 = {"compile": False, "dtype": "float64"}


def _rollout(env: gym.Env, steps: int, seed: int = 3) -> np.ndarray:
    """Observations of ``steps`` env steps under seeded random actions."""
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        obs, *_ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        out.append(obs)
    return np.array(out)


def test_coarsening_whole_multiples_only() -> None:
    assert coarsening(None, 0.001) == 1
    assert coarsening(0.001, 0.001) == 1
    assert coarsening(0.004, 0.001) == 4
    assert coarsening(0.003, 0.001) == 3  # 0.003 / 0.001 is 2.9999999999999996 in floating point
    for bad in (0.0015, 0.0, -0.002, float("nan"), float("inf"), "fast"):
        with pytest.raises(ValueError, match="physics_dt"):
            coarsening(bad, 0.001)  # type: ignore[arg-type]


def test_coarse_twin_is_the_model_at_that_step() -> None:
    """physics_dt = 2 dt with 20 physics steps a control period is, to the bit, the model with
    dt = 2 ms stepped 10 times (the same engine, motors and pushes); the period stays 20 ms."""
    m = load_model(default_model_path())
    coarse = gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=100,
                      backend_kwargs={**EAGER64, "physics_dt": 2 * m.dt})
    b = coarse.unwrapped.backend
    assert (b.coarsening, b.dt, b.physics_dt) == (2, m.dt, 2 * m.dt)
    assert coarse.unwrapped.dt == pytest.approx(0.02, abs=1e-15)
    slow = gym.make("TensegrityIco-v0", max_episode_steps=100, frame_skip=10,
                    backend=IdentifiedBackend(dataclasses.replace(m, dt=2 * m.dt), **EAGER64))
    a, c = _rollout(coarse, 8), _rollout(slow, 8)
    np.testing.assert_array_equal(a, c)
    fine = _rollout(gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=100,
                             backend_kwargs=EAGER64), 8)
    gap = np.abs(a - fine).max()
    assert 1e-6 < gap < 0.5  # a different integration of the same physics, not another system


def test_physics_dt_of_the_model_changes_nothing() -> None:
    m = load_model(default_model_path())
    a = _rollout(gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=100,
                          backend_kwargs={**EAGER64, "physics_dt": m.dt}), 5)
    b = _rollout(gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=100,
                          backend_kwargs=EAGER64), 5)
    np.testing.assert_array_equal(a, b)


def test_batched_coarse_twin_agrees_with_single() -> None:
    m = load_model(default_model_path())
    kw = {**EAGER64, "physics_dt": 4 * m.dt}
    venv = gym.make_vec("TensegrityIco-v0", num_envs=2, vectorization_mode="vector_entry_point",
                        backend="identified", max_episode_steps=100, backend_kwargs=kw)
    single = gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=100, backend_kwargs=kw)
    venv.reset(seed=[5, 6])
    single.reset(seed=6)
    rng = np.random.default_rng(0)
    for _ in range(4):
        act = rng.uniform(-1, 1, venv.action_space.shape).astype(np.float32)
        obs, *_ = venv.step(act)
        one, *_ = single.step(act[1])
    np.testing.assert_allclose(obs[1], one, rtol=0, atol=1e-9)


def test_period_not_divisible_is_refused() -> None:
    m = load_model(default_model_path())
    with pytest.raises(ValueError, match="frame_skip must be a multiple of 4"):
        gym.make("TensegrityIco-v0", backend="identified", frame_skip=10,
                 backend_kwargs={**EAGER64, "physics_dt": 4 * m.dt})


@pytest.mark.parametrize("extra, words", [
    (["--physics-dt", "0.0015"], "--physics-dt 0.0015: physics_dt must be a whole multiple"),
    (["--physics-dt", "0.003"], "--physics-dt 0.003: 3 physics steps of the model do not divide"),
    (["--physics-dt", "0.002", "--plant"], "--physics-dt sets the twin's integration step"),
    (["--physics-dt", "fast"], "--physics-dt fast: give 'auto' or a step in seconds"),
])
def test_cli_refuses_bad_physics_dt(tmp_path, extra: list[str], words: str) -> None:
    out = tmp_path / "p.zip"
    r = subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", "train", "--identified", default_model_path(),
                        "--timesteps", "64", "--out", str(out), *extra], check=False, capture_output=True,
                       text=True)
    assert r.returncode != 0
    assert words in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()
