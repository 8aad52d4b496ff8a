"""A recording's frame rate against the robot's own oscillations (identified.fit.sampling_rate):
what the frames cannot carry loses its error bar, never keeps one that does not cover the truth."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from identified.engine.integration import RodState
from identified.engine.stability import oscillation_frequencies
from identified.fit.sampling_rate import fastest_oscillation, withhold_unresolved
from identified.model import load_model
from identified.twin import engine_from_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend, default_model_path


@pytest.fixture(scope="module")
def shipped():
    return load_model(default_model_path())


def test_dampings_masses_and_inertias_lose_their_error_bars_below_twice_the_fastest_mode(shipped):
    m = copy.deepcopy(shipped)
    m.metrics = {"not_identifiable": ["rod0: held"], "warnings": []}
    k_se = np.array(m.stderr["stiffness"], dtype=float, copy=True)
    assert withhold_unresolved(m, rate_hz=10.0, fastest_hz=10.3)
    for key in ("damping", "mass", "inertia"):
        assert np.isnan(np.asarray(m.stderr[key], dtype=float)).all()
    np.testing.assert_array_equal(m.stderr["stiffness"], k_se)  # positions: the frames hold them
    np.testing.assert_array_equal(m.damping, shipped.damping)  # the values stay (the twin steps with them)
    assert len(m.metrics["not_identifiable"]) == 2 and len(m.metrics["warnings"]) == 1
    assert "10.3 Hz" in m.metrics["warnings"][0] and "20.6 Hz or more" in m.metrics["warnings"][0]


@pytest.mark.parametrize("rate", [30.0, 20.6])  # Nyquist 15 Hz, and exactly the fastest mode
def test_a_rate_that_resolves_the_modes_changes_nothing(shipped, rate):
    m = copy.deepcopy(shipped)
    before = {k: np.array(v, dtype=float, copy=True) for k, v in m.stderr.items() if k in ("damping", "mass")}
    assert not withhold_unresolved(m, rate_hz=rate, fastest_hz=10.3)
    for k, v in before.items():
        np.testing.assert_array_equal(m.stderr[k], v)
    assert "warnings" not in m.metrics or not any("oscillates" in w for w in m.metrics["warnings"])


def test_fastest_oscillation_is_the_largest_over_the_takes(shipped):
    """The shipped robot standing, and the same robot spinning in the second take: the fastest mode
    of either (each take's first state), the cable modes' ~10 Hz at the standing pose."""
    b = IdentifiedBackend(None)
    s = b.nominal_states()
    pos, quat = np.asarray(s.pos, float), np.asarray(s.quat, float)
    vel, ang = np.zeros_like(pos), np.zeros_like(pos)
    spun = ang + np.array([0.0, 0.0, 3.0])  # every rod turning about the vertical
    rest = np.asarray(b.nominal_rest_lengths(), float)
    data = SimpleNamespace(n_episodes=2, pos=np.stack([pos, pos])[:, None], quat=np.stack([quat, quat])[:, None],
                           vel=np.stack([vel, vel])[:, None], angvel=np.stack([ang, spun])[:, None],
                           rest_length=np.stack([rest, rest])[:, None])
    eng = engine_from_model(shipped)
    each = [oscillation_frequencies(eng, RodState(pos, quat, vel, w), rest).max() for w in (ang, spun)]
    assert each[1] > each[0] and fastest_oscillation(shipped, data) == each[1]  # the second take
    assert fastest_oscillation(shipped, data, takes=1) == each[0]
    assert 8.0 < each[0] < 12.0  # the robot's cable modes (10.2 Hz measured, 2026-11-27)
