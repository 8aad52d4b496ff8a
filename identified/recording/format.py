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
encoder sample between camera frames (:func:`split_rates`).  The :class:`Recording`'s rows are then
the camera frames, with the encoders' values interpolated at them (``.ctrl`` held), and every
encoder sample is kept in :class:`Encoders` for :meth:`Recording.rest_at`.

:func:`read_recording` parses and checks the table on its own (numbers, time order, columns it
knows); :func:`check_recording` checks it against a model's topology (site and tendon names,
a rod that cannot be placed, values in millimetres).  Every error is one line naming the file,
the line and the column.  :func:`save_recording` writes atomically.
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field, replace

import numpy as np

from identified.dataset import atomic_write
from identified.topology import Topology

__all__ = [
    "Encoders",
    "Recording",
    "RecordingError",
    "check_recording",
    "join_recordings",
    "read_recording",
    "save_recording",
    "site_world_positions",
    "split_rates",
    "with_encoders",
]

UNLABELLED = re.compile(r"^marker\d+$")
_AXES = ("x", "y", "z")
#: a marker further than this from the world origin is not in metres (m)
FAR = 100.0
#: a take whose frames lie further apart than this (median, s) does not have its time in seconds
SLOW = 1.0
#: camera frames further apart than this many of the take's median interval have frames missing
#: between them (a multi-rate recording leaves out a frame where no marker was seen)
DROPPED = 1.5
#: a sample within this many seconds of an instant counts as at it (the CSV's nine decimals against
#: ``t0 + k dt`` in floating point)
SAME_INSTANT = 1e-9


class RecordingError(ValueError):
    """The recording is unreadable, inconsistent or does not belong to the model."""


@dataclass(frozen=True)
class Encoders:
    """Every row of a multi-rate recording that carries an encoder cell, at the encoders' own rate:
    ``time`` (K,) s, ``episode`` (K,) the take (numbered as the recording's), ``rest``, ``ctrl``,
    ``length`` (K, ·) in the recording's column order (NaN where empty), ``lines`` (K,) file lines."""

    time: np.ndarray
    episode: np.ndarray
    rest: np.ndarray
    ctrl: np.ndarray
    length: np.ndarray
    lines: np.ndarray | None = None


