"""Rod states reconstructed from a recording's markers, and the fit on them."""

from __future__ import annotations

import numpy as np
import pytest

from identified.fit.markers import states_from_recording
from identified.recording import RecordingError
from identified.rotation import quat_to_matrix
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("recfit") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=2, steps=2000, seed=6))
    return path, Topology.from_mjcf(path), data


def test_states_from_clean_markers(robot):
    """From clean 100 Hz markers with gaps: positions, axes and transverse spin of the plant's rods;
    no spin about an axis the markers cannot see."""
    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100, dropout=0.02), seed=1)
    ms = states_from_recording(rec, topo, dt=data.dt, lam=1e-12)  # clean: the splines interpolate
    rd = ms.data
    n = rd.n_steps
    assert ms.starts == [data.dt, data.dt]  # both takes start placed (no gap in the first frame)
    truth = data.select(steps=n + 1)
    pos_err = np.linalg.norm(rd.pos - truth.pos[:, 1:], axis=-1)
    assert np.median(pos_err) < 5e-6
    ax_true = quat_to_matrix(truth.quat[:, 1:])[..., :, 2]
    ax = quat_to_matrix(rd.quat)[..., :, 2]
    assert np.median(np.linalg.norm(ax - ax_true, axis=-1)) < 1e-5
    w = truth.angvel[:, 1:]
    perp = w - np.sum(w * ax_true, -1, keepdims=True) * ax_true
    assert np.median(np.linalg.norm(rd.angvel - perp, axis=-1)) < 0.02 * np.median(np.linalg.norm(perp, axis=-1))
    assert np.abs(np.sum(rd.angvel * ax, -1)).max() < 1e-8  # parallel transport: no axial spin
    assert ms.unobservable == [(i, 2) for i in range(6)]
    # the states step as the engine's Euler does: x[n+1] = x[n] + dt v[n+1]
    np.testing.assert_allclose(rd.pos[:, 1:], rd.pos[:, :-1] + data.dt * rd.vel[:, 1:], atol=1e-12)
    # rest lengths from the encoders, interpolated between frames
    assert np.abs(rd.rest_length - truth.rest_length[:, 1:]).max() < 2e-3


def test_missing_encoder_is_refused(robot):
    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=50), seed=1)
    from dataclasses import replace

    short = replace(rec, rest_names=rec.rest_names[1:], rest=rec.rest[:, 1:])
    with pytest.raises(RecordingError, match="no 'cable0.rest' column"):
        states_from_recording(short, topo)


@pytest.mark.expensive  # ~10-20 s; with the benchmarks (the suite's 10 minutes)
def test_axial_inertia_is_not_identifiable(robot):
    """A fit from end-cap markers holds every axial moment: null error bar, named in the metrics."""
    from identified.fit.identify import ScaleSpec
    from identified.fit.markers import fit_recording

    path, _, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100), seed=2)
    m = fit_recording(rec, path, effects=["ground_contact"], scale=ScaleSpec(total_mass=21.0), jobs=1)
    assert len(m.metrics["not_identifiable"]) == 6
    assert np.isnan(m.stderr["inertia"][:, 2]).all() and np.isfinite(m.stderr["inertia"][:, :2]).all()
    # two takes of 2 s: too short to cut into 10 blocks for the jackknife; the fit says its error bars are too small
    assert m.metrics["stderr"].startswith("iid rows")
    said = [w for w in m.metrics["warnings"] if w.startswith("only 2 take(s)")]
    assert said and "(record 10 takes, or takes of 8.2 s, for error bars that cover)" in said[0]  # a length that is cut
    from identified.fit.contact_damping import FACTORS

    assert m.metrics["recording"]["friction_damping"]["factor"] in FACTORS


@pytest.mark.expensive  # ~10-20 s; with the benchmarks (the suite's 10 minutes)
def test_friction_damping_from_short_free_runs(robot):
    """The contact law's friction damping chosen by the short free runs: a law fitted on the
    plant's full states with its beta_a, beta_p divided by 4 is scaled back by the factor whose
    free runs from those states err least (3-8: the free runs' best is near, not at, the least
    squares' value), well below the divided law's error, and its standard errors become null."""
    from identified.fit.contact_damping import refine_friction_damping
    from identified.fit.identify import ScaleSpec
    from identified.fit.pipeline import fit_model

    path, _, data = robot
    m = fit_model(data, path, effects=["ground_contact"], scale=ScaleSpec(total_mass=21.0), weak_window=None, jobs=1)
    law = m.effects[0]
    fitted = {k: law["parameters"][k] for k in ("beta_a", "beta_p")}
    law["parameters"].update({k: v / 4 for k, v in fitted.items()})
    out = refine_friction_damping(m, data)
    errors = out["errors"]
    assert errors[str(out["factor"])] == min(errors.values()), errors
    assert 3.0 <= out["factor"] <= 8.0 and errors["1.0"] > 1.2 * min(errors.values()), errors
    for k, v in fitted.items():
        assert law["parameters"][k] == pytest.approx(out["factor"] * v / 4, rel=1e-12)
        assert law["stderr"][k] is None


