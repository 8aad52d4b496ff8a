"""Frames where a camera's clock puts them (:func:`identified.fit.output_error.marker_windows`,
:func:`~identified.fit.output_error.frame_weights`): a recording stamped ``k / 30`` s (off the
engine's 1 ms steps) or with a jittering clock is cut into windows, every window of it, and at
the truth, from the plant's own states, the windows reproduce its clean markers to rounding,
through the ground's contacts; windows of 10 frames at 30 Hz on the 1 ms grid (33, 33 and 34 ms
apart) are all kept."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from identified.effects.pyramid_contact import PyramidContact
from identified.fit.output_error import frame_weights, window_grid, window_problem
from identified.recording import RecordingError, site_world_positions
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model

from .test_pyramid_contact import TRUTH
from .test_record_output_error import _truth

HELD = [(i, 2) for i in range(6)]  # end caps on the rods' axes: the axial spin is not seen


def test_frame_weights_and_grid_exact():
    """A frame 33.3 steps from its window's start is read 0.7 from step 33 and 0.3 from 34; one on
    a step from that step alone.  The grid passes through the frames that every window has on the
    same step (30 Hz windows of 10 frames on the 1 ms grid: each third frame, 100 ms apart) and
    cuts the rest into steps of at most ``substeps``."""
    at = np.array([[0.0, 33.3, 66.0], [0.0, 33.0, 66.0]])
    reads = dict(frame_weights(at, np.arange(67)))
    assert sorted(reads) == [0, 33, 34, 66]
    (l0, w0), = reads[0]
    assert l0 == 0 and w0.flatten().tolist() == [1.0, 1.0]
    (l33, w33), = reads[33]
    np.testing.assert_allclose(w33.flatten().numpy(), [0.7, 1.0], rtol=0, atol=1e-12)
    (l34, w34), = reads[34]
    np.testing.assert_allclose(w34.flatten().numpy(), [0.3, 0.0], rtol=0, atol=1e-12)
    assert l33 == l34 == 1 and reads[66][0][0] == 2
    tens = np.array([[0, 33, 67, 100, 133, 167, 200, 233, 267, 300],
                     [0, 33, 67, 100, 133, 167, 200, 233, 267, 300],
                     [0, 33, 66, 100, 133, 166, 200, 233, 266, 300],
                     [0, 34, 67, 100, 134, 167, 200, 234, 267, 300]], dtype=float)
    np.testing.assert_array_equal(window_grid(tens, 5, 300), np.arange(0, 301, 5))
    np.testing.assert_array_equal(window_grid(tens[:2], 5, 300)[:9], [0, 5, 10, 15, 20, 25, 29, 33, 38])
    np.testing.assert_array_equal(window_grid(tens, 1, 300), np.arange(301))
    g = window_grid(np.array([[0.4, 33.7], [0.9, 34.2]]), 4, 35)
    np.testing.assert_array_equal(g, [0, 4, 8, 12, 16, 20, 24, 28, 32, 35])


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """The robot on its ground, 1.2 s of random commands; its clean markers at every 1 ms step, and
    its recording at 30 Hz on the 1 ms grid."""
    torch.set_num_threads(1)
    path = str(tmp_path_factory.mktemp("wf") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=1, steps=1200, seed=5))
    rec = record_markers(data, path, RecordConfig(rate=30, noise_pos=0.0, dropout=0.0), seed=5)
    truth = _truth(path)
    sites = tuple(s for r in truth.topology.rods for s in r.sites)
    every = site_world_positions(truth.topology, data.pos[0], data.quat[0], sites)  # (T + 1, N, 3)
    law = PyramidContact.for_system(truth.topology, path)
    law.values = TRUTH.copy()
    return path, data, rec, truth, every, law


def _at_times(rec, every: np.ndarray, t: np.ndarray):
    """The recording with frames at the times ``t`` (s), the markers the plant's, linear between
    its 1 ms steps (the encoders' rest lengths come from ``data`` here, not from the file)."""
    n = t / 1e-3
    i = np.minimum(np.floor(n).astype(int), every.shape[0] - 2)
    f = (n - i)[:, None, None]
    m = (1 - f) * every[i] + f * every[i + 1]
    rows = np.zeros(t.size, dtype=int)
    return replace(rec, time=t, episode=np.zeros(t.size, dtype=int), markers=m, rest=rec.rest[rows],
                   ctrl=rec.ctrl[rows], length=rec.length[rows], lines=None)


def _rms(prob, dx) -> float:
    with torch.no_grad():
        return float(prob.residuals(prob.theta0, dx).square().mean().sqrt())


@pytest.mark.parametrize("clock", ["k/30", "jitter"])
def test_frames_off_the_steps_reproduce_the_plant(plant, clock):
    """Frames at ``k / 30`` s exactly, or 30 Hz with a clock that jitters by up to 3 ms: every window
    of 9 frames is cut (4 of 36 frames; the first and last are stepped), and at the truth, from the
    plant's own states, they leave the plant's markers at rounding (the windows on the grid do:
    3e-11 m); the same frames read at the nearest step (the time rounded to the step) are off by
    the motion over half a step."""
    path, data, rec, truth, every, law = plant
    t = np.arange(36) / 30
    if clock == "jitter":
        t = t + np.random.default_rng(1).uniform(-3e-3, 3e-3, t.size) * (np.arange(36) > 0)
    off = _at_times(rec, every, t)
    win, available, prob, dx, _ = window_problem(truth, off, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=2,
                                                 contact=law)
    assert available == 4 and win.n_windows == 2
    assert not np.allclose(win.at.numpy(), np.round(win.at.numpy()))  # the frames between the steps
    assert _rms(prob, dx) * 1e-3 < 1e-8
    # at 5 ms steps (the Jacobians') the windows miss by the coarse step's own error, as those of the
    # same frames on the grid do (measured: 1.333 and 1.330 mm), not more
    _, _, ongrid, dxg, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=2,
                                          contact=law)
    assert 0.9 < _rms(prob.at_step(5), dx) / _rms(ongrid.at_step(5), dxg) < 1.1
    snapped = replace(off, time=np.round(t, 3))
    _, _, near, dxn, _ = window_problem(truth, snapped, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=2,
                                        contact=law)
    assert _rms(near, dxn) * 1e-3 > 1e-5  # (measured: 0.11 and 0.09 mm)


