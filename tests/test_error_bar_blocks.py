"""Error bars from few independent runs: the cluster jackknife over consecutive blocks cut within
each run (identified.fit.uncertainty), exactly."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from identified.fit.identify import run_blocks, shortest_cut_run, shortest_cut_take
from identified.fit.regression import accumulate
from identified.fit.uncertainty import LinearSolve, block_slices, blocks_per_run, covariance


class _Columns:
    """One rod whose every equation block uses all ``L`` columns (a stand-in for RodColumns)."""

    def __init__(self, L: int) -> None:
        self.full = np.arange(L)[None]

    def block_columns(self, rod: int, rotation: bool) -> np.ndarray:
        return np.arange(self.full.shape[1])


def test_block_slices_are_contiguous_and_in_order():
    assert block_slices(10, 3) == [slice(0, 4), slice(4, 7), slice(7, 10)]
    assert block_slices(8, 1) == [slice(0, 8)]
    with pytest.raises(ValueError):
        block_slices(3, 4)


def test_blocks_per_run_makes_ten_blocks_of_the_least_length():
    assert blocks_per_run(6, 50, 17) == 2  # 12 blocks of 25 rows
    assert blocks_per_run(4, 50, 16) == 3  # 12 blocks of 16-17 rows
    assert blocks_per_run(3, 50, 17) == 1  # 4 blocks of 12 rows would be too short: no cut
    assert blocks_per_run(10, 50, 17) == 1  # enough independent runs already
    assert blocks_per_run(1, 200, 17) == 10


def test_run_blocks_of_recordings():
    """6 takes of 4 s at the engine's 1 ms step, windows of 301 steps (stride 75): 50 rows a take, a
    block at least max(1 s, 4 windows) = 1204 steps = 17 rows: two blocks of 2 s a take."""
    takes = lambda E, T: SimpleNamespace(n_episodes=E, n_steps=T, dt=0.001)
    cut = run_blocks(takes(6, 4000), 4096, "forward", 301)
    assert cut == {"blocks": 2, "clusters": "12 blocks of 2 s cut within 6 independent runs (episodes; fewer than 10)"}
    assert run_blocks(takes(2, 2000), 4096, "forward", 301)["blocks"] == 1  # 23 rows a take: too short
    assert run_blocks(takes(10, 4000), 4096, "forward", 301)["blocks"] == 1
    # a take longer than the chunks is already cut at them: 3 runs of 4096 steps and one of 1808
    assert run_blocks(takes(1, 14096), 4096, "forward", 301)["blocks"] == 1  # 1808 steps: 21 rows, 1 block
    # the shortest takes the warning asks for are the shortest that are cut
    for n in (2, 3, 6):
        need = shortest_cut_run(n, 0.001, 301)
        assert run_blocks(takes(n, need), 10**6, "forward", 301)["blocks"] > 1
        assert run_blocks(takes(n, need - 1), 10**6, "forward", 301)["blocks"] == 1
    assert shortest_cut_run(6, 0.001, 301) == 33 * 75 + 301  # 2 blocks of 17 rows
    # 4 takes of 5 s: the chunks cut each at 4096 steps, and the 903-step rest is too short to cut
    assert run_blocks(takes(4, 4999), 4096, "forward", 301)["blocks"] == 1
    shortest = shortest_cut_take(4, 0.001, 301)
    assert shortest == shortest_cut_run(4, 0.001, 301) and shortest < 4096  # within one chunk: as before
    longer = shortest_cut_take(4, 0.001, 301, at_least=5000)
    assert run_blocks(takes(4, longer), 4096, "forward", 301)["blocks"] > 1
    assert run_blocks(takes(4, longer - 75), 4096, "forward", 301)["blocks"] == 1  # the shortest of them


def _rows(rng: np.random.Generator, runs: int, per: int, p: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[B, -y]`` of ``runs`` runs of ``per`` rows with ``theta = [1, 2, 3, 1]`` (last: the anchor);
    regressors and noise drift within each run, so that which rows make a block matters."""
    t = np.tile(np.linspace(0.0, 1.0, per), runs)[:, None]
    B = rng.normal(size=(runs * per, p)) * np.geomspace(1, 10, p) * (1 + 3 * t)
    y = B @ np.arange(1.0, p + 1) + rng.normal(0, 0.3, runs * per) * (0.2 + 4 * t[:, 0] ** 2)
    return B, y