def test_noisy_markers_are_smoothed(robot):
    """1 mm of marker noise: the smoothing splines (GCV) place the rods better than one marker is placed."""
    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02), seed=3)
    ms = states_from_recording(rec, topo, dt=data.dt)
    rd = ms.data
    first = [round(t / data.dt) for t in ms.starts]  # a take starts where every rod is placed
    truth = np.stack([data.pos[e, f:f + rd.n_steps + 1] for e, f in enumerate(first)])
    err = np.linalg.norm(rd.pos - truth, axis=-1)
    assert np.median(err) < 0.7e-3  # one marker's error: median ~1.5 mm (3D)


def test_missing_markers_weigh_out_their_rods_steps(robot):
    """A rod's equations weigh 0 within GAP_FRAMES frames of a frame where one of its markers is
    missing, 1 from 2 x GAP_FRAMES frames on; other rods keep theirs.  The weights survive
    ``select`` and a save/load round trip."""
    from identified.dataset import load_dataset, save_dataset
    from identified.fit.markers import GAP_FRAMES

    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100), seed=1)
    hole = rec.markers.copy()
    f0 = 50  # frame 50 of the first take: rod 0's first marker missing for 3 frames
    hole[f0:f0 + 3, 0] = np.nan
    from dataclasses import replace

    ms = states_from_recording(replace(rec, markers=hole), topo, dt=data.dt, lam=1e-12)
    w = ms.data.weight
    assert w.shape == (2, ms.data.n_steps, 6)
    step = round(0.01 / data.dt)  # engine steps per frame
    first = round(ms.starts[0] / data.dt)  # the grid's instant 0 is the recording's step `first`
    t = np.arange(ms.data.n_steps) + first  # each instant in recording steps
    frame = t / step
    near = np.minimum(np.abs(frame - f0), np.abs(frame - (f0 + 2)))
    inside = (frame >= f0 - GAP_FRAMES) & (frame <= f0 + 2 + GAP_FRAMES - 1)
    assert np.all(w[0, inside, 0] == 0)
    assert np.all(w[0, near >= 2 * GAP_FRAMES + 1, 0] == 1)
    assert np.all(w[0, :, 1:] == 1) and np.all(w[1] == 1)
    assert np.all((w >= 0) & (w <= 1))
    assert ms.data.select(steps=100).weight.shape == (2, 100, 6)
    out = str(__import__("tempfile").mkdtemp()) + "/d.npz"
    save_dataset(out, ms.data)
    np.testing.assert_array_equal(load_dataset(out).weight, w)


def test_a_long_gap_weighs_out_its_cable_partners_too(robot):
    """A gap of more than LONG_GAP_FRAMES frames of one of a rod's markers also weighs out, with
    the same margin, the equations of the rods it shares a cable with (the bridged position sets
    their cables' forces); a rod sharing none with it keeps its weights, and a gap of
    LONG_GAP_FRAMES frames leaves the partners alone."""
    from dataclasses import replace

    from identified.fit.markers import GAP_FRAMES, LONG_GAP_FRAMES

    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100), seed=1)
    partners = {b for s in topo.springs if 0 in s.rods for b in s.rods if b not in (0, -1)}
    others = set(range(topo.n_rods)) - partners - {0}
    assert partners and others  # the robot: rod 0 shares cables with four rods, not its parallel twin
    step = round(0.01 / data.dt)
    for n, hit in ((LONG_GAP_FRAMES + 1, True), (LONG_GAP_FRAMES, False)):
        hole = rec.markers.copy()
        f0 = 50
        hole[f0:f0 + n, 0] = np.nan
        ms = states_from_recording(replace(rec, markers=hole), topo, dt=data.dt, lam=1e-12)
        w = ms.data.weight
        frame = (np.arange(ms.data.n_steps) + round(ms.starts[0] / data.dt)) / step
        inside = (frame >= f0 - GAP_FRAMES) & (frame <= f0 + n - 1 + GAP_FRAMES - 1)
        assert np.all(w[0, inside, 0] == 0)
        far = (frame < f0 - 2 * GAP_FRAMES - 1) | (frame > f0 + n - 1 + 2 * GAP_FRAMES + 1)
        for j in partners:
            assert np.all(w[0, inside, j] == 0) == hit and np.all(w[0, far, j] == 1)
        for j in others:
            assert np.all(w[0, :, j] == 1)
        assert np.all(w[1] == 1)


