"""The recording CSV: what a lab measures, as one table (header row, SI units, world frame, z up).

Columns (any order; names are the MJCF's):

=========================  ================================================================
column                     meaning
=========================  ================================================================
``time``                   s, increasing within a take
``episode`` (optional)     a new take where the value changes (any integer)
``<site>.x/.y/.z``         a marker at an MJCF site, m; an empty cell is a missing sample
``marker<N>.x/.y/.z``      an unlabelled marker (identity unknown, may change between frames)
``<tendon>.rest``          an actuated cable's rest length as its spool encoder reports it, m
``<actuator>.ctrl``        the command sent to a MuJoCo actuator, held until the next row
``<tendon>.length``        (optional) a measured cable length, m
=========================  ================================================================

Encoders often run faster than the cameras.  A recording may then interleave rows at both rates in
one table (sorted by time within a take): a row with no marker sample and an encoder cell is an
encoder sample between camera frames (:mod:`identified.recording.rates`).  The recording's rows are
then the camera frames, with the encoders' values interpolated at them (``.ctrl`` held), and every
encoder sample is kept in its ``encoders`` (:mod:`identified.recording.table`).

:func:`read_recording` parses and checks the table on its own (numbers, time order, columns it
knows); :mod:`identified.recording.checks` checks it against a model's topology (site and tendon
names, a rod that cannot be placed, values in millimetres).  Every error is one line naming the
file, the line and the column.  :func:`save_recording` writes atomically.
"""

from __future__ import annotations

import csv
import io
import os
import re

import numpy as np

from identified.dataset import atomic_write
from identified.recording.rates import split_rates
from identified.recording.table import AXES, Recording, RecordingError

__all__ = ["not_text", "parse_recording", "read_recording", "save_recording"]

#: a marker further than this from the world origin is not in metres (m)
FAR = 100.0
#: a take whose frames lie further apart than this (median, s) does not have its time in seconds
SLOW = 1.0


# ---------------------------------------------------------------------- reading
def read_recording(path: str | os.PathLike) -> Recording:
    """Parse a recording CSV (the module docstring) and check what needs no model.

    Raises :class:`RecordingError` with one line naming the file, line and column."""
    p = os.fspath(path)
    try:
        with open(p, encoding="utf-8-sig", newline="") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise RecordingError(f"recording '{p}' does not exist") from None
    except UnicodeDecodeError as exc:
        raise RecordingError(not_text(p, exc)) from None
    except OSError as exc:
        raise RecordingError(f"cannot read recording '{p}': {exc.strerror or exc}") from None
    return parse_recording(text, p)


def not_text(path: str, exc: UnicodeDecodeError) -> str:
    """The one-line message for a recording that is not UTF-8 text (compressed, binary, another
    encoding)."""
    head = b""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError:
        pass
    if head[:2] == b"\x1f\x8b":
        what = "a gzip-compressed file, not a text CSV: decompress it first"
    elif head[:4] == b"PK\x03\x04":
        what = "a zip archive, not a text CSV: extract the CSV first"
    else:
        what = (f"not a text CSV: byte 0x{exc.object[exc.start]:02x} at position {exc.start} is not UTF-8 (a binary "
                "file, or text in another encoding: save it as UTF-8)")
    return f"cannot read recording '{path}': {what}"


