"""Recordings whose encoders run faster than their cameras, written as one table: the encoder rows
between the camera frames told apart, and the frames the camera dropped put back as gaps."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from identified.recording.table import DROPPED, Encoders, Recording, RecordingError, with_encoders

__all__ = ["DROPPED", "split_rates"]


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
