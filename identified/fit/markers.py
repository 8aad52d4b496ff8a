"""Rod states from a recording: markers at a lab's rate turned into the fit's equations at the
engine's step.

A recording holds markers at 30-120 Hz with noise and gaps, not rod states at every engine step.
The path here:

1. a smoothing spline through each marker coordinate over the frames where the marker is seen
   (``scipy.interpolate.make_smoothing_spline``, one smoothing for the recording chosen by
   generalised cross validation, :func:`recording_smoothing`), which also bridges the marker's gaps while the rod's other markers are seen;
2. each rod's pose at every engine step from its smoothed markers (:mod:`identified.recording.poses`:
   a rigid fit; for a rod whose markers lie on its axis, the axis and its position only);
3. the smooth poses sampled at the engine's step ``dt``; velocities as the backward differences of
   those samples, angular velocities as the rotation between consecutive samples over ``dt`` --
   so the recorded states step exactly as the engine's semi-implicit Euler steps them
   (``x[n+1] = x[n] + dt v[n+1]``), and the fit's forward-difference equations
   (:mod:`identified.samples`) are the engine's own discretisation of the reconstructed motion;
   each cable's rest length at the same instants, linear between its encoder's samples (at the
   encoders' own rate in a multi-rate recording, :meth:`identified.recording.Recording.rest_at`);
4. each rod's equations weighed out (``Dataset.weight``) near the frames where one of its markers
   is missing (:func:`_seen_weight`): a spline bridging a gap is no measurement of acceleration;
   and those of the rods it shares a cable with during its long gaps (a bridged position is no
   measurement of their cables' lengths either);
5. a rod whose markers lie on its axis has no observable spin about that axis: its frame is
   carried along the axis without axial rotation (parallel transport, ``ω·a = 0``), its axial
   moment of inertia is held (not identifiable) and reported as such.

The equations are then summed over windows (the weak form, :mod:`identified.fit.derivatives`),
which removes what the splines leave of the noise at high frequency.  What it leaves at low
frequency still sits in every regressor, and least squares on noisy regressors is biased (errors
in variables; measured on the robot, 100 Hz, mean K -0.1 %, -0.6 % and -3.2 % at 0.5, 1 and 2 mm
of noise).  So the reconstruction is repeated from the markers with fresh noise of their size
added, every spline with the smoothing chosen for the recording (:func:`noise_replicas`), and the
fit measures the noise of its equations from those copies (:mod:`identified.fit.noise`, the
errors-in-variables estimator of :mod:`identified.fit.regression`; the same robot at 1 mm with 2 %
missing: worst K 1.16 -> 0.28 %, RMS z of K 5.0 -> 1.0).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.spatial.transform import Rotation

from identified.dataset import Dataset, DatasetError
from identified.fit.regression import IdentifiabilityError
from identified.recording import Recording, RecordingError, check_recording
from identified.recording.poses import RodGeometry, fit_axis, fit_rigid, rod_geometries
from identified.rotation import quat_multiply, quat_to_matrix
from identified.topology import Topology

__all__ = ["MarkerStates", "diagnosis_options", "fit_recording", "recording_dataset", "recording_states",
           "states_from_recording"]

GRAVITY = (0.0, 0.0, -9.81)
#: frames before and after a contact whose smoothed states the joint fit leaves out (a spline
#: through sampled markers spreads an impact over about this many frames)
CONTACT_FRAMES = 3
#: frames on either side of a missing marker sample whose equations the fit leaves out (a spline
#: bridging the gap errs there too), and the frames of the ramp back to full weight after them
GAP_FRAMES = 2
#: a rod's gap of more than this many frames also weighs out the equations of the rods it shares a
#: cable with (with its GAP_FRAMES margin and ramp): the spline's bridged position, off by
#: centimetres over a long gap through an impact, sets those cables' forces (measured on the robot,
#: 10 x 10 s at 100 Hz, 1 mm, 2 % missing: one take's 0.37 s gap of one end cap left a neighbour's
#: mass 4.4 % off, and K 1.1 %; 0.5 % and 0.2 % with its partners' equations left out)
LONG_GAP_FRAMES = 10
#: marker noise (m) below which a recording counts as clean: its splines interpolate, and the fit
#: needs no noise replicas
CLEAN = 1e-7


@dataclass
class MarkerStates:
    """The dataset reconstructed from a recording and what the markers could not tell.

    ``unobservable``: (rod index, body axis) pairs whose rotation the markers cannot see;
    ``notes``: sentences for the model's metrics.
    """

    data: Dataset
    unobservable: list[tuple[int, int]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    geometries: list[RodGeometry] = field(default_factory=list)
    frames_used: int = 0
    starts: list[float] = field(default_factory=list)  # time (s, the recording's) of each take's first state
    marker_noise: float | None = None  # the noise std (m) the replicas were drawn with


def states_from_recording(rec: Recording, topology: Topology, dt: float = 0.001,
                          gravity: tuple[float, float, float] = GRAVITY, lam: float | None = None,
                          replicas: int = 0, seed: int = 0, measure_noise: bool = False,
                          actuators: tuple[str, ...] | None = None) -> MarkerStates:
    """Rod states at every ``dt`` from a labelled, checked recording (the module docstring).

    ``lam``: the splines' smoothing (``None``: generalised cross validation per coordinate).
    ``replicas``: this many copies of the reconstruction from the markers with fresh noise of the
    recording's size added (antithetic pairs; each spline with the smoothing chosen for the
    recording itself), carried as ``Dataset.replicas`` for the fit's errors in variables
    (:func:`noise_replicas`).  ``MarkerStates.marker_noise`` is measured (:func:`marker_noise`)
    where there are replicas or ``measure_noise`` asks for it.  ``actuators``: the MuJoCo actuators
    whose commands the recording must carry (``None``: the topology's,
    :attr:`~identified.topology.Topology.force_actuators`)."""
    motors = tuple(a.name for a in topology.force_actuators) if actuators is None else tuple(actuators)
    check_recording(rec, topology, motors)
    missing = [s for s in topology.spring_names if s not in rec.rest_names]
    if missing:
        raise RecordingError(f"{rec.header_where()}: no '{missing[0]}.rest' column: the fit needs every cable's "
                             f"rest length (encoder), {len(missing)} tendon(s) have none")
    silent = [a for a in motors if a not in rec.ctrl_names]
    if silent:
        raise RecordingError(f"{rec.header_where()}: no '{silent[0]}.ctrl' column: the model's MuJoCo actuators pull "
                             f"on its cables, and the fit needs the commands they were sent ({len(silent)} of "
                             f"{len(motors)} have none)")
    geos = rod_geometries(topology, tuple(rec.marker_names))
    col = {n: k for k, n in enumerate(rec.marker_names)}
    unobs, notes = [], []
    for i, g in enumerate(geos):
        if g.collinear:
            if np.linalg.norm(g.origin) > 1e-9:
                raise RecordingError(f"'{rec.source}': rod '{g.name}': its markers lie on a line that misses the "
                                     f"rod's origin by {100 * np.linalg.norm(g.origin):.3g} cm, so the origin's "
                                     "position is not observable from them (its spin about that line moves it): "
                                     "record a marker off that line (a site of the rod in the MJCF, and its column)")
            ax = int(np.argmax(np.abs(g.axis)))
            if abs(abs(g.axis[ax]) - 1.0) > 1e-9:
                raise RecordingError(f"'{rec.source}': rod '{g.name}': its markers lie on a line that is not a "
                                     "body axis; the axial inertia would not be a principal moment")
            unobs.append((i, ax))
            notes.append(f"{g.name}: spin about the rod's axis is not observable (its markers lie on the axis): "
                         "axial moment of inertia not identifiable")
    pieces, starts, spans = [], [], []
    smoothing: dict = {}  # (take, site, coordinate) -> the spline's smoothing, for the replicas
    takes = [_placed_span(rec, rows, geos, col) for rows in rec.episodes()]
    if lam is None:
        lam = recording_smoothing(rec, takes[0], geos[0].sites, col)
    for take, rows in enumerate(takes):
        t = rec.time[rows]
        n = int(np.floor((t[-1] - t[0]) / dt + 1e-9))
        if n < 3:
            raise RecordingError(f"{rec.where(int(rows[0]))}: a take of {t[-1] - t[0]:.3g} s is "
                                 "shorter than three engine steps")
        grid = t[0] + dt * np.arange(n + 1)  # one sample before the first state (velocities)
        pos, quat = _poses(rec, rows, geos, col, grid, lam, smoothing, take)
        rest = rec.rest_at(int(rec.episode[rows[0]]), grid[1:])[:, [rec.rest_names.index(s) for s in topology.spring_names]]
        weight = _seen_weight(rec, rows, geos, col, grid[1:], _partners(topology))
        ctrl = rec.ctrl_at(int(rec.episode[rows[0]]), grid[1:])[:, [rec.ctrl_names.index(a) for a in motors]]
        pieces.append(_states(pos, quat, dt) + (rest, weight, ctrl))
        starts.append(float(grid[1]))
        spans.append((rows, grid))
    T = min(p[0].shape[0] for p in pieces) - 1
    if T < 1:
        raise RecordingError(f"'{rec.source}': every take is too short to fit")
    data = _assemble(rec, topology, pieces, T, dt, gravity, motors)
    sigma = None
    if replicas > 0 or measure_noise:
        sigma = marker_noise(rec, spans, geos, col, smoothing)
    if sigma is not None and sigma > CLEAN:
        data = replace(data, replicas=noise_replicas(rec, geos, col, spans, smoothing, data, replicas, sigma, seed))
    return MarkerStates(data, unobs, notes, geos, rec.n_frames, starts, sigma)


def _states(pos: np.ndarray, quat: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """Positions, quaternions, velocities and angular velocities at the grid's instants 1.. from
    poses at every instant (instant 0 gives the first velocities)."""
    return pos[1:], quat[1:], np.diff(pos, axis=0) / dt, _angvel(quat, dt)


def noise_replicas(rec: Recording, geos: list[RodGeometry], col: dict[str, int], spans: list, smoothing: dict,
                   data: Dataset, copies: int, sigma: float, seed: int = 0) -> tuple[Dataset, ...]:
    """``copies`` reconstructions of ``data`` from the recording's markers with fresh Gaussian noise
    of std ``sigma`` (:func:`marker_noise`) added, in antithetic pairs ``±n``, every spline with
    the smoothing chosen for the recording: the scatter the splines, rigid fits and differences give
    the states (``Dataset.replicas``; :mod:`identified.fit.noise`)."""
    rng = np.random.default_rng([seed, 0x3A7])
    out = []
    draws = None
    for k in range(copies):
        if k % 2 == 0:
            draws = rng.standard_normal(rec.markers.shape)
        noisy = replace(rec, markers=rec.markers + (1.0 if k % 2 == 0 else -1.0) * sigma * draws)
        pieces = []
        for take, (rows, grid) in enumerate(spans):
            pos, quat = _poses(noisy, rows, geos, col, grid, None, smoothing, take, reuse=True)
            pieces.append(_states(pos, quat, data.dt))
        T = data.n_steps
        cut = lambda i, n: np.stack([p[i][:n] for p in pieces])  # noqa: B023 (used at once)
        out.append(replace(data, pos=cut(0, T + 1), quat=cut(1, T + 1), vel=cut(2, T + 1), angvel=cut(3, T + 1)))
    return tuple(out)


def marker_noise(rec: Recording, spans: list, geos: list[RodGeometry], col: dict[str, int], smoothing: dict) -> float:
    """The markers' noise std (m): the recording's own statement (``# noise_pos=``), else the RMS of
    what the splines leave of the visible samples (the fit's errors in variables take only the
    shape of the noise from it: each equation's noise level is fitted)."""
    if rec.stated_noise is not None:
        return rec.stated_noise
    # stated clean (0) or not stated: what the splines leave, which at a low rate is the error of
    # smoothing between samples (measured on the robot at 10 Hz, clean markers, 4 takes of 5 s:
    # without replicas worst K 12.3 % with RMS z 21; with them 1.0 % and 0.3)
    sq, n = 0.0, 0
    for take, (rows, _grid) in enumerate(spans):
        t = rec.time[rows]
        for g in geos:
            for s in g.sites:
                y = rec.markers[rows, col[s]]
                ok = np.isfinite(y).all(-1)
                for k in range(3):
                    fit = make_smoothing_spline(t[ok], y[ok, k], lam=smoothing[(take, s, k)])(t[ok])
                    sq += float(np.sum((y[ok, k] - fit) ** 2))
                    n += int(ok.sum())
    return float(np.sqrt(sq / max(n, 1)))


def _assemble(rec: Recording, topology: Topology, pieces: list, T: int, dt: float,
              gravity: tuple[float, float, float], motors: tuple[str, ...] = ()) -> Dataset:
    """The dataset of the takes' reconstructed ``pieces``, each cut to ``T`` steps; ``motors``:
    the MuJoCo actuators whose commands the pieces carry."""
    cut = lambda k, s: np.stack([p[k][:s] for p in pieces])
    R = topology.n_rods
    E = len(pieces)
    act = tuple(s.name for s in topology.springs if s.actuated)
    rest = cut(4, T)
    data = Dataset(dt=float(dt), gravity=np.asarray(gravity, dtype=float), rod_names=topology.rod_names,
                   tendon_names=topology.spring_names, actuated_names=act,
                   pos=cut(0, T + 1), quat=cut(1, T + 1), vel=cut(2, T + 1), angvel=cut(3, T + 1),
                   command=rest[..., [topology.spring_names.index(a) for a in act]], rest_length=rest,
                   push_force=np.zeros((E, T, R, 3)), push_point=np.zeros((E, T, R, 3)), weight=cut(5, T),
                   actuator_names=motors, ctrl=cut(6, T))
    try:
        data.validate()
    except DatasetError as exc:
        raise RecordingError(f"'{rec.source}': the reconstructed states are not usable: {exc}") from None
    return data


def _placed_span(rec: Recording, rows: np.ndarray, geos: list[RodGeometry], col: dict[str, int]) -> np.ndarray:
    """The rows of a take from the first frame where every rod is placed to the last such frame:
    the splines bridge gaps inside, never extrapolate beyond."""
    ok = np.ones(rows.size, dtype=bool)
    for g in geos:
        seen = (~np.isnan(rec.markers[np.ix_(rows, [col[s] for s in g.sites])][..., 0])).sum(-1)
        ok &= seen >= (2 if g.collinear else 3)
    if ok.sum() < 2:
        raise RecordingError(f"{rec.where(int(rows[0]))}: no two frames of this take place "
                             "every rod")
    first, last = np.flatnonzero(ok)[[0, -1]]
    return rows[first:last + 1]


def _partners(topology: Topology) -> list[set[int]]:
    """For each rod, the other rods it shares a cable or spring with."""
    out: list[set[int]] = [set() for _ in range(topology.n_rods)]
    for s in topology.springs:
        a, b = s.rods
        if a >= 0 and b >= 0 and a != b:
            out[a].add(b)
            out[b].add(a)
    return out


def _seen_weight(rec: Recording, rows: np.ndarray, geos: list[RodGeometry], col: dict[str, int],
                 grid: np.ndarray, partners: list[set[int]] | None = None) -> np.ndarray:
    """(G, R) weight of each rod's equations at the ``grid`` instants: 0 from :data:`GAP_FRAMES`
    frames before a frame where one of the rod's markers is missing to as many after it, rising to
    1 over the next :data:`GAP_FRAMES` frames as a Hann ramp; the same about the gaps of more than
    :data:`LONG_GAP_FRAMES` frames of the rods it shares a cable with (``partners``).

    Inside a gap a marker's spline is an interpolation, not a measurement: its second derivative
    there -- the rod's acceleration in the equations -- can be off by the whole acceleration of an
    impact or a cable's snap (measured on the robot, 4 takes of 5 s at 100 Hz with 2 % missing:
    clean markers, largest error of M 1.44 % and of c 3.12 % with the gaps' equations, 0.27 % and
    2.07 % without; 1 mm of noise, M 10.4 % and 1.00 %, K 4.32 % and 1.16 %).  The fit's equations hold wherever
    they are weighed, so leaving those steps out costs data, never exactness; the smooth ramp keeps
    the weak form's summation by parts (:mod:`identified.fit.derivatives`) from turning the edge
    into a difference of noisy velocities."""
    t = rec.time[rows]
    f = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)  # frame at or before each instant
    def weight(missing: np.ndarray) -> np.ndarray:
        near = _distance(missing)  # frames from the nearest missing one
        # an instant between frames f and f + 1 is as far as the nearer of the two
        d = np.minimum(near[f], near[np.minimum(f + 1, t.size - 1)]).astype(float)
        ramp = np.clip((d - GAP_FRAMES) / GAP_FRAMES, 0.0, 1.0)
        return np.where(d <= GAP_FRAMES, 0.0, 0.5 - 0.5 * np.cos(np.pi * ramp))

    out = np.ones((grid.size, len(geos)))
    for i, g in enumerate(geos):
        missing = np.isnan(rec.markers[np.ix_(rows, [col[s] for s in g.sites])][..., 0]).any(-1)
        out[:, i] = np.minimum(out[:, i], weight(missing))
        long = _long_runs(missing, LONG_GAP_FRAMES)
        if partners and long.any():
            w = weight(long)
            for j in partners[i]:
                out[:, j] = np.minimum(out[:, j], w)
    return out


def _long_runs(mask: np.ndarray, n: int) -> np.ndarray:
    """``mask`` with only its runs of more than ``n`` true entries kept."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    start, stop = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = np.zeros_like(mask, dtype=bool)
    for a, b in zip(start, stop):
        if b - a > n:
            out[a:b] = True
    return out


def _distance(mask: np.ndarray) -> np.ndarray:
    """Distance (in entries) of every entry to the nearest true entry of ``mask``."""
    n = mask.size
    last = np.where(mask, np.arange(n), -(10 ** 9))
    last = np.maximum.accumulate(last)
    nxt = np.where(mask, np.arange(n), 10 ** 9)[::-1]
    nxt = np.minimum.accumulate(nxt)[::-1]
    return np.minimum(np.arange(n) - last, nxt - np.arange(n))


def _smooth(t: np.ndarray, y: np.ndarray, grid: np.ndarray, lam: list[float | None]) -> np.ndarray:
    """(F, k) values with NaN rows -> (G, k) on ``grid``: a smoothing spline per column, with the
    smoothing ``lam[k]`` (``None``: by generalised cross validation; the value chosen is written
    back into ``lam``)."""
    ok = np.isfinite(y).all(-1)
    if ok.sum() < 5:
        raise RecordingError("a marker is seen in fewer than 5 frames of the take")
    if all(x is not None for x in lam) and len(set(lam)) == 1:
        # one smoothing for every column: one spline of the columns together (the same linear
        # smoother, whose basis scipy builds in a pure-Python loop once instead of per column)
        return make_smoothing_spline(t[ok], y[ok], lam=lam[0])(grid)
    out = np.empty((grid.size, y.shape[1]))
    for k in range(y.shape[1]):
        if lam[k] is None:
            lam[k] = gcv_smoothing(t[ok], y[ok, k])
        out[:, k] = make_smoothing_spline(t[ok], y[ok, k], lam=lam[k])(grid)
    return out


def recording_smoothing(rec: Recording, rows: np.ndarray, sites: tuple[str, ...], col: dict[str, int]) -> float | None:
    """One smoothing for every spline of the recording: the median of the choices of generalised
    cross validation for the coordinates of ``sites`` over the take ``rows``.  Markers sampled
    alike with one sensor's noise get one choice (on the robot at 100 Hz and 1 mm, the 36
    coordinates of a take chose within 5 % of each other), and the choice costs scipy a
    pure-Python pass per trial value: made once, not per coordinate and take."""
    t = rec.time[rows]
    lams = []
    for s in sites:
        y = rec.markers[rows, col[s]]
        ok = np.isfinite(y).all(-1)
        if ok.sum() < 5:
            continue
        lams += [gcv_smoothing(t[ok], y[ok, k]) for k in range(3)]
    lams = [x for x in lams if x is not None]
    return float(np.median(lams)) if lams else None


def gcv_smoothing(t: np.ndarray, y: np.ndarray) -> float | None:
    """The smoothing (``lam`` of :func:`scipy.interpolate.make_smoothing_spline`) that generalised
    cross validation chooses for the samples ``y`` at ``t`` (Craven and Wahba 1979): scipy's own
    choice, read back so that the same smoother can be applied to other data (``None`` where this
    scipy does not expose it: each spline then chooses its own)."""
    from scipy.interpolate import _bsplines

    chosen: list[float] = []
    gcv = getattr(_bsplines, "_compute_optimal_gcv_parameter", None)
    if gcv is None:
        return None

    def keep(*args, **kwargs):
        chosen.append(float(gcv(*args, **kwargs)))
        return chosen[-1]

    _bsplines._compute_optimal_gcv_parameter = keep
    try:
        make_smoothing_spline(t, y)
    finally:
        _bsplines._compute_optimal_gcv_parameter = gcv
    return chosen[0]


def _poses(rec: Recording, rows: np.ndarray, geos: list[RodGeometry], col: dict[str, int], grid: np.ndarray,
           lam: float | None, smoothing: dict | None = None, take: int = 0,
           reuse: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's trajectory smoothed over its own visible frames (so one marker's gap is
    bridged while the rod's other markers are still seen), then each rod fitted rigidly to its
    smoothed markers at every grid instant.  ``smoothing``: each spline's smoothing by (take, site,
    coordinate), filled in (or, with ``reuse``, read)."""
    t = rec.time[rows]
    R = len(geos)
    pos = np.empty((grid.size, R, 3))
    quat = np.empty((grid.size, R, 4))
    smoothing = {} if smoothing is None else smoothing

    def smoothed(s: str) -> np.ndarray:
        lams = [smoothing[(take, s, k)] for k in range(3)] if reuse else [lam] * 3
        out = _smooth(t, rec.markers[rows, col[s]], grid, lams)
        smoothing.update({(take, s, k): lams[k] for k in range(3)})
        return out

    for i, g in enumerate(geos):
        try:
            pts = np.stack([smoothed(s) for s in g.sites], axis=1)
        except RecordingError as exc:
            raise RecordingError(f"{rec.where(int(rows[0]))}: rod '{g.name}': {exc}") from None
        w = np.ones(len(g.sites))
        if g.collinear:
            point, direction = fit_axis(pts, g.along, w)
            pos[:, i] = point
            quat[:, i] = _transport(direction, g.axis)
        else:
            c, rot = fit_rigid(pts, g.offsets, w)
            q = _continuous(Rotation.from_matrix(rot).as_quat()[:, [3, 0, 1, 2]])
            pos[:, i] = c
            quat[:, i] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return pos, quat