def parse_recording(text: str, source: str = "<recording>") -> Recording:
    """:func:`read_recording` on the text of a file (``source`` names it in messages)."""
    noise = None
    rows: list[list[str]] = []
    lines: list[int] = []
    header: list[str] | None = None
    for lineno, row in _numbered_rows(text):
        if row and row[0].lstrip().startswith("#"):
            m = re.search(r"noise_pos\s*=\s*([0-9.eE+-]+)", ",".join(row))
            if m:
                noise = _number(m.group(1), source, lineno, "# noise_pos")
            continue
        if not any(c.strip() for c in row):
            continue
        if header is None:
            header = [c.strip() for c in row]
            header_line = lineno
            continue
        rows.append(row)
        lines.append(lineno)
    if header is None:
        raise RecordingError(f"'{source}' is empty: a recording needs a header row and data rows")
    cols = _columns(header, source, header_line)
    if not rows:
        raise RecordingError(f"'{source}' has a header but no data rows")
    width = len(header)
    for row, lineno in zip(rows, lines):
        if len(row) != width:
            raise RecordingError(f"'{source}', line {lineno}: {len(row)} cells, the header has {width}")
    table = np.full((len(rows), width), np.nan)
    for r, (row, lineno) in enumerate(zip(rows, lines)):
        for c, cell in enumerate(row):
            s = cell.strip()
            if s:
                table[r, c] = _number(s, source, lineno, header[c])
    lines_a = np.array(lines, dtype=np.int64)
    time = table[:, cols["time"]]
    for r in np.flatnonzero(~np.isfinite(time)):
        raise RecordingError(f"'{source}', line {lines_a[r]}, column 'time': the time is empty or not finite")
    if "episode" in cols:
        raw = table[:, cols["episode"]]
        for r in np.flatnonzero(~np.isfinite(raw) | (raw != np.round(raw))):
            raise RecordingError(f"'{source}', line {lines_a[r]}, column 'episode': not a whole number")
        episode = np.cumsum(np.r_[0, raw[1:] != raw[:-1]]).astype(np.int64)
        seen: set[float] = set()
        for r in np.flatnonzero(np.r_[True, raw[1:] != raw[:-1]]):
            if raw[r] in seen:
                raise RecordingError(f"'{source}', line {lines_a[r]}, column 'episode': take {raw[r]:g} "
                                     "appears again after another take; keep each take's rows together")
            seen.add(raw[r])
    else:
        episode = np.zeros(len(rows), dtype=np.int64)
    same = episode[1:] == episode[:-1]
    bad = np.flatnonzero(same & ~(time[1:] > time[:-1]))
    if bad.size:
        r = int(bad[0]) + 1
        raise RecordingError(f"'{source}', line {lines_a[r]}, column 'time': {time[r]:g} s is not after the "
                             f"previous row's {time[r - 1]:g} s in the same take (time must increase)")
    _check_rate(time, episode, lines_a, source)
    names = tuple(cols["markers"])
    markers = np.stack([table[:, [cols["markers"][n][a] for a in range(3)]] for n in names], axis=1) \
        if names else np.zeros((len(rows), 0, 3))
    part = np.isnan(markers).any(-1) & ~np.isnan(markers).all(-1)
    if part.any():
        r, m = (int(i) for i in np.argwhere(part)[0])
        a = int(np.flatnonzero(np.isnan(markers[r, m]))[0])
        raise RecordingError(f"'{source}', line {lines_a[r]}, column '{names[m]}.{AXES[a]}': empty while the "
                             "marker's other coordinates are given (a missing sample leaves all three empty)")
    rec = Recording(
        time=time, episode=episode, marker_names=names, markers=markers,
        rest_names=tuple(cols["rest"]), rest=table[:, list(cols["rest"].values())],
        ctrl_names=tuple(cols["ctrl"]), ctrl=table[:, list(cols["ctrl"].values())],
        length_names=tuple(cols["length"]), length=table[:, list(cols["length"].values())],
        source=source, lines=lines_a, noise_pos=noise,
        headers=((source, header_line, frozenset(n for k in ("markers", "rest", "ctrl", "length") for n in cols[k])),),
    )
    _check_values(rec, header)
    return split_rates(rec)


def _check_rate(time: np.ndarray, episode: np.ndarray, lines: np.ndarray, source: str) -> None:
    """A take whose frames are more than :data:`SLOW` apart (median) has its time in other units
    than seconds (milliseconds: 1000x): one line naming its first row."""
    for e in np.unique(episode):
        rows = np.flatnonzero(episode == e)
        if rows.size < 2:
            continue
        gap = float(np.median(np.diff(time[rows])))
        if gap > SLOW:
            raise RecordingError(f"'{source}', line {lines[rows[1]]}, column 'time': frames {gap:g} s apart "
                                 f"(median of the take): time must be in seconds (divide milliseconds by 1000)")


def _numbered_rows(text: str):
    reader = csv.reader(io.StringIO(text))
    for row in reader:
        yield reader.line_num, row


