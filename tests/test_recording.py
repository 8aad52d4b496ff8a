"""Recordings: the CSV contract, its checks, the motion-capture readers, labelling and rod poses."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from identified.recording import (
    Recording,
    RecordingError,
    check_recording,
    load_recording,
    parse_recording,
    read_recording,
    save_recording,
    site_world_positions,
)
from identified.recording.labelling import label_markers
from identified.recording.poses import fit_axis, fit_rigid, rod_geometries
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("rec") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=2, steps=1500, seed=4))
    return path, Topology.from_mjcf(path), data


def test_sites_from_states_are_mujocos(robot):
    """Marker positions computed from rod states equal MuJoCo's own site positions."""
    import mujoco

    from tensegrity_gym.plant import MujocoPlant

    path, topo, _ = robot
    plant = MujocoPlant(path)
    plant.reset()
    for _ in range(50):
        plant.step()
    mujoco.mj_kinematics(plant.model, plant.data)  # site_xpos of the state after the last step
    s = plant.states()
    names = tuple(x for r in topo.rods for x in r.sites)
    mine = site_world_positions(topo, s.pos, s.quat, names)
    theirs = np.array([plant.data.site_xpos[mujoco.mj_name2id(plant.model, mujoco.mjtObj.mjOBJ_SITE, n)] for n in names])
    np.testing.assert_allclose(mine, theirs, atol=1e-12)


def test_round_trip_and_dropout(robot, tmp_path):
    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.0, dropout=0.05), seed=1)
    out = tmp_path / "r.csv"
    save_recording(out, rec)
    back = read_recording(out)
    assert back.marker_names == rec.marker_names and back.rest_names == data.tendon_names
    assert back.n_episodes == 2 and back.n_frames == rec.n_frames
    np.testing.assert_array_equal(np.isnan(back.markers), np.isnan(rec.markers))
    np.testing.assert_allclose(back.markers, rec.markers, atol=6e-8, equal_nan=True)
    np.testing.assert_allclose(back.time, rec.time, atol=1e-9)
    assert abs(back.rate_hz() - 100) < 1e-6
    # 5 % missing in runs: the share is near the asked one and the runs are longer than one frame
    assert 0.03 < back.missing_fraction() < 0.07
    miss = np.isnan(back.markers[:, :, 0])
    starts = (miss[1:] & ~miss[:-1]).sum()
    assert miss.sum() / max(starts, 1) > 2.5
    check_recording(back, topo)
    # the markers are where the plant's sites were (clean recording)
    k = 37
    t = round(back.time[k] / data.dt)
    truth = site_world_positions(topo, data.pos[0, t], data.quat[0, t], back.marker_names)
    seen = ~np.isnan(back.markers[k, :, 0])
    np.testing.assert_allclose(back.markers[k, seen], truth[seen], atol=1e-7)


def _csv(tmp_path, text: str, name: str = "bad.csv") -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


HEAD = "time,episode,rod0_end0.x,rod0_end0.y,rod0_end0.z,rod0_end1.x,rod0_end1.y,rod0_end1.z,cable0.rest\n"


@pytest.mark.parametrize("body, where", [
    ("0.00,0,0,0,0,0,0,1.7,0.9\n0.01,0,0,0,0,0,0,1.7,0.9\n0.01,0,0,0,0,0,0,1.7,0.9\n", "line 4, column 'time'"),
    ("0.00,0,0,0,0,0,0,1.7,0.9\n0.01,0,0,0,abc,0,0,1.7,0.9\n", "line 3, column 'rod0_end0.z'"),
    ("0.00,0,0,0,0,0,0,1.7,0.9\n0.01,0,0,,0,0,0,1.7,0.9\n", "line 3, column 'rod0_end0.y'"),
    ("0.00,0,0,0,0,0,0,1700,0.9\n", "line 2, column 'rod0_end1.z'"),
    ("0.00,0,0,0,0,0,0,1.7,-0.9\n", "line 2, column 'cable0.rest'"),
    # time in milliseconds: frames 10 "s" apart (median), the first take's second row named
    ("0,0,0,0,0,0,0,1.7,0.9\n10,0,0,0,0,0,0,1.7,0.9\n20,0,0,0,0,0,0,1.7,0.9\n", "line 3, column 'time'"),
])
def test_bad_rows_name_file_line_column(tmp_path, body, where):
    p = _csv(tmp_path, HEAD + body)
    with pytest.raises(RecordingError) as err:
        read_recording(p)
    msg = str(err.value)
    assert p in msg and where in msg and "\n" not in msg


