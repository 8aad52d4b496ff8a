"""Recordings: what a lab measures (markers at sites, encoder rest lengths, commands), read, checked
against a model, labelled and turned into rod poses.

:mod:`.table` the recording in memory; :mod:`.format` the recording CSV (reader, atomic writer);
:mod:`.rates` encoders faster than the cameras; :mod:`.join` a file per take; :mod:`.checks` against
a model; :mod:`.mocap` C3D and Motive CSV exports; :mod:`.labelling` anonymous markers labelled
against the model; :mod:`.poses` rigid fits of each rod's markers.  Numpy and scipy only: no engine, no fit.
"""

from identified.recording.checks import check_recording
from identified.recording.format import not_text, parse_recording, read_recording, save_recording
from identified.recording.join import join_recordings
from identified.recording.table import (
    Encoders,
    Recording,
    RecordingError,
    site_world_positions,
    with_encoders,
)

__all__ = [
    "Encoders",
    "Recording",
    "RecordingError",
    "check_recording",
    "join_recordings",
    "load_recording",
    "parse_recording",
    "read_recording",
    "save_recording",
    "site_world_positions",
    "with_encoders",
]


def load_recording(path, up: str | None = None) -> Recording:
    """A recording from ``path`` by its extension: ``.csv`` (the recording CSV, or a Motive export,
    recognised by its first cell), ``.c3d``."""
    import os

    p = os.fspath(path)
    ext = os.path.splitext(p)[1].lower()
    if ext == ".c3d":
        from identified.recording.mocap import read_c3d

        return read_c3d(p, up=up or "z")
    if ext == ".csv":
        try:
            with open(p, encoding="utf-8-sig") as fh:
                first = fh.readline()
        except UnicodeDecodeError as exc:
            raise RecordingError(not_text(p, exc)) from None
        except OSError:
            first = ""
        if first.startswith("Format Version"):
            from identified.recording.mocap import read_motive_csv

            return read_motive_csv(p, up=up or "y")
        return read_recording(p)
    raise RecordingError(f"'{p}': a recording is a .csv or .c3d file")
