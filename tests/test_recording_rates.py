"""Multi-rate recordings: encoders faster than the cameras, as rows between the camera frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from identified.fit.markers import states_from_recording
from identified.recording import (
    RecordingError,
    load_recording,
    parse_recording,
    read_recording,
    save_recording,
)
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model

HEAD = "time,episode,rod0_end0.x,rod0_end0.y,rod0_end0.z,rod0_end1.x,rod0_end1.y,rod0_end1.z,cable0.rest,motor0.ctrl\n"
M = "0,0,0,0,0,1.7"  # one frame's marker cells


def _row(t: float, markers: bool, rest: float | None, ctrl: float | None = None, ep: int = 0) -> str:
    cells = [f"{t:g}", str(ep), M if markers else ",,,,,", "" if rest is None else f"{rest:g}",
             "" if ctrl is None else f"{ctrl:g}"]
    return ",".join(cells) + "\n"


def test_encoder_rows_between_frames_are_read_at_their_own_rate():
    """Frames at 10 Hz, encoder rows at 40 Hz between them: the recording's rows are the frames,
    the rest lengths at the frames are the encoders' (exact: a linear ramp), ``.ctrl`` is held."""
    rows = []
    for k in range(9):  # 0 .. 0.2 s every 0.025 s; a frame every fourth row (no rest cell there)
        t = 0.025 * k
        rows.append(_row(t, k % 4 == 0, None if k % 4 == 0 else 1.0 + t, ctrl=float(k) if k % 2 else None))
    rec = parse_recording(HEAD + "".join(rows), "r.csv")
    assert rec.n_frames == 3 and rec.rate_hz() == pytest.approx(10.0)
    np.testing.assert_allclose(rec.time, [0.0, 0.1, 0.2])
    assert rec.encoders is not None and rec.encoders.time.size == 6 and rec.encoder_rate_hz() == pytest.approx(40.0)
    # the frames' rest: the ramp 1 + t between the encoder rows, held before the first (0.025 s)
    np.testing.assert_allclose(rec.rest[:, 0], [1.025, 1.1, 1.175], atol=1e-12)
    np.testing.assert_allclose(rec.rest_at(0, np.array([0.03, 0.0625, 0.19])), [[1.03], [1.0625], [1.175]], atol=1e-12)
    # the command held from its last sample: none yet at 0, row 3's (k = 3) at 0.1, row 7's at 0.2
    np.testing.assert_array_equal(rec.ctrl[:, 0], [np.nan, 3.0, 7.0])
    np.testing.assert_array_equal(rec.lines, [2, 6, 10])


def test_a_frame_without_a_marker_is_a_dropped_frame():
    """Where no marker is seen at a frame, its row reads as an encoder row; the frame is put back
    (the camera's frames further apart than 1.5 of their median interval) with every marker
    missing, so the fit weighs its equations out as at any gap."""
    rows = []
    for k in range(25):  # frames every 0.04 s at k % 4 == 0; the one at k = 8 sees no marker
        t = 0.01 * k
        rows.append(_row(t, k % 4 == 0 and k != 8, 1.0 + t))
    rec = parse_recording(HEAD + "".join(rows), "r.csv")
    np.testing.assert_allclose(rec.time, 0.04 * np.arange(7), atol=1e-12)
    assert np.isnan(rec.markers[2]).all() and not np.isnan(rec.markers[[0, 1, 3, 4, 5, 6]]).any()
    assert rec.lines[2] == 14  # the frame after the gap names it in messages
    assert rec.missing_fraction() == pytest.approx(1 / 7)
    np.testing.assert_allclose(rec.rest[:, 0], 1.0 + 0.04 * np.arange(7), atol=1e-12)
    # the same at one rate (an encoder cell in every frame): the frame is where it was
    single = parse_recording(HEAD + "".join(_row(0.04 * k, k != 2, 1.0 + k) for k in range(8)), "s.csv")
    assert single.n_frames == 8 and np.isnan(single.markers[2]).all() and not np.isnan(single.markers[3]).any()
    np.testing.assert_allclose(single.time, 0.04 * np.arange(8), atol=1e-12)
    np.testing.assert_allclose(single.rest[:, 0], 1.0 + np.arange(8), atol=1e-12)


def test_multi_rate_bad_input_names_the_line():
    only = HEAD + _row(0.0, True, 1.0) + _row(0.01, True, 1.0) + _row(0.02, False, 1.0, ep=1) + _row(0.03, False, 1.0, ep=1)
    with pytest.raises(RecordingError, match=r"'r.csv', line 4: this take has encoder rows but no marker sample"):
        parse_recording(only, "r.csv")
    empty = parse_recording(HEAD + _row(0.0, True, None) + _row(0.01, False, None, ctrl=1.0) + _row(0.02, True, None), "r.csv")
    with pytest.raises(RecordingError, match=r"'r.csv', line 3, column 'cable0.rest': empty in the whole take"):
        empty.rest_at(0, np.array([0.0]))


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("rates") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=2, steps=1500, seed=4))
    return path, Topology.from_mjcf(path), data


