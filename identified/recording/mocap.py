"""Files from motion-capture software read as recordings: C3D and OptiTrack Motive CSV exports.

* **C3D** (Vicon, Qualisys, OptiTrack and others; read with ``ezc3d``, the optional extra
  ``c3d``): point labels are marker names (a ``Subject:`` prefix is dropped), units from
  ``POINT:UNITS`` (``mm`` or ``m``), missing samples where the point's residual is negative or its
  coordinates are not finite.  Analog channels labelled ``<tendon>.rest``, ``<actuator>.ctrl`` or
  ``<tendon>.length`` become those columns: at the point frames where the analogs run at the
  points' rate, else as encoder samples at their own rate (:class:`~identified.recording.Encoders`,
  interpolated at the frames).  C3D is z-up by custom;
  ``up="y"`` converts a y-up file.
* **Motive CSV** (OptiTrack's export): the header block (``Length Units``), the ``Type`` / ``Name``
  / ``Position`` rows, then ``Frame, Time (Seconds), X, Y, Z, ...``.  Only ``Marker`` (and
  ``Rigid Body Marker``) position columns are read; Motive is y-up by default (``up="y"``, the
  default here, maps Motive's (x, y, z) to (x, -z, y)); unlabelled markers (``Unlabeled 1001``)
  become ``marker<N>`` columns.

Names that are not MJCF sites are kept as they are (then labelled against the model, or refused by
:func:`identified.recording.check_recording`).
"""

from __future__ import annotations

import csv
import io
import os
import re

import numpy as np

from identified.recording.format import not_text
from identified.recording.table import Encoders, Recording, RecordingError, with_encoders

__all__ = ["read_c3d", "read_motive_csv"]

_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # (x, y, z) y-up -> z-up


def _up(points: np.ndarray, up: str, source: str) -> np.ndarray:
    if up == "z":
        return points
    if up == "y":
        return points @ _Y_UP.T
    raise RecordingError(f"'{source}': up axis must be 'y' or 'z', got '{up}'")


def _marker_name(label: str, k: int) -> str:
    name = label.strip().split(":")[-1].strip()
    if not name or re.match(r"^(unlabeled|unlabelled|\*)\s*\d*$", name, re.IGNORECASE):
        digits = re.findall(r"\d+", name)
        return f"marker{digits[-1] if digits else k}"
    return re.sub(r"\s+", "_", name)