def test_accumulate_cuts_each_run_into_consecutive_blocks():
    rng = np.random.default_rng(3)
    B, y = _rows(rng, 2, 11)
    X = np.column_stack([B, -y])
    A = torch.zeros(22, 1, 6, 4, dtype=torch.float64)
    A[:, 0, 0] = torch.as_tensor(X)
    f = accumulate([(A, 2)], _Columns(4), 4, blocks=3, clusters="6 blocks")
    want = [(0, 4), (4, 8), (8, 11), (11, 15), (15, 19), (19, 22)]
    assert len(f.cluster_R) == 6 and f.rows[0] == 22 and f.clusters == "6 blocks"
    for Rg, (a, b) in zip(f.cluster_R, want):
        np.testing.assert_allclose(Rg[0].T @ Rg[0], X[a:b].T @ X[a:b], rtol=1e-12, atol=1e-12)
    whole = accumulate([(A, 2)], _Columns(4), 4)
    assert len(whole.cluster_R) == 2 and whole.clusters == ""
    np.testing.assert_allclose(f.R[0].T @ f.R[0], whole.R[0].T @ whole.R[0], rtol=1e-12)


def test_few_runs_error_bars_are_the_jackknife_over_blocks():
    """3 runs cut into 4 blocks each: the covariance is (G-1)/G times the spread of the least-squares
    estimates refitted without each contiguous block, G = 12 -- to rounding."""
    rng = np.random.default_rng(4)
    runs, per, k, p = 3, 37, 4, 3
    B, y = _rows(rng, runs, per, p)
    A = torch.zeros(runs * per, 1, 6, p + 1, dtype=torch.float64)
    A[:, 0, 0] = torch.as_tensor(np.column_stack([B, -y]))
    f = accumulate([(A, runs)], _Columns(p + 1), p + 1, blocks=k, clusters="12 blocks of 3 runs")
    est = np.linalg.lstsq(B, y, rcond=None)[0]
    _U, s, Vt = np.linalg.svd(B, full_matrices=False)
    lin = LinearSolve(M=Vt.T / s, IK=None, singular_values=s, residual=0.0)
    cov, how = covariance(f, np.eye(p + 1), np.eye(p + 1)[:, :p], np.append(est, 1.0), np.ones(6), None, lin)
    assert how == "cluster-robust jackknife over 12 blocks of 3 runs"
    parts = [np.arange(g * per + b.start, g * per + b.stop) for g in range(runs) for b in block_slices(per, k)]
    loo = np.array([np.linalg.lstsq(np.delete(B, j, 0), np.delete(y, j), rcond=None)[0] for j in parts])
    d = loo - loo.mean(axis=0)
    want = (len(parts) - 1) / len(parts) * d.T @ d
    np.testing.assert_allclose(cov[:p, :p], want, rtol=1e-9, atol=1e-14 * np.abs(want).max())


def test_clean_fit_from_three_episodes_is_exact_with_error_bars_over_blocks():
    """3 clean episodes of 4 s: the error bars are the jackknife over 12 blocks of 1 s, and the fit
    stays exact (the merged factors are those of the whole runs)."""
    from identified.fit.identify import ScaleSpec, identify
    from identified.topology import Topology
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import build_model

    xml = build_model("simple", "paper")
    data = collect(xml, CollectConfig(episodes=3, steps=4000, seed=9))
    model = identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(masses=(("rod0", 10.0),)))
    assert model.metrics["stderr"] == ("cluster-robust jackknife over 12 blocks of 1 s cut within 3 independent "
                                       "runs (episodes; fewer than 10)")
    np.testing.assert_allclose(model.stiffness, 100.0, rtol=1e-10)
    np.testing.assert_allclose(model.damping, 10.0, rtol=1e-10)
    assert np.all(model.stderr["stiffness"] < 1e-8)