def test_ten_frames_at_30_hz_keep_every_window(plant):
    """30 Hz on the 1 ms grid: frames 33, 33 and 34 ms apart, so windows of 10 frames start at three
    patterns of spacing.  Every one is cut (3 of the 36 frames' windows), each frame at its own
    step, and they reproduce the plant's markers at rounding.  Their 5 ms grid passes through the
    frames all three share (every third, 100 ms apart), and a window alone is stepped on it too."""
    path, data, rec, truth, _, law = plant
    win, available, prob, dx, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=10, contact=law)
    assert available == win.n_windows == 3
    at = win.at.numpy()
    assert np.array_equal(at, np.round(at)) and len({tuple(a) for a in at.tolist()}) == 3
    assert _rms(prob, dx) * 1e-3 < 1e-8
    coarse = prob.at_step(5)
    np.testing.assert_array_equal(coarse.grid, np.arange(0, 301, 5))
    # a window alone is stepped on the whole set's grid: its residuals are its rows of theirs, bit for bit
    whole = coarse.window_residuals(prob.theta0, dx)
    one = coarse.window_residuals(prob.theta0, dx[1:2], torch.tensor([1]))
    assert torch.equal(one, whole[1:2])


def test_windows_longer_than_the_takes_are_one_clear_line(plant):
    """Windows of more frames than any take holds: the file, the window's frames and the longest
    take's, not "no rod off the ground"."""
    path, data, rec, truth, _, law = plant
    with pytest.raises(RecordingError, match=r"windows of 100 frames do not fit in its takes \(the longest has 36 frames\)"):
        window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=100, contact=law)


def test_times_counted_from_an_epoch_fall_on_the_same_steps(plant):
    """A lab's clock counts from an epoch (1.7e9 s: its float64 times are rounded to 2.4e-7 s, a
    fraction 2.4e-4 of a step): the frames on the steps stay on them, the windows and their
    residuals those of the same recording counted from 0, bit for bit."""
    path, data, rec, truth, _, law = plant
    epoch = 1_732_900_000.0
    late = replace(rec, time=rec.time + epoch)
    assert not np.array_equal(late.time - epoch, rec.time)  # the rounding is there
    a = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=9, max_windows=2, contact=law)
    b = window_problem(truth, late, data, [epoch], path, 1e-3, HELD, frames=9, max_windows=2, contact=law)
    assert torch.equal(a[0].at, b[0].at) and torch.equal(a[0].x0, b[0].x0)
    assert torch.equal(a[2].window_residuals(a[2].theta0, a[3]), b[2].window_residuals(b[2].theta0, b[3]))