def read_c3d(path: str | os.PathLike, up: str = "z") -> Recording:
    """A C3D file as a recording (the module docstring)."""
    p = os.fspath(path)
    try:
        import ezc3d
    except ImportError:
        raise RecordingError(f"reading '{p}' needs the ezc3d package: pip install 'tensegrity-gym[c3d]'") from None
    if not os.path.isfile(p):
        raise RecordingError(f"recording '{p}' does not exist")
    try:
        c = ezc3d.c3d(p, extract_forceplat_data=False)
    except (RuntimeError, OSError, ValueError, IndexError) as exc:  # ezc3d on a foreign file
        raise RecordingError(f"'{p}' is not a readable C3D file: {str(exc).strip() or type(exc).__name__}") from None
    params = c["parameters"]
    labels = list(params["POINT"]["LABELS"]["value"])
    units = str((params["POINT"].get("UNITS", {}).get("value") or ["m"])[0]).strip().lower()
    scale = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}.get(units)
    if scale is None:
        raise RecordingError(f"'{p}': POINT:UNITS is '{units}'; this reader knows mm, cm and m")
    rate = float(c["header"]["points"]["frame_rate"])
    pts = np.asarray(c["data"]["points"], dtype=float)[:3]  # (3, n, F)
    F = pts.shape[-1]
    if F == 0 or not labels:
        raise RecordingError(f"'{p}' holds no marker frames")
    resid = np.asarray(c["data"]["meta_points"]["residuals"], dtype=float).reshape(-1, F) \
        if "meta_points" in c["data"] else np.zeros((len(labels), F))
    markers = np.transpose(pts, (2, 1, 0)) * scale  # (F, n, 3)
    markers[(resid.T < 0) | ~np.isfinite(markers).all(-1)] = np.nan
    markers = _up(markers, up, p)
    names = [_marker_name(lbl, k) for k, lbl in enumerate(labels)]
    cols: dict[str, dict[str, np.ndarray]] = {"rest": {}, "ctrl": {}, "length": {}}
    alabels = list(params.get("ANALOG", {}).get("LABELS", {}).get("value", []) or [])
    first = int(c["header"]["points"].get("first_frame", 0))
    time = (first + np.arange(F)) / rate
    per = 1
    if alabels:
        analogs = np.asarray(c["data"]["analogs"], dtype=float)[0]  # (channels, samples)
        per = max(1, analogs.shape[-1] // F)
        for k, lbl in enumerate(alabels):
            base, _, kind = lbl.strip().rpartition(".")
            if kind in cols and base:
                cols[kind][base] = analogs[k, :per * F]
    if per == 1:
        return _recording(p, time, np.zeros(F, dtype=np.int64), names, markers, cols)
    # analogs faster than the points: every sample kept as the encoders' own, the frames' cells from them
    atime = (first + np.arange(per * F) / per) / rate
    enc = Encoders(atime, np.zeros(per * F, dtype=np.int64), *(_stacked(cols[k], per * F) for k in ("rest", "ctrl", "length")))
    frames = _recording(p, time, np.zeros(F, dtype=np.int64), names, markers,
                        {kind: {n: np.full(F, np.nan) for n in d} for kind, d in cols.items()})
    return with_encoders(frames, enc)


def read_motive_csv(path: str | os.PathLike, up: str = "y") -> Recording:
    """An OptiTrack Motive CSV export as a recording (the module docstring)."""
    p = os.fspath(path)
    try:
        with open(p, encoding="utf-8-sig", newline="") as fh:
            rows = list(csv.reader(io.StringIO(fh.read())))
    except FileNotFoundError:
        raise RecordingError(f"recording '{p}' does not exist") from None
    except UnicodeDecodeError as exc:
        raise RecordingError(not_text(p, exc)) from None
    except OSError as exc:
        raise RecordingError(f"cannot read '{p}': {exc.strerror or exc}") from None
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        raise RecordingError(f"'{p}' is not a Motive CSV export (its first cell is not 'Format Version')")
    meta = {rows[0][i].strip(): rows[0][i + 1].strip() for i in range(0, len(rows[0]) - 1, 2)}
    units = meta.get("Length Units", "Meters").lower()
    scale = 1e-3 if units.startswith("milli") else 1e-2 if units.startswith("centi") else 1.0
    head = next((i for i, r in enumerate(rows) if len(r) > 1 and r[0].strip() == "Frame"), None)
    if head is None:
        raise RecordingError(f"'{p}': no 'Frame, Time (Seconds), ...' row: not a Motive CSV export")
    at = lambda key: next((i for i in range(head) if len(rows[i]) > 1 and rows[i][1].strip() == key), None)
    label = lambda key: None if at(key) is None else rows[at(key)]
    type_row, name_row = label("Type"), label("Name")
    kind_row = next((rows[i] for i in range(head) if any(c.strip() == "Position" for c in rows[i])), None)
    if type_row is None or name_row is None or kind_row is None:
        raise RecordingError(f"'{p}': the 'Type', 'Name' or 'Position' row above line {head + 1} is missing: "
                             "not a Motive CSV export")
    axes = rows[head]
    cols: dict[str, list[int]] = {}
    for j in range(2, len(axes)):
        typ = type_row[j].strip() if j < len(type_row) else ""
        if "Marker" not in typ or j >= len(kind_row) or kind_row[j].strip() != "Position":
            continue
        name = _marker_name(name_row[j], j)
        axis = axes[j].strip().upper()
        if axis in ("X", "Y", "Z"):
            cols.setdefault(name, [0, 0, 0])["XYZ".index(axis)] = j
    if not cols:
        raise RecordingError(f"'{p}': no marker position columns (Type 'Marker', 'Position', X/Y/Z)")
    data = rows[head + 1:]
    F = len(data)
    time = np.empty(F)
    markers = np.full((F, len(cols), 3), np.nan)
    names = list(cols)
    for f, row in enumerate(data):
        line = head + 2 + f
        try:
            time[f] = float(row[1])
        except (IndexError, ValueError):
            raise RecordingError(f"'{p}', line {line}, column 'Time (Seconds)': not a number") from None
        for m, name in enumerate(names):
            cells = [row[j].strip() if j < len(row) else "" for j in cols[name]]
            if all(cells):
                try:
                    markers[f, m] = [float(x) for x in cells]
                except ValueError:
                    raise RecordingError(f"'{p}', line {line}, column '{name}': not a number") from None
    markers = _up(markers * scale, up, p)
    return _recording(p, time, np.zeros(F, dtype=np.int64), names, markers,
                      {"rest": {}, "ctrl": {}, "length": {}}, lines=head + 2 + np.arange(F),
                      headers=((p, at("Name") + 1, frozenset(names)),))  # the markers' names: the 'Name' row


def _recording(source: str, time: np.ndarray, episode: np.ndarray, names: list[str], markers: np.ndarray,
               cols: dict[str, dict[str, np.ndarray]], lines: np.ndarray | None = None,
               headers: tuple = ()) -> Recording:
    bad = np.flatnonzero(~(np.diff(time) > 0))
    if bad.size:
        raise RecordingError(f"'{source}', frame {int(bad[0]) + 1}: time {time[bad[0] + 1]:g} s is not after "
                             f"the previous frame's {time[bad[0]]:g} s")
    F = time.shape[0]
    return Recording(time=time, episode=episode, marker_names=tuple(names), markers=markers,
                     rest_names=tuple(cols["rest"]), rest=_stacked(cols["rest"], F),
                     ctrl_names=tuple(cols["ctrl"]), ctrl=_stacked(cols["ctrl"], F),
                     length_names=tuple(cols["length"]), length=_stacked(cols["length"], F),
                     source=source, lines=lines, headers=headers)


def _stacked(columns: dict[str, np.ndarray], n: int) -> np.ndarray:
    """(n, len(columns)) the named columns side by side."""
    return np.stack(list(columns.values()), axis=1) if columns else np.zeros((n, 0))
