"""Unlabelled markers labelled against the model: which marker is at which site, frame by frame.

Motion capture without a rigid-body definition gives anonymous markers (``marker17.x`` ...): their
identities swap (after impacts, occlusions) and reflections add ghost markers.  The labeller
keeps a prediction of every site and, in every frame, assigns the markers to the predictions by
the Hungarian algorithm (``scipy.optimize.linear_sum_assignment``, minimum total squared
distance), with a gate: a marker farther than the gate from every prediction is a ghost, a site
whose best marker is beyond the gate is missing in that frame.  Predictions are constant-velocity
extrapolations of each site's last two labelled positions (over at most :data:`EXTRAPOLATE`); the
gate grows with the time a site has been unseen.  Each rod's labelled markers are then checked rigidly: two markers of one rod must be
as far apart as the model's sites (within ``rigid_tol``); a pair that is not drops the marker
farther from its prediction.

The first frame of each take has no history: its markers are assigned to the sites of a reference
pose (the model's nominal pose, or the caller's), which must be within the gate of the truth.  A
site without a marker there is predicted at its reference position with the first frame's gate,
growing with the time since the take's start, until its marker shows.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from identified.recording.table import Recording, RecordingError
from identified.topology import Topology

__all__ = ["EXTRAPOLATE", "label_markers"]

#: the longest time (s) a site's last velocity is extrapolated over while it is unseen; beyond it
#: the gate's growth alone covers the motion (an end cap falling at 4 m/s, extrapolated over a
#: gap of 6 frames, was predicted out of reach for the rest of its take)
EXTRAPOLATE = 0.05


def label_markers(rec: Recording, topology: Topology, reference: np.ndarray, sites: tuple[str, ...] | None = None,
                  gate: float = 0.05, gate_rate: float = 2.0, rigid_tol: float = 0.02) -> Recording:
    """Label ``rec``'s anonymous markers with the sites ``sites`` (default: every rod site).

    ``reference`` (n_sites, 3): where the sites are at the start of every take (world frame, m).
    ``gate`` (m): the largest distance from a site's prediction at which a marker is taken for it,
    growing by ``gate_rate`` m/s of time unseen.  Returns the recording with one marker column per
    site (NaN where no marker passed the gate); RecordingError when a take cannot be started
    (too few markers near the reference)."""
    names = tuple(sites) if sites is not None else tuple(s for r in topology.rods for s in r.sites)
    ref = np.asarray(reference, dtype=float)
    if ref.shape != (len(names), 3):
        raise ValueError(f"reference must have shape ({len(names)}, 3), got {ref.shape}")
    where = {s: (i, r.site_offsets[k]) for i, r in enumerate(topology.rods) for k, s in enumerate(r.sites)}
    rod_of = np.array([where[n][0] for n in names])
    pairs = [(a, b, float(np.linalg.norm(where[names[a]][1] - where[names[b]][1])))
             for a in range(len(names)) for b in range(a + 1, len(names)) if rod_of[a] == rod_of[b]]
    out = np.full((rec.n_frames, len(names), 3), np.nan)
    for rows in rec.episodes():
        _label_take(rec, rows, ref, out, pairs, gate, gate_rate, rigid_tol)
    return rec.with_markers(names, out)


def _label_take(rec: Recording, rows: np.ndarray, ref: np.ndarray, out: np.ndarray, pairs, gate: float,
                gate_rate: float, rigid_tol: float) -> None:
    n = ref.shape[0]
    last = np.full((2, n, 3), np.nan)  # the last two labelled positions of each site
    last_t = np.full((2, n), np.nan)
    base = np.full(n, gate)  # each site's gate before its growth with the time unseen
    guessed = np.zeros(n, dtype=bool)  # last[0] is the reference, not a marker: no velocity from it
    for k, r in enumerate(rows):
        t = rec.time[r]
        obs = rec.markers[r]
        obs = obs[~np.isnan(obs[:, 0])]
        if k == 0:
            pred, g = ref, np.full(n, 4 * gate)
        else:
            have2 = ~np.isnan(last_t[1])
            vel = np.where(have2[:, None], (last[0] - last[1]) / np.where(have2, last_t[0] - last_t[1], 1.0)[:, None],
                           0.0)
            since = t - last_t[0]
            pred = last[0] + vel * np.minimum(np.nan_to_num(since), EXTRAPOLATE)[:, None]
            g = base + gate_rate * np.nan_to_num(since - np.nanmin(since))
        known = ~np.isnan(pred[:, 0])
        if obs.shape[0] == 0 or not known.any():
            continue
        d2 = ((pred[known][:, None, :] - obs[None, :, :]) ** 2).sum(-1)
        big = 1e6 * (1.0 + d2.max())
        cost = np.where(d2 <= (g[known] ** 2)[:, None], d2, big)
        ri, ci = linear_sum_assignment(cost)
        sites = np.flatnonzero(known)
        frame = np.full((n, 3), np.nan)
        for a, b in zip(ri, ci):
            if cost[a, b] < big:
                frame[sites[a]] = obs[b]
        for a, b, length in pairs:  # a rod's markers must be as far apart as its sites
            if np.isnan(frame[a, 0]) or np.isnan(frame[b, 0]):
                continue
            if abs(np.linalg.norm(frame[a] - frame[b]) - length) > rigid_tol:
                worse = a if np.sum((frame[a] - pred[a]) ** 2) > np.sum((frame[b] - pred[b]) ** 2) else b
                frame[worse] = np.nan
        if k == 0 and np.isnan(frame[:, 0]).mean() > 0.5:
            raise RecordingError(f"{rec.where(r)}: cannot label the markers: fewer than half "
                                 f"the sites have a marker within {4 * gate:g} m of the reference pose at the "
                                 "start of this take")
        out[r] = frame
        seen = ~np.isnan(frame[:, 0])
        last[1, seen], last_t[1, seen] = last[0, seen], np.where(guessed[seen], np.nan, last_t[0, seen])
        last[0, seen], last_t[0, seen] = frame[seen], t
        base[seen], guessed[seen] = np.where(np.isnan(last_t[1, seen]), 4 * gate, gate), False  # no velocity yet: wide
        if k == 0:  # a site hidden at the start is looked for around the reference, as in this frame
            last[0, ~seen], last_t[0, ~seen], base[~seen], guessed[~seen] = ref[~seen], t, 4 * gate, True
