"""Measured cable lengths (a recording's ``<tendon>.length`` columns, from stretch sensors or
encoders of a cable's path) checked against the lengths the markers give.

The fit needs no cable length: the markers place the rods, and the rods' sites give every cable's
length.  A sensor's own length is a second look at the same quantity, so it checks the recording:
a constant offset is the sensor's zero (reported, not an error); what is left after it is the
sensor's noise plus the markers' -- unless the column is named for another cable, the sensor
slipped, or the model's sites are not where the cable runs.  A cable whose measured length does
not follow the markers' (correlation below :data:`FOLLOWS`) is named in a warning.
"""

from __future__ import annotations

import numpy as np
import torch

from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.recording import Recording
from identified.topology import Topology

__all__ = ["FOLLOWS", "cable_length_check"]

#: the correlation over the frames between a cable's measured length and the markers' below which
#: the measurement does not follow the cable (a swapped column, a slipped sensor)
FOLLOWS = 0.9


def cable_length_check(rec: Recording, data, starts: list[float], topology: Topology) -> tuple[dict, list[str]]:
    """Each ``.length`` column of ``rec`` against its cable's length from the reconstructed states
    ``data`` (take ``e``'s state ``n`` at ``starts[e] + n dt``), at the frames those states cover.

    Returns ``(report, warnings)``: per cable its ``offset_m`` (measured minus markers, mean),
    ``rms_m`` (of the difference once the offset is removed), ``correlation`` and ``frames``."""
    springs = list(topology.spring_names)
    measured, from_markers = {n: [] for n in rec.length_names}, {n: [] for n in rec.length_names}
    for e, rows in enumerate(rec.episodes()):
        n = np.round((rec.time[rows] - starts[e]) / data.dt).astype(int)
        inside = (n >= 0) & (n <= data.n_steps)
        rows, n = rows[inside], n[inside]
        if not rows.size:
            continue
        t = lambda x: torch.as_tensor(x[e, n], dtype=torch.float64)  # noqa: B023 (used at once)
        ends = endpoint_kinematics(topology, t(data.pos), t(data.quat), t(data.vel), t(data.angvel))
        length = spring_geometry(ends).length.numpy()
        for j, name in enumerate(rec.length_names):
            ok = np.isfinite(rec.length[rows, j])
            measured[name].append(rec.length[rows, j][ok])
            from_markers[name].append(length[ok, springs.index(name)])
    report, warnings = {}, []
    for name in rec.length_names:
        a = np.concatenate(measured[name] or [np.zeros(0)])
        b = np.concatenate(from_markers[name] or [np.zeros(0)])
        if a.size < 3:
            report[name] = {"frames": int(a.size), "offset_m": None, "rms_m": None, "correlation": None}
            continue
        d = a - b
        corr = float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan")
        report[name] = {"frames": int(a.size), "offset_m": float(d.mean()), "rms_m": float(d.std()),
                        "correlation": corr}
        if not corr >= FOLLOWS:
            warnings.append(f"cable '{name}': its measured length ('{name}.length') does not follow the length the "
                            f"markers give (correlation {corr:.2f} over {a.size} frames, RMS {1e3 * d.std():.3g} mm "
                            "after the offset): a column named for another cable, a slipped sensor, or sites that "
                            "are not where the cable runs")
    return report, warnings