def test_checks_against_the_model(robot, tmp_path):
    path, topo, data = robot
    rec = record_markers(data, path, RecordConfig(rate=50), seed=2)
    good = tmp_path / "good.csv"
    save_recording(good, rec)
    text = good.read_text()

    def bad(new_text: str) -> str:
        p = _csv(tmp_path, new_text)
        with pytest.raises(RecordingError) as err:
            check_recording(read_recording(p), topo)
        assert p in str(err.value)
        return str(err.value)

    # the header is line 2, below the stated noise: the messages name it
    assert text.startswith("# noise_pos=0\n")
    assert "line 2, column 'rodX_end0.x': the model has no site 'rodX_end0'" in bad(text.replace("rod2_end0.", "rodX_end0."))
    assert "line 2, column 'rope7.rest': the model has no tendon 'rope7'" in bad(text.replace("cable7.rest", "rope7.rest"))
    # millimetres: every coordinate x1000
    mm = rec.with_markers(rec.marker_names, rec.markers * 1000)
    p = tmp_path / "mm.csv"
    save_recording(p, mm)
    with pytest.raises(RecordingError, match="millimetres|metres"):
        check_recording(read_recording(p), topo)
    # a rod with one marker column cannot be placed
    keep = [k for k, n in enumerate(rec.marker_names) if n != "rod3_end1"]
    one = rec.with_markers(tuple(rec.marker_names[k] for k in keep), rec.markers[:, keep])
    with pytest.raises(RecordingError, match="rod 'rod3' has 1 marker column"):
        check_recording(one, topo)
    # a rod that is hidden in most frames of a take
    hidden = rec.markers.copy()
    hidden[5:, rec.marker_names.index("rod4_end0")] = np.nan
    with pytest.raises(RecordingError, match="rod 'rod4' has fewer than 2 visible markers"):
        check_recording(rec.with_markers(rec.marker_names, hidden), topo)


def test_cli_collect_record_and_bad_input(tmp_path):
    model = tmp_path / "robot.xml"
    write_model(str(model), "ico", preset="robot")
    out = tmp_path / "r.csv"
    run = lambda *a: subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", *a], check=False, capture_output=True,
                                    text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    r = run("collect", "--model", str(model), "--episodes", "1", "--steps", "600", "--record", "markers",
            "--rate", "50", "--noise-pos", "0.001", "--dropout", "0.1", "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    rec = read_recording(out)
    assert rec.n_frames == 30 and rec.noise_pos == 0.001 and rec.stated_noise == 0.001
    # a noise stated clean (0) or not stated is none the fit can weigh its residual against
    assert dataclasses.replace(rec, noise_pos=0.0).stated_noise is None
    assert dataclasses.replace(rec, noise_pos=None).stated_noise is None
    # noise of the asked size: markers of one rod keep their distance within ~sqrt(2) sigma
    d = np.linalg.norm(rec.markers[:, 0] - rec.markers[:, 1], axis=-1)
    assert 0.0005 < np.nanstd(d) < 0.003
    bad = run("collect", "--model", str(model), "--record", "markers", "--push-every", "10", "--out", str(out))
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--push-every" in bad.stderr


def test_rigid_fits_are_exact():
    rng = np.random.default_rng(0)
    off = rng.normal(size=(4, 3))
    rot = Rotation.random(20, random_state=1).as_matrix()
    c = rng.normal(size=(20, 3))
    pts = c[:, None] + np.einsum("fij,kj->fki", rot, off)
    pts[3, 1] = np.nan  # a missing marker leaves three: still placed
    pts[4, :2] = np.nan  # two left: not placed
    cc, rr = fit_rigid(pts, off, np.ones(4))
    ok = np.arange(20) != 4
    np.testing.assert_allclose(cc[ok], c[ok], atol=1e-10)
    np.testing.assert_allclose(rr[ok], rot[ok], atol=1e-10)
    assert np.isnan(cc[4]).all()
    # on an axis: the point at coordinate 0 and the direction
    along = np.array([-0.85, 0.3, 0.85])
    a = rng.normal(size=(20, 3))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    pts = c[:, None] + along[None, :, None] * a[:, None]
    p0, dd = fit_axis(pts, along, np.ones(3))
    np.testing.assert_allclose(p0, c, atol=1e-12)
    np.testing.assert_allclose(dd, a, atol=1e-12)


def test_end_caps_on_the_axis_hide_the_spin(robot):
    _, topo, _ = robot
    geos = rod_geometries(topo)
    assert all(g.collinear and not g.axial_spin_observable for g in geos)
    assert np.allclose(np.abs(geos[0].axis), [0, 0, 1])


def test_unlabelled_markers_are_labelled(robot):
    """Identities shuffled every 0.2 s and two ghosts per frame: every visible marker gets its site back."""
    path, topo, data = robot
    clean = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02), seed=3)
    anon = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02, unlabelled=True,
                                                   swap_every=0.2, ghosts=2), seed=3)
    assert anon.unlabelled and len(anon.marker_names) == len(clean.marker_names) + 2
    from identified.mjcf import nominal_pose, read_mjcf_text

    pose = nominal_pose(read_mjcf_text(path), topo.rod_names)
    ref = site_world_positions(topo, pose.pos, pose.quat, clean.marker_names)
    out = label_markers(anon, topo, ref, clean.marker_names)
    seen = ~np.isnan(clean.markers[..., 0])
    got = ~np.isnan(out.markers[..., 0])
    right = np.all(np.abs(out.markers - clean.markers) < 1e-12, axis=-1)
    assert (right & seen).sum() / seen.sum() > 0.995  # labelled and right
    assert not np.any(got & ~right)  # never a wrong label, never a ghost taken