def test_gcv_smoothing_is_scipys_choice():
    """The smoothing read back from scipy's generalised cross validation gives its very spline."""
    from scipy.interpolate import make_smoothing_spline

    from identified.fit.markers import gcv_smoothing

    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 2.0, 200)
    y = np.sin(3 * t) + 0.01 * rng.standard_normal(t.size)
    lam = gcv_smoothing(t, y)
    assert lam is not None and lam > 0
    np.testing.assert_array_equal(make_smoothing_spline(t, y, lam=lam)(t), make_smoothing_spline(t, y)(t))


def test_noise_replicas_scatter_as_the_reconstruction(robot):
    """Replicas of states from 1 mm markers: the same shape and weights; a pair is antithetic about
    the reconstruction (the splines are linear, the pose fits nearly so); each scatters about it as
    the reconstruction from noisy markers scatters about that from the clean ones (same smoothing)."""
    path, topo, data = robot
    from dataclasses import replace

    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02), seed=3)
    clean = record_markers(data, path, RecordConfig(rate=100), seed=3)
    clean = replace(clean, markers=np.where(np.isnan(rec.markers), np.nan, clean.markers))  # the same gaps
    ms = states_from_recording(rec, topo, dt=data.dt, lam=1e-6, replicas=2)
    rd = ms.data
    a, b = rd.replicas
    assert a.pos.shape == rd.pos.shape and a.weight is rd.weight
    noise = rd.pos - states_from_recording(clean, topo, dt=data.dt, lam=1e-6).data.pos
    scatter = np.sqrt(np.mean((a.pos - rd.pos) ** 2))
    assert 0.9 < scatter / np.sqrt(np.mean(noise ** 2)) < 1.1
    mid = 0.5 * (a.pos + b.pos) - rd.pos
    assert np.sqrt(np.mean(mid ** 2)) < 0.01 * scatter
    assert rd.select(episodes=[1], steps=50).replicas[0].pos.shape == (1, 51, 6, 3)


@pytest.mark.expensive
def test_noisy_markers_fit_calibrated(tmp_path):
    """The robot preset from 1 mm markers at 100 Hz with 2 % missing (10 takes of 2 s, total mass
    known; the error bars are the cluster jackknife over the takes): every K within 1 % and
    M within 5 % of the plant's, every z-score (estimate - truth) / standard error of K, c and M
    within 3 and their RMS within 1.5.  Cheap siblings: the weights and replicas tests above, and
    tests/test_recording_error_bars.py (the jackknife exactly, the unseen spin's equation left out)."""
    from identified.fit.identify import ScaleSpec
    from identified.fit.markers import fit_recording

    path = str(tmp_path / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=10, steps=2000, seed=0))
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02), seed=0)
    m = fit_recording(rec, path, effects=["ground_contact"], scale=ScaleSpec(total_mass=21.0), jobs=1)
    assert m.metrics["stderr"].startswith("cluster-robust jackknife")
    truth = {"stiffness": 2000.0, "damping": 30.0, "mass": 3.5}  # the robot preset's
    z = []
    for key, value in truth.items():
        est, se = np.asarray(getattr(m, key)), np.asarray(m.stderr[key])
        z.append((est - value) / se)
        if key == "stiffness":
            assert np.abs(est / value - 1).max() < 0.01
        if key == "mass":
            assert np.abs(est / value - 1).max() < 0.05
    z = np.concatenate(z)
    assert np.abs(z).max() < 3.0 and np.sqrt(np.mean(z ** 2)) < 1.5


def test_weak_form_is_the_windowed_sum():
    """Each weak-form row is the Hann-weighted sum of the equation rows over its window, windows
    every quarter window within an episode, never across one."""
    import torch

    from identified.fit.derivatives import weak_form

    rng = np.random.default_rng(0)
    for T, window, stride in ((1000, 7, None), (999, 301, None), (500, 31, 1), (301, 301, None), (2000, 11, 3)):
        A = torch.as_tensor(rng.normal(size=(3 * T, 4, 5)))
        got = weak_form(A, 3, window, stride)
        s = stride or max(1, window // 4)
        phi = np.hanning(window + 2)[1:-1]
        phi = phi / phi.sum()
        starts = range(0, T - window + 1, s)
        want = np.stack([np.einsum("t,tij->ij", phi, A.numpy()[e * T + a:e * T + a + window])
                         for e in range(3) for a in starts])
        np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-14)


