"""Training's bookkeeping on hand-made numbers (no PPO run): the rollout size with envs that do not
divide it, and the forward progress it reports per episode (x velocity times dt, summed over the
episode, reset when the episode ends)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tensegrity_gym.training import PPO_HYPERPARAMETERS, TrainConfig, _make_callback


@pytest.mark.parametrize(("envs", "rollout", "timesteps", "n_steps"), [
    (3, 1000, 10_000, 334),   # 1000 / 3 rounded up: at least the rollout
    (64, 4096, 100_000, 64),  # divides
    (7, 4096, 100, 15),       # a run shorter than one rollout: one rollout of its length, rounded up
    (5, 10, 10_000, 2),
])
def test_rollout_is_rounded_up_to_a_multiple_of_the_envs(envs, rollout, timesteps, n_steps):
    hp = TrainConfig(timesteps=timesteps, envs=envs, rollout=rollout).algo_kwargs()
    assert hp["n_steps"] == n_steps
    assert hp["n_steps"] * envs >= min(rollout, timesteps) > (hp["n_steps"] - 1) * envs
    assert hp["batch_size"] == min(PPO_HYPERPARAMETERS["batch_size"], n_steps * envs)


def test_sac_buffer_and_learning_starts_follow_a_short_run():
    hp = TrainConfig(timesteps=500, algo="sac", envs=2).algo_kwargs()
    assert hp["buffer_size"] == 500 and hp["learning_starts"] <= 50


def test_reported_progress_is_x_velocity_times_dt_per_episode(tmp_path):
    dt = 0.05
    cfg = TrainConfig(timesteps=100, envs=2)
    cb = _make_callback(cfg, dt, str(tmp_path / "P.zip"), dict, progress=False)
    cb.model = SimpleNamespace(get_env=lambda: SimpleNamespace())  # an env without VecNormalize
    vx = [[1.0, 2.0], [3.0, -1.0], [0.5, 4.0], [2.0, 2.0], [-1.0, 1.0]]
    done = [[False, False], [False, True], [True, False], [False, False], [False, True]]
    for v, d in zip(vx, done):
        infos = [{"x_velocity": v[i], "y_velocity": 100.0 + v[i], "episode": {"r": 10.0 * v[i], "l": 7}}
                 for i in range(2)]
        if d[0]:  # an episode end without a Monitor record: counted, no return
            del infos[0]["episode"]
        cb.locals = {"infos": infos, "dones": np.array(d), "rewards": np.array(v)}
        assert cb._on_step() is True
    # env 1 ends at steps 1 and 4, env 0 at step 2, in this order
    want = [(2.0 - 1.0) * dt, (1.0 + 3.0 + 0.5) * dt, (4.0 + 2.0 + 1.0) * dt]
    assert list(cb.progress) == pytest.approx(want, rel=1e-12)
    assert list(cb.returns) == [-10.0, 10.0] and cb.episodes == 3
    assert cb._dist.tolist() == pytest.approx([(2.0 - 1.0) * dt, 0.0], rel=1e-12)  # episodes under way
    # the learning curve's rows: the same progress, the Monitor's return and length where it has them
    assert [row["progress_m"] for row in cb.log] == pytest.approx(want, rel=1e-12)
    assert [row["length"] for row in cb.log] == [7, -1, 7]
