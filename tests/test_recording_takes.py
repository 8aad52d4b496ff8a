"""Several files as the takes of one recording (motion-capture software writes a file per take)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from identified.fit.markers import states_from_recording
from identified.recording import (
    RecordingError,
    check_recording,
    join_recordings,
    read_recording,
    save_recording,
)
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    """A 3-take recording (markers at 100 Hz, 1 mm, gaps; encoders at 500 Hz) and its takes as
    three files."""
    d = tmp_path_factory.mktemp("takes")
    path = str(d / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=3, steps=700, seed=5))
    rec = record_markers(data, path, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02, encoder_rate=500.0), seed=3)
    whole = d / "all.csv"
    save_recording(whole, rec)
    files = []
    for e in range(3):
        text = whole.read_text().splitlines(keepends=True)
        keep = [ln for ln in text[2:] if ln.split(",")[1] == str(e)]
        files.append(d / f"take{e}.csv")
        files[-1].write_text("".join(text[:2] + keep))
    return path, Topology.from_mjcf(path), d, whole, files


def test_joined_takes_are_the_recording(takes):
    """The takes read from three files and joined are the three-take recording: the same frames,
    encoder samples and reconstructed states, to the bit; each take's messages name its own file."""
    _path, topo, _d, whole, files = takes
    one = read_recording(whole)
    joined = join_recordings([read_recording(f) for f in files])
    for attr in ("time", "episode", "markers", "rest"):
        np.testing.assert_array_equal(getattr(joined, attr), getattr(one, attr))
    np.testing.assert_array_equal(joined.encoders.time, one.encoders.time)
    np.testing.assert_array_equal(joined.encoders.rest, one.encoders.rest)
    assert joined.sources == tuple(str(f) for f in files) and joined.noise_pos == 0.001
    row = int(np.flatnonzero(joined.episode == 2)[0])
    assert joined.where(row) == f"'{files[2]}', line 3"  # the comment, the header, then its rows
    a, b = states_from_recording(one, topo), states_from_recording(joined, topo)
    for attr in ("pos", "quat", "vel", "angvel", "rest_length", "weight"):
        np.testing.assert_array_equal(getattr(a.data, attr), getattr(b.data, attr))


def test_joined_columns_and_what_is_refused(takes):
    _path, topo, _d, _whole, files = takes
    recs = [read_recording(f) for f in files[:2]]
    # take 1's file lacks a marker and an encoder: empty in its take, and the fit names that file
    r1 = recs[1]
    k = r1.marker_names.index("rod2_end1")
    keep = [m for m in range(len(r1.marker_names)) if m != k]
    r1 = dataclasses.replace(r1, marker_names=tuple(r1.marker_names[m] for m in keep), markers=r1.markers[:, keep],
                             rest_names=r1.rest_names[1:], rest=r1.rest[:, 1:],
                             encoders=dataclasses.replace(r1.encoders, rest=r1.encoders.rest[:, 1:]))
    j = join_recordings([recs[0], r1])
    assert j.marker_names == recs[0].marker_names and j.rest_names == recs[0].rest_names
    assert np.isnan(j.markers[j.episode == 1, k]).all() and not np.isnan(j.markers[j.episode == 0, k]).all()
    with pytest.raises(RecordingError, match=rf"^'{files[1]}', line \d+, column 'rod2_end0.x': rod 'rod2' has fewer "
                                             "than 2 visible markers"):
        states_from_recording(j, topo)
    with pytest.raises(RecordingError, match=rf"^'{files[1]}', line 3, column 'cable0.rest': empty in the whole take"):
        j.rest_at(1, np.array([0.1]))
    # a column only take 1's file has, named for no tendon: that file's header named
    lines = Path(files[1]).read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    extra = str(files[1]) + ".rope.csv"
    with open(extra, "w") as fh:
        fh.write("\n".join(lines[:h] + [lines[h] + ",rope3.length"] + [x + ",1.0" for x in lines[h + 1:]]) + "\n")
    with pytest.raises(RecordingError, match=rf"^'{extra}', line {h + 1}, column 'rope3.length': the model has no tendon"):
        check_recording(join_recordings([recs[0], read_recording(extra)]), topo)
    with pytest.raises(RecordingError, match="states a marker noise of 0.002 m.*join recordings of one noise"):
        join_recordings([recs[0], dataclasses.replace(recs[1], noise_pos=0.002)])
    anon = dataclasses.replace(recs[1], marker_names=tuple(f"marker{i}" for i in range(len(recs[1].marker_names))))
    with pytest.raises(RecordingError, match="its markers are anonymous.*join recordings of one kind"):
        join_recordings([recs[0], anon])


def test_cli_takes_several_files(takes):
    path, _topo, d, whole, files = takes
    run = lambda *a: subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", *a], check=False, capture_output=True,
                                    text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    one = json.loads(run("summary", str(whole), "--json").stdout)
    r = run("summary", *map(str, files), "--model", path, "--json")
    assert r.returncode == 0, r.stderr
    three = json.loads(r.stdout)
    for key in ("takes", "frames", "rate_hz", "duration_s", "missing", "encoder_rate_hz"):
        assert three[key] == one[key], key
    for bad, words in (((str(files[0]), str(d / "d.npz")), f"'{d / 'd.npz'}' is not a recording (.csv, .c3d)"),
                       ((str(files[0]), str(d / "missing.csv")), f"recording '{d / 'missing.csv'}' does not exist"),
                       ((str(files[0]), str(files[1]), str(files[0])), f"'{files[0]}' is given twice")):
        r = run("fit", *bad, "--model", path, "--out", str(d / "f.json"))
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and words in r.stderr, r.stderr
    r = run("fit", *map(str, files), "--model", path, "--out", str(files[1]))
    assert r.returncode == 2 and str(files[1]) in r.stderr and r.stderr.count("\n") == 1, r.stderr
