"""The twin beside the plant: ``side_by_side`` puts the frames next to each other, pixel for pixel."""

from __future__ import annotations

import numpy as np

from tensegrity_gym.gap import side_by_side


def test_side_by_side_frames_and_the_shorter_episode_holding_its_last_frame():
    rng = np.random.default_rng(0)
    left = [rng.integers(0, 255, (5, 6, 3), dtype=np.uint8) for _ in range(3)]
    right = [rng.integers(0, 255, (5, 6, 3), dtype=np.uint8) for _ in range(5)]
    out = side_by_side(left, right, gap=2)
    assert len(out) == 5 and all(f.shape == (5, 6 + 2 + 6, 3) and f.dtype == np.uint8 for f in out)
    for k, f in enumerate(out):
        np.testing.assert_array_equal(f[:, :6], left[min(k, 2)])
        np.testing.assert_array_equal(f[:, 6:8], 255)
        np.testing.assert_array_equal(f[:, 8:], right[k])