def _continuous(q: np.ndarray) -> np.ndarray:
    """Quaternion signs made continuous over the fitted frames (q and -q are the same rotation)."""
    q = q.copy()
    prev = None
    for f in range(q.shape[0]):
        if not np.isfinite(q[f, 0]):
            continue
        if prev is not None and q[f] @ prev < 0:
            q[f] = -q[f]
        prev = q[f]
    return q


def _arc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shortest-arc unit quaternions (..., 4) turning unit vectors ``a`` into ``b`` (..., 3)."""
    d = np.einsum("...i,...i->...", a, b)
    q = np.concatenate([(1.0 + d)[..., None], np.cross(a, b)], axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _transport(a: np.ndarray, body_axis: np.ndarray) -> np.ndarray:
    """(G, 4) frames whose ``body_axis`` follows the world directions ``a`` (G, 3) without spin about it."""
    q0 = _arc(body_axis, a[0])
    turn = _arc(a[:-1], a[1:])  # turn[k] takes a[k] to a[k + 1]
    # inclusive scan turn[k] ... turn[0] (Hillis and Steele 1986): log2(G) vectorised passes
    shift = 1
    while shift < turn.shape[0]:
        nxt = turn.copy()
        nxt[shift:] = quat_multiply(turn[shift:], turn[:-shift])
        turn = nxt / np.linalg.norm(nxt, axis=-1, keepdims=True)
        shift *= 2
    q = np.concatenate([q0[None], quat_multiply(turn, q0[None])])
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _angvel(quat: np.ndarray, dt: float) -> np.ndarray:
    """World angular velocities (G-1, R, 3) taking ``quat[n-1]`` to ``quat[n]`` in ``dt`` (the
    rotation over the step, as the engine's quaternion update makes it)."""
    conj = quat[:-1] * np.array([1.0, -1.0, -1.0, -1.0])
    d = quat_multiply(conj, quat[1:])  # body-frame increment
    d = np.where(d[..., :1] < 0, -d, d)
    s = np.linalg.norm(d[..., 1:], axis=-1)
    angle = 2.0 * np.arctan2(s, d[..., 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = np.where(s[..., None] > 1e-15, d[..., 1:] / s[..., None], 0.0)
    w_body = axis * (angle / dt)[..., None]
    return np.einsum("...ij,...j->...i", quat_to_matrix(quat[1:]), w_body)


def labelled(rec: Recording, topology: Topology, mjcf: str) -> Recording:
    """``rec`` with site-named marker columns: as it is, or labelled against the model's nominal
    pose when its markers are anonymous (:mod:`identified.recording.labelling`)."""
    if not rec.unlabelled:
        return rec
    from identified.mjcf import nominal_pose, read_mjcf_text
    from identified.recording import site_world_positions
    from identified.recording.labelling import label_markers

    sites = tuple(s for r in topology.rods for s in r.sites)
    pose = nominal_pose(read_mjcf_text(mjcf), topology.rod_names)
    ref = site_world_positions(topology, pose.pos, pose.quat, sites)
    return label_markers(rec, topology, ref, sites)


def fit_recording(rec: Recording, mjcf: str, dt: float = 0.001, gravity: tuple[float, float, float] = GRAVITY,
                  weak_window: int | None = None, noise_copies: int = 1, output_error: bool | dict = False,
                  **fit_kwargs):
    """Identify a model from a recording: labelled if need be, rod states reconstructed
    (:func:`states_from_recording`), then :func:`identified.fit.pipeline.fit_model` with the weak
    form and the unobservable moments held.  ``fit_kwargs`` go to ``fit_model``.  ``output_error``
    (true, or the options of :func:`identified.fit.output_error.refine_markers`): then K, c, M and
    the observable moments refined against the markers themselves.  A ground contact law's friction
    damping is then chosen by the short free runs from the reconstructed states
    (:mod:`identified.fit.contact_damping`).  Where the identified robot oscillates faster than half
    the recording's rate, the dampings', masses' and moments' standard errors are withheld and a
    warning says why (:mod:`identified.fit.sampling_rate`; ``metrics.recording.fastest_oscillation_hz``)."""
    from identified.fit.derivatives import default_window
    from identified.fit.identify import shortest_cut_take
    from identified.fit.pipeline import fit_model
    from identified.fit.sampling_rate import fastest_oscillation, withhold_unresolved
    from identified.fit.uncertainty import MIN_BLOCK_SECONDS, MIN_BLOCK_WINDOWS, MIN_RUNS

    topo = Topology.from_mjcf(mjcf)
    rec = labelled(rec, topo, mjcf)
    ms = states_from_recording(rec, topo, dt, gravity, replicas=noise_copies)
    window = weak_window or default_window(dt)
    if ms.data.n_steps < 2 * window:
        raise RecordingError(f"'{rec.source}': takes of {ms.data.n_steps * dt:.3g} s are too short: the fit sums "
                             f"its equations over {window * dt:.2g} s windows and needs takes of at least "
                             f"{2 * window * dt:.2g} s")
    margin = int(np.ceil(CONTACT_FRAMES / (rec.rate_hz() * dt)))
    from identified.fit.contact_damping import refine_friction_damping

    damping: list[dict | None] = [None]

    def contact_damping(model) -> None:  # the contact's friction damping, from short free runs
        damping[0] = refine_friction_damping(model, ms.data, jobs=fit_kwargs.get("jobs", "auto"))

    try:
        model = fit_model(ms.data, mjcf, weak_window=window, hold_inertia=ms.unobservable, contact_margin=margin,
                          before_metrics=contact_damping, **fit_kwargs)  # the metrics are those of the law as refined
    except IdentifiabilityError as exc:
        raise _on_the_ground(exc, mjcf, topo, ms.data) from None
    model.metrics["recording"] = {"source": rec.source, "frames": rec.n_frames, "takes": rec.n_episodes,
                                  "rate_hz": rec.rate_hz(), "missing": rec.missing_fraction(),
                                  "labelled_automatically": rec.unlabelled, "notes": ms.notes,
                                  "noise_replicas": len(ms.data.replicas), "marker_noise": ms.marker_noise}
    if damping[0] is not None:
        model.metrics["recording"]["friction_damping"] = damping[0]
    if rec.length_names:  # the cables' measured lengths against the markers' (a check; the fit needs none)
        from identified.fit.cable_lengths import cable_length_check

        report, warnings = cable_length_check(rec, ms.data, ms.starts, topo)
        model.metrics["recording"]["cable_lengths"] = report
        model.metrics.setdefault("warnings", []).extend(warnings)
    if output_error:
        from identified.fit.output_error import refine_markers

        opts = output_error if isinstance(output_error, dict) else {}
        model = refine_markers(model, rec, ms.data, ms.starts, mjcf, ms.unobservable, sigma=ms.marker_noise,
                               progress=bool(fit_kwargs.get("progress")), **opts)
        from identified.fit.checks import refresh_physics
        from identified.predict import attach_metrics

        refresh_physics(model)  # the checks and errors of the refined values
        attach_metrics(model, ms.data)
    if str(model.metrics.get("stderr", "")).startswith("iid rows"):
        # too few takes for the jackknife over them, and too short to cut into enough blocks
        # (:func:`identified.fit.identify.run_blocks`): the rows' error bars, which on splined states
        # under-cover (6 takes of 4 s at 100 Hz, 0.5 mm, uncut: RMS z 2.9 for c, 3.1 for M)
        block = max(MIN_BLOCK_SECONDS, MIN_BLOCK_WINDOWS * window * dt)
        need = shortest_cut_take(rec.n_episodes, dt, window)  # the shortest takes that are cut
        if need is not None and need <= ms.data.n_steps:
            # these takes are longer and still not cut (the fit's chunks cut a long take, and their
            # last piece is a run of its own): longer ones that are
            need = shortest_cut_take(rec.n_episodes, dt, window, at_least=ms.data.n_steps + 1)
        takes = "" if need is None else f", or takes of {need * dt:.2g} s"
        model.metrics.setdefault("warnings", []).append(
            f"only {rec.n_episodes} take(s) of {ms.data.n_steps * dt:.3g} s, too short to cut into {MIN_RUNS} "
            f"blocks of {block:.2g} s for the jackknife: the standard errors are the equations' as if "
            f"independent, which on reconstructed states are too small (record {MIN_RUNS} takes{takes}, for "
            "error bars that cover)")
    # on the model returned, refined or not: the refinement's windows start from the same splined
    # states, and its error bars at a rate the robot outruns were never shown to cover
    fastest = fastest_oscillation(model, ms.data)
    model.metrics["recording"]["fastest_oscillation_hz"] = fastest
    withhold_unresolved(model, rec.rate_hz(), fastest)
    return model


#: the share of the rod-instants on the ground (within the contact margin) above which a regression
#: that cannot identify the robot says why (:func:`_on_the_ground`)
MOSTLY_ON_THE_GROUND = 0.5


def _on_the_ground(exc: IdentifiabilityError, mjcf: str, topology: Topology, data: Dataset) -> IdentifiabilityError:
    """``exc`` (the regression cannot identify some parameters) with the cause where the rods touch
    the ground most of the time: the regression fits K, c and M on the rods off the ground (a contact
    law is fitted on the residual of the others), and the marker fit simulates the contact instead
    (measured: the 3-bar prism of ``examples/``, its bars always standing, was refused from a clean
    recording at 100, 250 and 1000 Hz, with "excite these with more varied motion")."""
    from identified.effects.ground_contact import CONTACT_MARGIN
    from identified.fit.output_error import near_ground

    near = near_ground(mjcf, topology, data)  # within CONTACT_MARGIN: where the regression leaves a rod's rows out
    share = float(near.mean()) if near is not None and near.size else 0.0
    if share <= MOSTLY_ON_THE_GROUND:
        return exc
    return IdentifiabilityError(f"{exc}; but the rods are on the ground (within {100 * CONTACT_MARGIN:g} cm) at "
                                f"{100 * share:.0f} % of the "
                                "instants, and the regression fits K, c and M on the rods off it: fit through the engine, "
                                "which simulates the contact (add --refine, with --start MODEL.json: a model of this "
                                "robot, an earlier fit or its design values)", exc.names)


def recording_dataset(path: str | Recording, model) -> Dataset:
    """The rod states of the recording at ``path`` (or the recording itself) at the step of an
    identified ``model`` (whose topology names the sites), for prediction and diagnosis on a recording."""
    return recording_states(path, model).data


def recording_states(path: str | Recording, model, noise: bool = False) -> MarkerStates:
    """:func:`recording_dataset` with what the reconstruction knows (``noise``: also the markers'
    noise, ``MarkerStates.marker_noise``: the recording's statement, else what the splines leave)."""
    from identified.recording import load_recording

    rec = load_recording(path) if isinstance(path, str) else path
    if rec.unlabelled:
        if not model.source_model:
            raise RecordingError(f"'{rec.source}': unlabelled markers need the model's MJCF to be labelled")
        rec = labelled(rec, model.topology, model.source_model)
    return states_from_recording(rec, model.topology, model.dt, tuple(model.gravity), measure_noise=noise,
                                 actuators=tuple(a["name"] for a in model.actuators))


def diagnosis_options(rec: Recording, dt: float) -> dict[str, int]:
    """How :func:`identified.diagnose.diagnose` scores its candidate effects on the states
    reconstructed from ``rec`` at step ``dt``, as the fit reads them: on the weak form of the
    equations (0.3 s windows, :func:`identified.fit.derivatives.default_window`: the splines'
    second derivatives carry the markers' noise, which a window's sum removes), leaving out the
    rows within :data:`CONTACT_FRAMES` frames of a contact (a spline spreads an impact over them)."""
    from identified.fit.derivatives import default_window

    return {"weak_window": default_window(dt), "contact_margin": int(np.ceil(CONTACT_FRAMES / (rec.rate_hz() * dt)))}