@dataclass(frozen=True)
class Recording:
    """A recording as arrays; ``N`` rows (frames), ``M`` markers.

    ``markers`` (N, M, 3): NaN where a sample is missing.  ``rest``, ``ctrl``, ``length``: (N, ·)
    columns named by ``rest_names``, ``ctrl_names``, ``length_names`` (NaN where empty).
    ``episode`` (N,) int: the take of each row, renumbered 0, 1, ... in order of appearance.
    ``lines`` (N,) int: the file line of each row (for messages). ``noise_pos``: the marker noise
    std (m) when the recording states it (a ``# noise_pos=...`` comment line), else ``None``.
    ``encoders``: the encoder samples at their own rate where it is not the frames' (a multi-rate
    recording, :func:`split_rates`), else ``None`` (the frames' own cells are the samples).
    ``sources``: the file of each take where the recording joins several (:func:`join_recordings`),
    else empty (every take is ``source``'s).
    """

    time: np.ndarray
    episode: np.ndarray
    marker_names: tuple[str, ...]
    markers: np.ndarray
    rest_names: tuple[str, ...] = ()
    rest: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    ctrl_names: tuple[str, ...] = ()
    ctrl: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    length_names: tuple[str, ...] = ()
    length: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    source: str = "<recording>"
    lines: np.ndarray | None = None
    noise_pos: float | None = None
    encoders: Encoders | None = None
    sources: tuple[str, ...] = ()
    headers: tuple[tuple[str, int, frozenset[str]], ...] = ()

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def n_episodes(self) -> int:
        return int(self.episode.max()) + 1 if self.n_frames else 0

    @property
    def stated_noise(self) -> float | None:
        """The markers' noise std (m) the recording states (``noise_pos`` above 0), else ``None``
        (not stated, or stated clean: the fit then measures it)."""
        return float(self.noise_pos) if self.noise_pos is not None and self.noise_pos > 0 else None

    @property
    def unlabelled(self) -> bool:
        """True when the marker columns carry no site names (``marker<N>``)."""
        return bool(self.marker_names) and all(UNLABELLED.match(n) for n in self.marker_names)

    def line(self, row: int) -> int:
        """The file line of row ``row`` (the header is line 1)."""
        return int(self.lines[row]) if self.lines is not None else row + 2

    def where(self, row: int, episode: int | None = None, line: int | None = None) -> str:
        """``'file', line N`` of row ``row`` for messages: the file of its take (``episode``, else
        the row's) and its line (``line``, else the row's)."""
        e = int(self.episode[row]) if episode is None else int(episode)
        src = self.sources[e] if self.sources else self.source
        return f"'{src}', line {self.line(row) if line is None else int(line)}"

    def header_where(self, name: str | None = None) -> str:
        """``'file', line N`` of the header row that has column ``name`` (a site, tendon or actuator
        name; ``None``: the first file's header) for messages about a column: ``headers`` holds each
        file's header line and its names (one entry per file joined), else line 1 of ``source``."""
        for src, line, names in self.headers:
            if name is None or name in names:
                return f"'{src}', line {line}"
        return f"'{self.source}', line 1"

    def episodes(self) -> list[np.ndarray]:
        """Row indices of each take, in order."""
        return [np.flatnonzero(self.episode == e) for e in range(self.n_episodes)]

    def rest_at(self, episode: int, times: np.ndarray) -> np.ndarray:
        """(len(times), S) every ``.rest`` column at ``times`` (s) of take ``episode``: linear
        between the encoder's samples (at their own rate in a multi-rate recording), held beyond its
        first and last.  RecordingError where a column has no sample in the take."""
        src, rows = self._samples(episode)
        out = _sampled(src.time[rows], src.rest[rows], times, hold=False)
        for j in np.flatnonzero(~np.isfinite(src.rest[rows]).any(0)):
            raise RecordingError(f"{self._where_sample(src, episode, rows[0])}, column '{self.rest_names[j]}.rest': empty "
                                 "in the whole take; the fit needs every cable's rest length")
        return out

    def ctrl_at(self, episode: int, times: np.ndarray) -> np.ndarray:
        """(len(times), U) every ``.ctrl`` column at ``times`` (s) of take ``episode``: each command
        held from its last sample at or before the instant (:data:`SAME_INSTANT`).
        RecordingError where an instant comes before the column's first sample in the take."""
        src, rows = self._samples(episode)
        times = np.asarray(times, dtype=float)
        out = _sampled(src.time[rows], src.ctrl[rows], times, hold=True)
        for j in np.flatnonzero(np.isnan(out).any(0)):
            ok = np.isfinite(src.ctrl[rows, j])
            r = rows[np.flatnonzero(ok)[0]] if ok.any() else rows[0]
            what = (f"its first command ({src.time[r]:g} s) comes after the take's first state "
                    f"({times.min():g} s)") if ok.any() else "empty in the whole take"
            raise RecordingError(f"{self._where_sample(src, episode, r)}, column '{self.ctrl_names[j]}.ctrl': {what}; the "
                                 "fit needs every MuJoCo actuator's command at every step")
        return out

    def _samples(self, episode: int) -> tuple[Recording | Encoders, np.ndarray]:
        """Where the encoders' samples of take ``episode`` are (:class:`Encoders` in a multi-rate
        recording, else the frames themselves), and their rows there."""
        src = self.encoders if self.encoders is not None else self
        return src, np.flatnonzero(src.episode == episode)

    def _where_sample(self, src: Recording | Encoders, episode: int, row: int) -> str:
        """:meth:`where` for row ``row`` of ``src``, the encoders' samples (:meth:`_samples`), in take
        ``episode``."""
        return self.where(0, episode, int(src.lines[row]) if src.lines is not None else int(row) + 2)

    def rate_hz(self) -> float:
        """Median sampling rate over all takes, Hz."""
        d = np.concatenate([np.diff(self.time[i]) for i in self.episodes()] or [np.zeros(0)])
        return float(1.0 / np.median(d)) if d.size else float("nan")

    def encoder_rate_hz(self) -> float:
        """The encoders' median sampling rate over all takes, Hz (the frames' where they are read at
        the frames)."""
        if self.encoders is None:
            return self.rate_hz()
        enc = self.encoders
        d = np.concatenate([np.diff(enc.time[enc.episode == e]) for e in range(self.n_episodes)] or [np.zeros(0)])
        return float(1.0 / np.median(d)) if d.size else float("nan")

    def missing_fraction(self) -> float:
        """Share of marker samples that are missing."""
        return float(np.isnan(self.markers[..., 0]).mean()) if self.markers.size else 0.0

    def with_markers(self, names: tuple[str, ...], markers: np.ndarray) -> Recording:
        """The same recording with other marker columns (after labelling)."""
        return replace(self, marker_names=tuple(names), markers=np.asarray(markers, dtype=float))


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
        raise RecordingError(f"'{source}', line {lines_a[r]}, column '{names[m]}.{_AXES[a]}': empty while the "
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


def split_rates(rec: Recording) -> Recording:
    """A recording whose encoders run faster than its cameras, written as one table: the rows with
    no marker sample and an encoder cell are encoder samples between the camera frames.  Returns
    the camera frames as the recording's rows (the ``.rest`` and ``.length`` columns interpolated at
    them, ``.ctrl`` held from its last sample), every encoder row kept in ``encoders``, and the
    frames the camera dropped (where the frames lie further apart than :data:`DROPPED` of the take's
    median interval) put back with every marker missing, so the fit treats them as the gap they are.
    A recording without such rows is returned as it is."""
    if not rec.marker_names:
        return rec
    seen = ~np.isnan(rec.markers[..., 0]).all(1)
    enc = np.zeros(rec.n_frames, dtype=bool)
    for arr in (rec.rest, rec.ctrl, rec.length):
        if arr.size:
            enc |= np.isfinite(arr).any(1)
    if not (~seen & enc).any():
        return rec
    lines = rec.lines if rec.lines is not None else np.arange(rec.n_frames) + 2
    encoders = Encoders(rec.time[enc], rec.episode[enc], rec.rest[enc], rec.ctrl[enc], rec.length[enc], lines[enc])
    time, episode, frame_lines, markers = [], [], [], []
    for e in range(rec.n_episodes):
        rows = np.flatnonzero((rec.episode == e) & seen)
        if rows.size == 0:
            r = int(np.flatnonzero(rec.episode == e)[0])
            raise RecordingError(f"'{rec.source}', line {lines[r]}: this take has encoder rows but no marker sample")
        t = rec.time[rows]
        keep = np.ones(rows.size, dtype=bool)
        after = rows  # the file row each frame's messages name (a dropped frame: the next frame's)
        if rows.size > 2:
            h = float(np.median(np.diff(t)))
            missed = np.r_[np.round(np.diff(t) / h).astype(np.int64) - 1, 0]
            missed[np.diff(t, append=t[-1]) < DROPPED * h] = 0
            if missed.any():  # dropped frames back, evenly spaced in their gap
                at = np.repeat(np.arange(rows.size), missed + 1)
                k = np.concatenate([np.arange(n + 1) for n in missed])
                nxt = t[np.minimum(at + 1, rows.size - 1)]
                t = t[at] + k * (nxt - t[at]) / (missed[at] + 1)
                keep = k == 0
                # a dropped frame at the table's row nearest to it (the frame's own row, or an encoder
                # sample on the same clock), where one lies within a quarter interval
                table = rec.time[rec.episode == e]
                j = np.clip(np.searchsorted(table, t), 1, table.size - 1)
                near = np.where(np.abs(table[j - 1] - t) <= np.abs(table[j] - t), table[j - 1], table[j])
                t = np.where(~keep & (np.abs(near - t) <= 0.25 * h), near, t)
                after = np.where(keep, rows[at], rows[np.minimum(at + 1, rows.size - 1)])
                rows = rows[at]
        m = rec.markers[rows].copy()
        m[~keep] = np.nan
        time.append(t)
        episode.append(np.full(t.size, e, dtype=np.int64))
        frame_lines.append(lines[after])
        markers.append(m)
    frames = replace(rec, time=np.concatenate(time), episode=np.concatenate(episode), markers=np.concatenate(markers),
                     lines=np.concatenate(frame_lines))
    return with_encoders(frames, encoders)


def with_encoders(rec: Recording, encoders: Encoders) -> Recording:
    """``rec`` (its rows the camera frames) with the encoder samples ``encoders`` at their own rate:
    the frames' ``.rest`` and ``.length`` cells linear between the samples (held beyond the first and
    last), ``.ctrl`` held from its last sample (empty before the first)."""
    def at_frames(arr: np.ndarray, hold: bool) -> np.ndarray:
        out = np.full((rec.n_frames, arr.shape[1]), np.nan)
        for e in range(rec.n_episodes):
            f, r = rec.episode == e, encoders.episode == e
            out[f] = _sampled(encoders.time[r], arr[r], rec.time[f], hold)
        return out

    return replace(rec, rest=at_frames(encoders.rest, False), ctrl=at_frames(encoders.ctrl, True),
                   length=at_frames(encoders.length, False), encoders=encoders)


def _sampled(t: np.ndarray, x: np.ndarray, times: np.ndarray, hold: bool) -> np.ndarray:
    """(len(times), C) each column of the samples ``x`` (K, C) taken at ``t`` (K,) (NaN: no sample)
    at ``times``: linear between its samples and held beyond its first and last, or (``hold``)
    held from its last sample at or before the instant (:data:`SAME_INSTANT`; NaN before the
    first).  NaN throughout for a column without a sample."""
    times = np.asarray(times, dtype=float)
    out = np.full((times.size, x.shape[1]), np.nan)
    for j in range(x.shape[1]):
        ok = np.isfinite(x[:, j])
        if not ok.any():
            continue
        if hold:
            i = np.searchsorted(t[ok], times + SAME_INSTANT, side="right") - 1
            out[:, j] = np.where(i >= 0, x[ok, j][np.maximum(i, 0)], np.nan)
        else:
            out[:, j] = np.interp(times, t[ok], x[ok, j])
    return out


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
        if kind in _AXES:
            cols["markers"].setdefault(base, [None, None, None])[_AXES.index(kind)] = c
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
            missing = _AXES[idx.index(None)]
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
        raise RecordingError(f"{rec.where(r)}, column '{rec.marker_names[m]}.{_AXES[a]}': "
                             f"{rec.markers[r, m, a]:g} is {FAR:g} m or more from the origin: the recording "
                             "must be in metres (divide millimetres by 1000)")


# ---------------------------------------------------------------------- several files
def join_recordings(recs: list[Recording]) -> Recording:
    """Several recordings as the takes of one, in the order given (motion-capture software writes
    a file per take).  Columns are matched by name; a column one file lacks is empty in its takes
    (a marker not seen, an encoder not logged: the checks and the fit then say so, naming that
    file).  Messages name each take's own file (:meth:`Recording.where`).  The files must agree on
    what their markers are (named by site, or anonymous) and on the noise they state."""
    if len(recs) == 1:
        return recs[0]
    kinds = {r.unlabelled for r in recs if r.marker_names}
    if len(kinds) > 1:
        odd = next(r for r in recs if r.unlabelled != recs[0].unlabelled)
        raise RecordingError(f"'{odd.source}': its markers are {'anonymous' if odd.unlabelled else 'named by site'} "
                             f"and those of '{recs[0].source}' are not: join recordings of one kind")
    noises = {r.noise_pos for r in recs}
    if len(noises) > 1:
        odd = next(r for r in recs if r.noise_pos != recs[0].noise_pos)
        raise RecordingError(f"'{odd.source}' states a marker noise of {odd.noise_pos} m and '{recs[0].source}' of "
                             f"{recs[0].noise_pos} m: join recordings of one noise (or state none)")

    def union(attr: str) -> tuple[str, ...]:
        return tuple(dict.fromkeys(n for r in recs for n in getattr(r, attr)))

    names = {a: union(a) for a in ("marker_names", "rest_names", "ctrl_names", "length_names")}

    def placed(arr: np.ndarray, have: tuple[str, ...], attr: str, rows: int) -> np.ndarray:
        out = np.full((rows, len(names[attr])) + arr.shape[2:], np.nan)
        for j, n in enumerate(have):
            out[:, names[attr].index(n)] = arr[:, j]
        return out

    parts: dict[str, list] = {k: [] for k in ("time", "episode", "markers", "rest", "ctrl", "length", "lines")}
    enc_parts: dict[str, list] = {k: [] for k in ("time", "episode", "rest", "ctrl", "length", "lines")}
    sources: list[str] = []
    first = 0
    for r in recs:
        lines = r.lines if r.lines is not None else np.arange(r.n_frames) + 2
        parts["time"].append(r.time)
        parts["episode"].append(r.episode + first)
        parts["lines"].append(lines)
        parts["markers"].append(placed(r.markers, r.marker_names, "marker_names", r.n_frames))
        for kind in ("rest", "ctrl", "length"):
            parts[kind].append(placed(getattr(r, kind), getattr(r, f"{kind}_names"), f"{kind}_names", r.n_frames))
        enc = r.encoders or Encoders(r.time, r.episode, r.rest, r.ctrl, r.length, lines)
        enc_parts["time"].append(enc.time)
        enc_parts["episode"].append(enc.episode + first)
        enc_parts["lines"].append(enc.lines if enc.lines is not None else np.zeros(enc.time.size, dtype=np.int64))
        for kind in ("rest", "ctrl", "length"):
            enc_parts[kind].append(placed(getattr(enc, kind), getattr(r, f"{kind}_names"), f"{kind}_names",
                                          enc.time.size))
        sources += list(r.sources) if r.sources else [r.source] * r.n_episodes
        first += r.n_episodes
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    encoders = None
    if any(r.encoders is not None for r in recs):
        encoders = Encoders(**{k: np.concatenate(v) for k, v in enc_parts.items()})
    return Recording(time=cat["time"], episode=cat["episode"], marker_names=names["marker_names"],
                     markers=cat["markers"], rest_names=names["rest_names"], rest=cat["rest"],
                     ctrl_names=names["ctrl_names"], ctrl=cat["ctrl"], length_names=names["length_names"],
                     length=cat["length"], source=", ".join(dict.fromkeys(r.source for r in recs)), lines=cat["lines"],
                     noise_pos=recs[0].noise_pos, encoders=encoders, sources=tuple(sources),
                     headers=tuple(h for r in recs for h in (r.headers or ((r.source, 1, frozenset()),))))


# ---------------------------------------------------------------------- against the model
def check_recording(rec: Recording, topology: Topology, actuators: tuple[str, ...] = ()) -> None:
    """Check ``rec`` against the model: names, placeable rods, units (RecordingError, one line).

    ``actuators``: the model's MuJoCo actuator names (the ``.ctrl`` columns may name them).
    """
    sites = {s: i for i, r in enumerate(topology.rods) for s in r.sites}
    springs = set(topology.spring_names)
    if not rec.unlabelled:
        for n in rec.marker_names:
            if n not in sites and not UNLABELLED.match(n):
                raise RecordingError(f"{rec.header_where(n)}, column '{n}.x': the model has no site '{n}' on a rod "
                                     f"(sites: {', '.join(list(sites)[:6])}, ...)")
    for kind, names in (("rest", rec.rest_names), ("length", rec.length_names)):
        for n in names:
            if n not in springs:
                raise RecordingError(f"{rec.header_where(n)}, column '{n}.{kind}': the model has no tendon '{n}'")
    for n in rec.ctrl_names:
        if n not in actuators:
            raise RecordingError(f"{rec.header_where(n)}, column '{n}.ctrl': the model has no actuator '{n}'"
                                 + (f" (actuators: {', '.join(actuators[:6])})" if actuators else ""))
    if rec.unlabelled:
        return
    _check_units(rec, topology, sites)
    for i, rod in enumerate(topology.rods):
        cols = [m for m, n in enumerate(rec.marker_names) if sites.get(n) == i]
        if len(cols) < 2:
            have = ", ".join(rec.marker_names[m] for m in cols) or "none"
            raise RecordingError(f"{rec.header_where()}: rod '{rod.name}' has {len(cols)} marker column(s) ({have}); "
                                 f"at least 2 of its sites ({', '.join(rod.sites)}) are needed to place it")
        seen = (~np.isnan(rec.markers[:, cols, 0])).sum(axis=1)
        for ep in rec.episodes():
            ok = seen[ep] >= 2
            if ok.mean() < 0.5:
                r = int(ep[np.flatnonzero(~ok)[0]])
                raise RecordingError(f"{rec.where(r)}, column '{rec.marker_names[cols[0]]}.x': rod "
                                     f"'{rod.name}' has fewer than 2 visible markers in {100 * (1 - ok.mean()):.0f} % "
                                     "of this take's frames: too few to place it")


def _check_units(rec: Recording, topology: Topology, sites: dict[str, int]) -> None:
    """Distances between markers of one rod against the model's: 1000x means millimetres."""
    for i, rod in enumerate(topology.rods):
        cols = [m for m, n in enumerate(rec.marker_names) if sites.get(n) == i]
        for a in range(len(cols)):
            for b in range(a + 1, len(cols)):
                oa = rod.site_offsets[rod.sites.index(rec.marker_names[cols[a]])]
                ob = rod.site_offsets[rod.sites.index(rec.marker_names[cols[b]])]
                ref = float(np.linalg.norm(oa - ob))
                d = np.linalg.norm(rec.markers[:, cols[a]] - rec.markers[:, cols[b]], axis=-1)
                if ref <= 0 or not np.isfinite(d).any():
                    continue
                ratio = np.nanmedian(d) / ref
                if ratio > 30 or ratio < 1 / 30:
                    r = int(np.flatnonzero(np.isfinite(d))[0])
                    unit = "millimetres (divide by 1000)" if 300 < ratio < 3000 else "another unit than metres"
                    raise RecordingError(
                        f"{rec.where(r)}, column '{rec.marker_names[cols[b]]}.x': markers "
                        f"{rec.marker_names[cols[a]]} and {rec.marker_names[cols[b]]} are {np.nanmedian(d):.4g} "
                        f"apart, the model's sites {ref:.4g} m: the recording looks like {unit}")


# ---------------------------------------------------------------------- writing
def save_recording(path: str | os.PathLike, rec: Recording, precision: int = 7) -> None:
    """Write ``rec`` as a recording CSV, atomically (a temporary file renamed into place); a
    multi-rate recording as its frames and encoder rows in time order (:func:`split_rates`)."""
    time, episode, markers, rest, ctrl, length = (rec.time, rec.episode, rec.markers, rec.rest, rec.ctrl, rec.length) \
        if rec.encoders is None else _merged(rec)
    header = ["time", "episode"]
    blocks = [time[:, None], episode[:, None].astype(float)]
    for m, n in enumerate(rec.marker_names):
        header += [f"{n}.{a}" for a in _AXES]
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


def site_world_positions(topology: Topology, pos: np.ndarray, quat: np.ndarray,
                         names: tuple[str, ...]) -> np.ndarray:
    """World positions (..., len(names), 3) of rod sites from rod states ``pos`` (..., R, 3) and
    ``quat`` (..., R, 4)."""
    from identified.rotation import quat_to_matrix

    where = {s: (i, r.site_offsets[k]) for i, r in enumerate(topology.rods) for k, s in enumerate(r.sites)}
    rot = quat_to_matrix(quat)
    out = []
    for n in names:
        i, off = where[n]
        out.append(pos[..., i, :] + np.einsum("...ij,j->...i", rot[..., i, :, :], off))
    return np.stack(out, axis=-2)
