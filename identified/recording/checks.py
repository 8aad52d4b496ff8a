"""A recording checked against a model: its site, tendon and actuator names, rods it cannot place,
markers in another unit than metres.  Every error one line naming the file, line and column."""

from __future__ import annotations

import numpy as np

from identified.recording.table import UNLABELLED, Recording, RecordingError
from identified.topology import Topology

__all__ = ["check_recording"]


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