def test_a_site_hidden_at_the_start_of_a_take_is_labelled_when_it_shows(robot):
    """A marker missing in a take's first frames (the site farthest from the reference pose) is
    found once it shows, not lost for the whole take."""
    path, topo, data = robot
    clean = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001), seed=5)
    anon = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, unlabelled=True, swap_every=0.2,
                                                   ghosts=1), seed=5)
    from identified.mjcf import nominal_pose, read_mjcf_text

    pose = nominal_pose(read_mjcf_text(path), topo.rod_names)
    ref = site_world_positions(topo, pose.pos, pose.quat, clean.marker_names)
    far = [int(np.argmax(np.linalg.norm(clean.markers[anon.episode == e][0] - ref, axis=-1))) for e in (0, 1)]
    assert np.linalg.norm(clean.markers[anon.episode == 1][0, far[1]] - ref[far[1]]) > 0.06  # beyond the gate
    hidden = {(0, far[0]): 1, (1, far[1]): 8}  # (take, site): frames hidden from the take's start
    markers = anon.markers.copy()
    for (take, site), frames in hidden.items():
        for r in np.flatnonzero(anon.episode == take)[:frames]:
            col = np.flatnonzero(np.all(markers[r] == clean.markers[r, site], axis=-1))
            assert col.size == 1
            markers[r, col] = np.nan
    out = label_markers(anon.with_markers(anon.marker_names, markers), topo, ref, clean.marker_names)
    got = ~np.isnan(out.markers[..., 0])
    right = np.all(np.abs(out.markers - clean.markers) < 1e-12, axis=-1)
    assert not np.any(got & ~right)  # never a wrong label, never a ghost taken
    for (take, site), frames in hidden.items():
        rows = np.flatnonzero(anon.episode == take)[frames:]
        assert right[rows, site].mean() > 0.99  # found once it shows


def test_a_fast_site_hidden_for_a_while_is_found_again(robot):
    """The fastest end cap, hidden for 8 frames just after a take starts, is found when it shows:
    its last velocity is not extrapolated over the whole gap."""
    path, topo, data = robot
    clean = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001), seed=6)
    anon = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, unlabelled=True, swap_every=0.2,
                                                   ghosts=1), seed=6)
    markers = anon.markers.copy()
    hidden = {}
    for take in (0, 1):
        rows = np.flatnonzero(anon.episode == take)
        speed = np.linalg.norm(clean.markers[rows[2]] - clean.markers[rows[1]], axis=-1) * 100
        hidden[take] = site = int(np.argmax(speed))
        assert speed[site] > 1.0  # m/s: the gap moves it beyond a fixed gate
        for r in rows[3:11]:
            markers[r, np.flatnonzero(np.all(markers[r] == clean.markers[r, site], axis=-1))] = np.nan
    from identified.mjcf import nominal_pose, read_mjcf_text

    pose = nominal_pose(read_mjcf_text(path), topo.rod_names)
    ref = site_world_positions(topo, pose.pos, pose.quat, clean.marker_names)
    out = label_markers(anon.with_markers(anon.marker_names, markers), topo, ref, clean.marker_names)
    got = ~np.isnan(out.markers[..., 0])
    right = np.all(np.abs(out.markers - clean.markers) < 1e-12, axis=-1)
    assert not np.any(got & ~right)
    for take, site in hidden.items():
        assert right[np.flatnonzero(anon.episode == take)[11:], site].mean() > 0.99