def test_fast_encoders_give_the_fit_the_plants_rest_lengths(robot, tmp_path):
    """Markers at 30 Hz, encoders at 1 kHz written between the frames: the frames are those of the
    30 Hz recording, the file reads back to itself, and the reconstructed dataset's rest lengths
    are the plant's own at every step (to the CSV's 1e-7 m), where the encoders read at the frames
    leave the linear interpolation's millimetres."""
    path, topo, data = robot
    cfg = RecordConfig(rate=30, noise_pos=0.01, dropout=0.02)
    slow = record_markers(data, path, cfg, seed=5)
    fast = record_markers(data, path, RecordConfig(**{**cfg.__dict__, "encoder_rate": 1000.0}), seed=5)
    p = tmp_path / "fast.csv"
    save_recording(p, fast)
    back = read_recording(p)
    assert back.n_frames == slow.n_frames and back.encoders.time.size == data.n_episodes * data.n_steps
    np.testing.assert_allclose(back.markers, slow.markers, atol=6e-8)
    np.testing.assert_allclose(back.rest, slow.rest, atol=6e-8)  # the frames' own instants are encoder samples
    save_recording(tmp_path / "again.csv", back)
    assert (tmp_path / "again.csv").read_text() == p.read_text()
    # a frame with no marker seen (the 30 Hz frames 33 or 34 ms apart): back as a gap at its own instant
    blank = fast.markers.copy()
    blank[10] = np.nan
    save_recording(tmp_path / "blank.csv", fast.with_markers(fast.marker_names, blank))
    gap = read_recording(tmp_path / "blank.csv")
    np.testing.assert_array_equal(gap.time, back.time)
    assert np.isnan(gap.markers[10]).all() and np.isnan(gap.markers).sum() == np.isnan(blank).sum()
    errors = {}
    for name, rec in (("slow", slow), ("fast", back)):
        ms = states_from_recording(rec, topo)
        err = 0.0
        for e in range(data.n_episodes):
            s = round(ms.starts[e] / data.dt)
            T = ms.data.n_steps
            err = max(err, float(np.abs(ms.data.rest_length[e] - data.rest_length[e, s:s + T]).max()))
        errors[name] = err
    assert errors["fast"] < 6e-8
    assert errors["slow"] > 1e-3  # what the fast encoders remove: the motors move mm between 30 Hz frames


def test_c3d_analogs_faster_than_the_points(tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100]
    c["parameters"]["POINT"]["LABELS"]["value"] = ("rod0_end0", "rod0_end1")
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    pts = np.ones((4, 2, 5))
    pts[:3] = np.arange(30).reshape(3, 2, 5) * 0.01
    c["data"]["points"] = pts
    c.add_parameter("ANALOG", "LABELS", ("cable0.rest",))
    c["parameters"]["ANALOG"]["RATE"]["value"] = [1000]
    c["parameters"]["ANALOG"]["USED"]["value"] = [1]
    t = np.arange(50) / 1000
    c["data"]["analogs"] = (1.0 + t ** 2).reshape(1, 1, 50)
    p = str(tmp_path / "take.c3d")
    c.write(p)
    rec = load_recording(p)
    assert rec.n_frames == 5 and rec.encoders is not None and rec.encoder_rate_hz() == pytest.approx(1000.0)
    np.testing.assert_allclose(rec.encoders.time, t, atol=1e-12)
    np.testing.assert_allclose(rec.rest[:, 0], 1.0 + (np.arange(5) / 100) ** 2, atol=1e-6)
    np.testing.assert_allclose(rec.rest_at(0, np.array([0.0135])), [[1.0 + 0.5 * (0.013 ** 2 + 0.014 ** 2)]], atol=1e-6)


def test_cli_collect_encoder_rate_and_options_without_record(robot, tmp_path):
    path = robot[0]
    run = lambda *a: subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", *a], check=False, capture_output=True,
                                    text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    out = tmp_path / "r.csv"
    r = run("collect", "--model", path, "--episodes", "1", "--steps", "600", "--record", "markers", "--rate", "50",
            "--encoder-rate", "500", "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    assert "24 encoder rest lengths at 500 Hz" in r.stdout
    s = run("summary", str(out), "--json")
    info = json.loads(s.stdout)
    assert info["frames"] == 30 and info["rate_hz"] == pytest.approx(50.0) and info["encoder_rate_hz"] == pytest.approx(500.0)
    for bad, words in ((("--rate", "30", "--out", str(tmp_path / "d.npz")), "--rate is for a recording"),
                       (("--dropout", "0.1", "--out", str(tmp_path / "d.npz")), "--dropout is for a recording"),
                       (("--record", "markers", "--encoder-rate", "2000", "--out", str(out)), "--encoder-rate must be in"),
                       (("--record", "markers", "--ghosts", "1", "--out", str(out)), "add --unlabelled")):
        r = run("collect", "--model", path, "--episodes", "1", "--steps", "100", *bad, "--quiet")
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and words in r.stderr, r.stderr


def test_a_command_is_held_from_its_own_instant():
    """``.ctrl`` at an engine step's instant is the sample written for that instant, though the
    step's time (``t0 + k dt``) and the CSV's nine decimals differ in the last bit."""
    t = 0.0137 + 0.001 * np.arange(200)
    rows = "".join(f"{x:.9f},0,0,0,0,0,0,1.7,1.0,{k}\n" for k, x in enumerate(t))
    rec = parse_recording(HEAD + rows, "r.csv")
    below = np.flatnonzero(t < rec.time)  # instants that fall a rounding error before their row
    assert below.size > 0
    np.testing.assert_array_equal(rec.ctrl_at(0, t)[:, 0], np.arange(200))