def _number(s: str, source: str, line: int, column: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise RecordingError(f"'{source}', line {line}, column '{column}': '{s}' is not a number") from None
    if not np.isfinite(v):
        raise RecordingError(f"'{source}', line {line}, column '{column}': '{s}' is not a finite number")
    return v


def _columns(header: list[str], source: str, line: int) -> dict:
    cols: dict = {"markers": {}, "rest": {}, "ctrl": {}, "length": {}}
    seen: dict[str, int] = {}
    for c, name in enumerate(header):
        if not name:
            raise RecordingError(f"'{source}', line {line}, column {c + 1}: the header cell is empty")
        if name in seen:
            raise RecordingError(f"'{source}', line {line}, column '{name}': named twice")
        seen[name] = c
        if name in ("time", "episode"):
            cols[name] = c
            continue
        base, dot, kind = name.rpartition(".")
        if not dot or not base:
            raise RecordingError(f"'{source}', line {line}, column '{name}': not a recording column (time, "
                                 "episode, <site>.x/.y/.z, <tendon>.rest, <actuator>.ctrl, <tendon>.length)")
        if kind in AXES:
            cols["markers"].setdefault(base, [None, None, None])[AXES.index(kind)] = c
        elif kind in ("rest", "ctrl", "length"):
            cols[kind][base] = c
        else:
            raise RecordingError(f"'{source}', line {line}, column '{name}': unknown suffix '.{kind}' (expected "
                                 ".x/.y/.z, .rest, .ctrl or .length)")
    if "time" not in cols:
        sep = next((name for sep, name in ((";", "semicolons"), ("\t", "tabs")) if len(header) == 1 and sep in header[0]),
                   None)
        if sep:
            raise RecordingError(f"'{source}', line {line}: the header is one cell of names separated by {sep}: "
                                 "a recording is comma-separated")
        raise RecordingError(f"'{source}', line {line}: no 'time' column")
    for base, idx in cols["markers"].items():
        if None in idx:
            missing = AXES[idx.index(None)]
            raise RecordingError(f"'{source}', line {line}, column '{base}.{missing}' is missing: a marker needs "
                                 ".x, .y and .z")
    return cols


def _check_values(rec: Recording, header: list[str]) -> None:
    for kind, names, arr in (("rest", rec.rest_names, rec.rest), ("length", rec.length_names, rec.length)):
        neg = np.argwhere(arr < 0)
        if neg.size:
            r, j = (int(i) for i in neg[0])
            raise RecordingError(f"{rec.where(r)}, column '{names[j]}.{kind}': a length "
                                 f"cannot be negative ({arr[r, j]:g})")
    far = np.abs(rec.markers) > FAR
    if far.any():
        r, m, a = (int(i) for i in np.argwhere(far)[0])
        raise RecordingError(f"{rec.where(r)}, column '{rec.marker_names[m]}.{AXES[a]}': "
                             f"{rec.markers[r, m, a]:g} is {FAR:g} m or more from the origin: the recording "
                             "must be in metres (divide millimetres by 1000)")


# ---------------------------------------------------------------------- writing
def save_recording(path: str | os.PathLike, rec: Recording, precision: int = 7) -> None:
    """Write ``rec`` as a recording CSV, atomically (a temporary file renamed into place); a
    multi-rate recording as its frames and encoder rows in time order (:mod:`~identified.recording.rates`)."""
    time, episode, markers, rest, ctrl, length = (rec.time, rec.episode, rec.markers, rec.rest, rec.ctrl, rec.length) \
        if rec.encoders is None else _merged(rec)
    header = ["time", "episode"]
    blocks = [time[:, None], episode[:, None].astype(float)]
    for m, n in enumerate(rec.marker_names):
        header += [f"{n}.{a}" for a in AXES]
        blocks.append(markers[:, m])
    for kind, names, arr in (("rest", rec.rest_names, rest), ("ctrl", rec.ctrl_names, ctrl),
                             ("length", rec.length_names, length)):
        header += [f"{n}.{kind}" for n in names]
        if names:
            blocks.append(arr)
    table = np.concatenate(blocks, axis=1)
    digits = [9, 0] + [precision] * (table.shape[1] - 2)

    def write(fh) -> None:
        if rec.noise_pos is not None:
            fh.write(f"# noise_pos={rec.noise_pos:.6g}\n")
        fh.write(",".join(header) + "\n")
        for row in table:
            fh.write(",".join("" if not np.isfinite(v) else (f"{v:.{d}f}" if d else str(int(v)))
                              for v, d in zip(row, digits)) + "\n")

    atomic_write(path, write)


def _merged(rec: Recording) -> tuple[np.ndarray, ...]:
    """The rows of a multi-rate recording's table: time, episode, markers, rest, ctrl, length of its
    frames and its encoder rows in time order within each take (a frame at an encoder sample's
    instant shares its row; a dropped frame is a row with every marker cell empty)."""
    enc = rec.encoders
    parts: list[list[np.ndarray]] = [[] for _ in range(6)]
    for e in range(rec.n_episodes):
        f, r = np.flatnonzero(rec.episode == e), np.flatnonzero(enc.episode == e)
        t = np.union1d(rec.time[f], enc.time[r])
        m = np.full((t.size,) + rec.markers.shape[1:], np.nan)
        m[np.searchsorted(t, rec.time[f])] = rec.markers[f]
        i = np.searchsorted(t, enc.time[r])
        cells = []
        for arr in (enc.rest, enc.ctrl, enc.length):
            out = np.full((t.size, arr.shape[1]), np.nan)
            out[i] = arr[r]
            cells.append(out)
        for k, a in enumerate((t, np.full(t.size, e), m, *cells)):
            parts[k].append(a)
    return tuple(np.concatenate(p) for p in parts)