def test_motive_csv_export(robot, tmp_path):
    """A Motive export (millimetres, y up, a labelled and an unlabelled marker) reads as z-up metres."""
    lines = ["Format Version,1.23,Take Name,t,Capture Frame Rate,120.0,Length Units,Millimeters,Coordinate Space,Global",
             "",
             ",Type,Marker,Marker,Marker,Marker,Marker,Marker",
             ",Name,robot:rod0_end0,robot:rod0_end0,robot:rod0_end0,Unlabeled 1004,Unlabeled 1004,Unlabeled 1004",
             ",ID,1,1,1,2,2,2",
             ",,Position,Position,Position,Position,Position,Position",
             "Frame,Time (Seconds),X,Y,Z,X,Y,Z",
             "0,0.000000,100.0,200.0,300.0,1.0,2.0,3.0",
             "1,0.008333,110.0,210.0,310.0,,,"]
    p = _csv(tmp_path, "\n".join(lines) + "\n", "motive.csv")
    rec = load_recording(p)
    assert rec.marker_names == ("rod0_end0", "marker1004")
    np.testing.assert_allclose(rec.markers[0, 0], [0.1, -0.3, 0.2])
    np.testing.assert_allclose(rec.markers[1, 0], [0.11, -0.31, 0.21])
    assert np.isnan(rec.markers[1, 1]).all()
    np.testing.assert_allclose(rec.time, [0.0, 0.008333])
    assert rec.header_where("rod0_end0") == f"'{p}', line 4"  # a message about a marker names its 'Name' row


def test_c3d_file(tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("robot:rod0_end0", "rod0_end1")
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, 2, 6))
    pts[:3] = np.arange(36).reshape(3, 2, 6) * 10.0
    pts[:3, 1, 2] = np.nan  # a gap
    c["data"]["points"] = pts
    c.add_parameter("ANALOG", "LABELS", ("cable0.rest",))
    c["parameters"]["ANALOG"]["RATE"]["value"] = [100]
    c["parameters"]["ANALOG"]["USED"]["value"] = [1]
    c["data"]["analogs"] = np.linspace(0.9, 1.0, 6).reshape(1, 1, 6)
    p = str(tmp_path / "take.c3d")
    c.write(p)
    rec = load_recording(p)
    assert rec.marker_names == ("rod0_end0", "rod0_end1") and rec.rest_names == ("cable0",)
    np.testing.assert_allclose(rec.markers[:, 0], pts[:3, 0].T / 1000, atol=1e-7)
    assert np.isnan(rec.markers[2, 1]).all() and not np.isnan(rec.markers[3, 1]).any()
    np.testing.assert_allclose(rec.rest[:, 0], np.linspace(0.9, 1.0, 6), atol=1e-6)
    np.testing.assert_allclose(rec.time, np.arange(6) / 100)


def test_time_in_seconds_at_the_slowest_accepted():
    """Frames exactly SLOW apart are accepted, further apart refused with the median gap; a take's
    one slow gap (a pause) does not count, the median of its gaps does."""
    from identified.recording.format import SLOW

    ok = parse_recording(f"time,a.x,a.y,a.z\n0,0,0,0\n{SLOW},0,0,0\n", "x.csv")
    assert ok.n_frames == 2
    paused = parse_recording("time,a.x,a.y,a.z\n0,0,0,0\n0.01,0,0,0\n5,0,0,0\n5.01,0,0,0\n", "x.csv")
    assert paused.n_frames == 4
    with pytest.raises(RecordingError, match=r"line 3, column 'time': frames 1\.5 s apart .*milliseconds"):
        parse_recording("time,a.x,a.y,a.z\n0,0,0,0\n1.5,0,0,0\n3,0,0,0\n", "x.csv")


