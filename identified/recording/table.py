"""The recording in memory: :class:`Recording` (camera frames: markers, the encoders' values at
them, commands, measured lengths), :class:`Encoders` (the encoders' own samples where they run
faster than the cameras) and :class:`RecordingError`, the one-line error of every reader and check.

The encoders' values at any instant (:meth:`Recording.rest_at`, :meth:`Recording.ctrl_at`): rest
and measured lengths linear between samples, commands held from their last sample
(:func:`with_encoders` puts them at the frames).  Numpy only.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np

from identified.topology import Topology

__all__ = ["AXES", "UNLABELLED", "Encoders", "Recording", "RecordingError", "site_world_positions", "with_encoders"]

#: anonymous marker columns (``marker17.x``)
UNLABELLED = re.compile(r"^marker\d+$")
#: a marker column's suffixes, in order
AXES = ("x", "y", "z")
#: a sample within this many seconds of an instant counts as at it (the CSV's nine decimals against
#: ``t0 + k dt`` in floating point)
SAME_INSTANT = 1e-9
#: camera frames further apart than this many of the take's median interval have frames missing
#: between them (a multi-rate recording leaves out a frame where no marker was seen)
DROPPED = 1.5


def _rate(intervals: list[np.ndarray]) -> float:
    """One over the mean of the takes' sampling ``intervals`` (s), those above :data:`DROPPED` times
    their median (frames missing) left out; NaN where there are none."""
    d = np.concatenate(intervals or [np.zeros(0)])
    if not d.size:
        return float("nan")
    return float(1.0 / np.mean(d[d <= DROPPED * np.median(d)]))


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
    recording, :mod:`identified.recording.rates`), else ``None`` (the frames' own cells are the
    samples).  ``sources``: the file of each take where the recording joins several
    (:mod:`identified.recording.join`), else empty (every take is ``source``'s).  ``headers``: each
    file's header line and the names in its columns (:meth:`header_where`), one per file.
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
        """The frames' sampling rate over all takes, Hz: one over their mean interval, the gaps of
        dropped frames left out (intervals above :data:`DROPPED` times the median).  The mean, not
        the median: frames stamped on a clock of whole milliseconds lie 8, 8 and 9 ms apart at
        120 Hz (33, 33 and 34 at 30 Hz), and their median says 125 Hz (30.3)."""
        return _rate([np.diff(self.time[i]) for i in self.episodes()])

    def encoder_rate_hz(self) -> float:
        """The encoders' sampling rate over all takes, Hz, as :meth:`rate_hz` (the frames' where they
        are read at the frames)."""
        if self.encoders is None:
            return self.rate_hz()
        enc = self.encoders
        return _rate([np.diff(enc.time[enc.episode == e]) for e in range(self.n_episodes)])

    def missing_fraction(self) -> float:
        """Share of marker samples that are missing."""
        return float(np.isnan(self.markers[..., 0]).mean()) if self.markers.size else 0.0

    def with_markers(self, names: tuple[str, ...], markers: np.ndarray) -> Recording:
        """The same recording with other marker columns (after labelling)."""
        return replace(self, marker_names=tuple(names), markers=np.asarray(markers, dtype=float))


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