def test_one_smoothing_splines_columns_together():
    """Columns with one smoothing are splined together, exactly as one by one."""
    from scipy.interpolate import make_smoothing_spline

    from identified.fit.markers import _smooth

    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 5, 300))
    y = rng.normal(size=(300, 3)).cumsum(0)
    y[[5, 77, 200]] = np.nan
    grid = np.linspace(0.1, 4.9, 2000)
    got = _smooth(t, y, grid, [1e-4] * 3)
    ok = np.isfinite(y).all(-1)
    want = np.stack([make_smoothing_spline(t[ok], y[ok, k], lam=1e-4)(grid) for k in range(3)], -1)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_effect_search_fits_a_recording_on_a_part_without_replicas(robot, monkeypatch):
    """The effect search fits its candidates on the middle steps of a recording's training takes
    (RECORDING_SEARCH_STEPS in all, at least 1000 a take), without the noise replicas; rod
    states not reconstructed from markers (no replicas) are searched on in full."""
    from identified.fit import pipeline

    path, topo, data = robot
    assert pipeline.search_part(data) is None
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001), seed=2)
    ms = states_from_recording(rec, topo, dt=data.dt, replicas=1)
    assert len(ms.data.replicas) == 1 and ms.data.n_steps > 1500
    monkeypatch.setattr(pipeline, "RECORDING_SEARCH_STEPS", 1000)
    part = pipeline.search_part(ms.data)
    assert part.replicas == () and part.n_episodes == 2 and part.n_steps == 1000
    a = (ms.data.n_steps - 1000) // 2
    assert a > 0
    np.testing.assert_array_equal(part.pos, ms.data.pos[:, a:a + 1001])
    np.testing.assert_array_equal(part.rest_length, ms.data.rest_length[:, a:a + 1000])
    np.testing.assert_array_equal(part.weight, ms.data.weight[:, a:a + 1000])
    monkeypatch.setattr(pipeline, "RECORDING_SEARCH_STEPS", 3000)
    assert pipeline.search_part(ms.data).n_steps == min(1500, ms.data.n_steps)


def test_a_rod_whose_markers_miss_its_origin_is_refused():
    """End caps on a line that misses the rod's frame origin (the composite rod of ``examples/``, an
    electronics box off the axis): the origin moves with the unseen spin, refused in one line
    that says by how much and what would place it."""
    import os

    model = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "six_bar_composite.xml")
    data = collect(model, CollectConfig(episodes=1, steps=300, seed=1))
    rec = record_markers(data, model, RecordConfig(rate=100), seed=1)
    with pytest.raises(RecordingError, match=r"rod 'strut0': its markers lie on a line that misses the rod's origin "
                                             r"by \d.* cm.*record a marker off that line") as err:
        states_from_recording(rec, Topology.from_mjcf(model))
    assert "\n" not in str(err.value)


def test_a_robot_standing_on_the_ground_is_told_to_fit_through_the_engine(robot, tmp_path):
    """The regression leaves the equations of a rod on the ground out (its contact law is fitted on
    their residual): where the rods stand on it all the time (the prism of ``examples/``), the data
    cannot identify the cables, and the refusal says why and what fits such a robot; a robot that
    leaves the ground (the ico robot, ~30 % of its rod-instants on it) is refused without it."""
    import os

    from identified.fit.markers import fit_recording
    from identified.fit.regression import IdentifiabilityError

    prism = os.path.join(os.path.dirname(__file__), "..", "examples", "prism3.xml")
    data = collect(prism, CollectConfig(episodes=2, steps=2000, seed=3))
    rec = record_markers(data, prism, RecordConfig(rate=100, noise_pos=0.001), seed=1)
    with pytest.raises(IdentifiabilityError, match=r"the data cannot identify .*; but the rods are on the ground "
                                                   r"\(within 1 cm\) at (9[0-9]|100) % of the instants.*add --refine"):
        fit_recording(rec, prism, effects=["ground_contact"], jobs=1)
    path, _, robot_data = robot
    few = record_markers(robot_data.select(steps=700), path, RecordConfig(rate=100, noise_pos=0.001), seed=1)
    with pytest.raises(IdentifiabilityError) as err:
        fit_recording(few, path, effects=["ground_contact"], jobs=1)
    assert "on the ground" not in str(err.value)