@pytest.mark.parametrize("raw, words", [
    (b"\x1f\x8b\x08\x00" + bytes(range(200, 256)), "gzip-compressed"),
    (b"PK\x03\x04" + bytes(range(200, 256)), "zip archive"),
    (bytes(range(128, 256)), "byte 0x80 at position 0 is not UTF-8"),
])
def test_a_file_that_is_not_text_is_named_in_one_line(tmp_path, raw, words):
    """Compressed or binary files: one line naming the file and what it is, from the CSV reader and
    from the loader that dispatches on the first line (no UnicodeDecodeError traceback)."""
    p = tmp_path / "take.csv"
    p.write_bytes(raw)
    for read in (read_recording, load_recording):
        with pytest.raises(RecordingError) as err:
            read(p)
        msg = str(err.value)
        assert f"'{p}'" in msg and words in msg and "\n" not in msg


def test_separators_and_line_endings(tmp_path):
    """A UTF-8 byte-order mark and Windows line endings read as the plain file; semicolons or tabs
    are named."""
    plain = "time,a.x,a.y,a.z\n0,1,2,3\n0.01,1,2,3\n"
    want = parse_recording(plain, "x.csv")
    for k, raw in enumerate((b"\xef\xbb\xbf" + plain.encode(), plain.replace("\n", "\r\n").encode())):
        p = tmp_path / f"v{k}.csv"
        p.write_bytes(raw)
        got = load_recording(p)
        assert got.marker_names == ("a",)
        np.testing.assert_array_equal(got.markers, want.markers)
        np.testing.assert_array_equal(got.time, want.time)
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        with pytest.raises(RecordingError, match=f"line 1: the header is one cell of names separated by {name}"):
            parse_recording(plain.replace(",", sep), "x.csv")


def test_parse_needs_time_and_rows():
    with pytest.raises(RecordingError, match="no 'time' column"):
        parse_recording("a.x,a.y,a.z\n1,2,3\n", "x.csv")
    with pytest.raises(RecordingError, match="no data rows"):
        parse_recording("time,a.x,a.y,a.z\n", "x.csv")
    with pytest.raises(RecordingError, match="'a.z' is missing"):
        parse_recording("time,a.x,a.y\n0,1,2\n", "x.csv")


def test_cli_fit_and_summary_on_a_recording_too_short(tmp_path):
    """summary reads a recording; fit refuses one too short for its windows in one line, writing nothing."""
    model = tmp_path / "robot.xml"
    write_model(str(model), "ico", preset="robot")
    rec = tmp_path / "short.csv"
    run = lambda *a: subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", *a], check=False, capture_output=True,
                                    text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run("collect", "--model", str(model), "--episodes", "1", "--steps", "400", "--record", "markers",
               "--out", str(rec), "--quiet").returncode == 0
    s = run("summary", str(rec), "--model", str(model), "--json")
    assert s.returncode == 0, s.stderr
    import json

    info = json.loads(s.stdout)
    assert info["takes"] == 1 and info["frames"] == 40 and abs(info["rate_hz"] - 100) < 1e-6
    out = tmp_path / "F.json"
    f = run("fit", str(rec), "--model", str(model), "--total-mass", "21", "--out", str(out), "--quiet")
    assert f.returncode == 2 and f.stderr.count("\n") == 1 and str(rec) in f.stderr and "too short" in f.stderr
    assert not out.exists()


def test_rate_is_the_mean_interval_without_the_gaps():
    """Frames stamped on whole milliseconds lie 8, 8 and 9 ms apart at 120 Hz (33, 33 and 34 at
    30 Hz): the rate is 120 Hz (30), where the median interval says 125 (30.3); a stretch of frames
    missing from the file (a gap of 10 intervals) does not lower it; the encoders' alike."""
    for hz in (120, 30):
        t = np.round(np.arange(361) / hz, 3)
        rec = Recording(time=t, episode=np.zeros(t.size, dtype=int), marker_names=("a",), markers=np.zeros((t.size, 1, 3)))
        assert abs(rec.rate_hz() - hz) < 0.01 * hz / 120 and abs(1 / np.median(np.diff(t)) - hz) > 0.29
    t = np.r_[np.arange(50), np.arange(60, 100)] / 100
    rec = Recording(time=t, episode=np.zeros(t.size, dtype=int), marker_names=("a",), markers=np.zeros((t.size, 1, 3)))
    assert rec.rate_hz() == pytest.approx(100.0, rel=1e-12) and rec.encoder_rate_hz() == pytest.approx(100.0, rel=1e-12)
    assert np.isnan(dataclasses.replace(rec, time=t[:1], episode=np.zeros(1, dtype=int), markers=np.zeros((1, 1, 3))).rate_hz())
