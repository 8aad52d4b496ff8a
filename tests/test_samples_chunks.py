"""The slabs the regression's rows are built in (:func:`identified.samples.iter_chunks`): an
episode longer than a slab is cut into pieces, and a last piece too short for one weak-form window
joins the piece before it (it made the fit fail: "episodes of 4 steps are shorter than the
weak-form window"); where the last piece holds a window, the slabs are as they were."""

from __future__ import annotations

import numpy as np

from identified.fit.identify import ScaleSpec, identify
from identified.samples import _spans
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, collect

from .test_record_output_error import _robot, _truth


def _steps(spans):
    return [(e.start, t.start, t.stop) for e, t in spans]


def test_a_short_last_piece_joins_the_one_before():
    assert _steps(_spans(2, 4100, 4096, "forward")) == [(0, 0, 4096), (0, 4096, 4100), (1, 0, 4096), (1, 4096, 4100)]
    assert _steps(_spans(2, 4100, 4096, "forward", min_steps=30)) == [(0, 0, 4100), (1, 0, 4100)]
    assert _steps(_spans(1, 4127, 4096, "central", min_steps=30)) == [(0, 1, 4097), (0, 4097, 4127)]
    assert _steps(_spans(1, 4126, 4096, "central", min_steps=30)) == [(0, 1, 4126)]
    # the published recordings' takes (10 s at 1 ms): a last piece of 1808 holds every window, as before
    assert _steps(_spans(1, 10000, 4096, "forward", min_steps=270)) == [(0, 0, 4096), (0, 4096, 8192), (0, 8192, 10000)]
    # several short episodes per slab: unchanged
    assert _steps(_spans(5, 1000, 4096, "forward", min_steps=30)) == [(0, 0, 1000), (4, 0, 1000)]


def test_the_weak_form_fits_episodes_a_little_longer_than_a_slab(tmp_path):
    """Two clean episodes of 205 steps of the robot without its ground, in slabs of 100 with
    windows of 30: the fit runs, and on its exact equations it recovers the plant's K, c, M."""
    path = _robot(tmp_path, floor=False)
    data = collect(path, CollectConfig(episodes=2, steps=205, seed=4))
    truth = _truth(path)
    model = identify(data, Topology.from_mjcf(path), scale=ScaleSpec(total_mass=float(truth.mass.sum())),
                     weak_window=30, chunk_steps=100)
    for key in ("stiffness", "damping", "mass"):
        np.testing.assert_allclose(getattr(model, key), getattr(truth, key), rtol=1e-6)
