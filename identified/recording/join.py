"""Several files as the takes of one recording (motion-capture software writes a file per take)."""

from __future__ import annotations

import numpy as np

from identified.recording.table import Encoders, Recording, RecordingError

__all__ = ["join_recordings"]


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
