"""The gap's figures on hand-made episodes (no policy, no physics): forward progress per episode,
the plant/twin and plant/random ratios, and the open-loop divergence of the centres of mass."""

from __future__ import annotations

import numpy as np
import pytest

from tensegrity_gym.gap import EpisodeSet, against_line, open_loop_divergence, run_episodes, transfer_ratios


class _Line:
    """K sub-envs moving along x by their action's first component per step; sub-env k ends
    (terminated) after ``ends[k]`` steps; reset puts it at x = 10 k."""

    def __init__(self, ends: list[int]) -> None:
        self.num_envs = len(ends)
        self.ends = np.array(ends)
        self.single_action_space = type("S", (), {"shape": (2,)})()

    def reset(self, seed=None):
        self.x = 10.0 * np.arange(self.num_envs)
        self.t = np.zeros(self.num_envs, dtype=int)
        return np.zeros((self.num_envs, 3)), self._info()

    def _info(self):
        return {"x_position": self.x.copy(), "com": [np.array([x, 0.0, 1.0]) for x in self.x]}

    def step(self, a):
        self.x = self.x + a[:, 0]
        self.t += 1
        term = self.t >= self.ends
        return np.zeros((self.num_envs, 3)), a[:, 0] * 2.0, term, np.zeros(self.num_envs, bool), self._info()


def test_run_episodes_progress_returns_and_lengths():
    env = _Line([3, 5])
    acts = iter([[0.5, 0.1], [1.0, -1.0], [0.2, 0.0], [-0.3, 0.3], [0.7, 0.7]])
    rows = [np.array([[a[0], 0.0], [a[1], 0.0]], dtype=np.float32) for a in acts]
    it = iter(rows)
    out = run_episodes(env, lambda obs: next(it), seeds=[4, 5])
    # env 0: steps 1-3 (0.5 + 1.0 + 0.2), env 1: steps 1-5 (0.1 - 1.0 + 0.0 + 0.3 + 0.7)
    assert out.progress.tolist() == pytest.approx([1.7, 0.1], abs=1e-6)
    assert out.returns.tolist() == pytest.approx([3.4, 0.2], abs=1e-6)
    assert out.lengths.tolist() == [3, 5]
    assert [len(c) for c in out.com] == [4, 6] and out.com[1][0].tolist() == [10.0, 0.0, 1.0]
    s = out.summary()
    assert s["progress_m"] == pytest.approx(0.9, abs=1e-6) and s["episodes"] == 2


def test_open_loop_actions_end_an_episode_at_nan():
    env = _Line([10, 10])
    actions = np.zeros((2, 4, 2))
    actions[:, :, 0] = [[1.0, 1.0, 1.0, 1.0], [2.0, 2.0, np.nan, 1.0]]
    out = run_episodes(env, lambda obs: None, seeds=[0, 1], actions=actions)
    assert out.lengths.tolist() == [4, 2] and out.progress.tolist() == pytest.approx([4.0, 4.0])


def _summary(progress):
    n = len(progress)
    return EpisodeSet(list(range(n)), np.zeros(n), np.asarray(progress, float), np.ones(n, int), [], [],
                      np.zeros(n, bool)).summary()


def test_transfer_ratios_are_plant_over_twin_and_over_random():
    twin, plant, rnd = _summary([0.8, 0.4]), _summary([0.3, 0.3]), _summary([0.1, -0.05])
    out = transfer_ratios(twin, plant, rnd)
    assert out["plant_over_twin"] == pytest.approx(0.5) and out["plant_over_random"] == pytest.approx(12.0)
    # delta method: the plant's episodes agree (0 spread), the twin's mean 0.6 has a standard error
    # of 0.2 (sample std 0.2828 / sqrt 2): 0.5 x 0.2 / 0.6
    assert out["plant_over_twin_stderr"] == pytest.approx(0.5 * 0.2 / 0.6, rel=1e-12)
    both = transfer_ratios(twin, _summary([0.2, 0.4]), rnd)  # and the plant's: 0.5 sqrt((0.1/0.3)^2 + (0.2/0.6)^2)
    assert both["plant_over_twin_stderr"] == pytest.approx(0.5 * np.sqrt(2) / 3, rel=1e-12)
    assert transfer_ratios(_summary([0.0]), plant, _summary([-0.1])) == {"plant_over_twin": None,
                                                                        "plant_over_twin_stderr": None,
                                                                        "plant_over_random": None}
    assert transfer_ratios(_summary([0.5]), _summary([0.4]), rnd)["plant_over_twin_stderr"] is None  # one episode


def test_open_loop_divergence_by_hand():
    dt = 0.5
    com = lambda xs: np.array([[x, 0.0, 0.0] for x in xs])
    plant = EpisodeSet([0, 1], np.zeros(2), np.zeros(2), np.array([4, 2]), [], [com([0, 1, 2, 3, 4]), com([0, 1, 2])],
                       np.zeros(2, bool))
    twin = EpisodeSet([0, 1], np.zeros(2), np.zeros(2), np.array([4, 2]), [],
                      [com([0, 1, 2.5, 3.5, 5]), com([0, 1.5, 100.0])], np.array([False, True]))
    out = open_loop_divergence(plant, twin, dt)
    # instant 1: both episodes (0 and 0.5); instant 2: the twin's episode 1 diverged there (its last
    # state is not a state): episode 0 only
    assert out["com_divergence_m"] == pytest.approx([0.0, 0.25, 0.5, 0.5, 1.0])
    assert out["at"]["1s"] == pytest.approx(0.5) and out["at"]["5s"] is None
    assert out["time_to_0.1m_s"] == pytest.approx(0.5) and out["time_to_0.5m_s"] == pytest.approx(2.0)
    assert out["final_m"] == pytest.approx(1.0) and out["mean_m"] == pytest.approx(0.45)


def test_a_ratio_is_under_the_line_only_beyond_its_standard_errors():
    # 0.80 + 2 x 0.04 = 0.88 < 0.9: under beyond the noise; 0.80 + 2 x 0.06 = 0.92: within it
    assert against_line(0.80, 0.04) == "under"
    assert against_line(0.80, 0.06) == "within noise"
    assert against_line(0.80, 0.05, z=1.0) == "under" and against_line(0.80, 0.05) == "within noise"
    assert against_line(0.90, 0.50) == "met" and against_line(1.3, None) == "met"
    assert against_line(0.2, None) == "within noise"  # no error bar: the data cannot tell
    assert against_line(None, 0.1) is None
    assert against_line(0.45, 0.02, line=0.5) == "under" and against_line(0.45, 0.03, line=0.5) == "within noise"
