"""Output-error refinement against the markers: the spring-rod parameters that best predict the
recorded marker positions through the engine's own steps.

The regression (:mod:`identified.fit.regression`) fits equations built from states that splines
reconstruct from the markers (:mod:`identified.fit.markers`).  Its estimate is consistent but not
efficient: the splines spread every impact, gap and cable snap over several frames, and the
equations near them are weighed out.  Here the markers themselves are the measurement:

* the recording is cut into windows of ``frames`` consecutive frames (each frame in one window), each
  frame read at its own time, between the engine's steps where the camera's clock puts it
  (:func:`frame_weights`);
* in each window the rods are stepped by the identified engine (semi-implicit Euler at the fit's
  ``dt``, or at up to ``substeps`` of it: :func:`coarse_steps`; the encoders' rest lengths and the
  MuJoCo actuators' forces from the recorded commands as the inputs, the actuators' biases and
  time constants held at the model's, their gains too unless they are unknowns, ``free_gains`` of
  :func:`window_problem`) from a *free* initial state per window and rod
  (position, rotation, velocity, angular velocity: multiple shooting, so no error accumulates from
  one window into the next), and each site's simulated position is compared with its marker at
  every frame where it is seen;
* a rod near the ground during a window (an end sphere within ``CONTACT_MARGIN`` of it, as in the
  regression) feels, besides its cables and gravity, a free wrench from the ground in that window,
  linear in time (``order=2``; ``1``: constant): the contact law is not needed to fit the
  spring-rod parameters, and a contact law's error cannot bias them.  (``order=0`` moves such a
  rod as the smoothed states say instead, out of the cost: cheaper, but its cables then act on
  the others through the splines' errors, which biases the fit.)
* or (``contact``, :func:`window_problem`) every rod is simulated in every window through the
  ground's contact law (an effect of :mod:`identified.effects`, ``pyramid_contact``: geometry from
  the MJCF, its parameters given -- a start -- or unknowns like K, c, M): the windows then follow
  the contacts (no free wrench whose misfit biases K, c, M), their nuisances are the initial
  states alone, and longer windows are possible;
* the cost, ``Σ |site(θ, x₀) - marker|² / σ²`` over every seen marker sample, is minimised over the
  parameters ``θ`` (the logarithms of K, c, M and the observable moments of inertia) and every
  window's initial state and ground wrench by Gauss-Newton (a Jacobian reused for a few steps, each
  step halved until it lowers the cost), the windows' unknowns eliminated by their Schur
  complement (each window's residuals depend on its own unknowns only;
  :mod:`identified.fit.window_solve`).

The Jacobian is exact (forward-mode automatic differentiation through the engine,
:func:`torch.func.jvp` batched over tangents with :func:`torch.func.vmap`).  The standard errors
are the Gauss-Newton ones: ``σ̂² (JᵀJ)⁻¹`` with the windows' states marginalised, ``σ̂²`` the cost
per degree of freedom at the optimum (the markers' noise, plus whatever the model leaves).

The global scale is invisible to marker positions (every force and mass scaled by one factor
gives the same accelerations): the parameters move in the subspace orthogonal to that direction
and are rescaled at the end to the regression's anchor (a known total mass); the covariance is
carried through the rescaling (delta method).

Paper: the engine's eqs. 1-4 and its semi-implicit Euler; the cost is the output-error
maximum-likelihood estimate for Gaussian marker noise (Ljung 1999, *System Identification*,
sec. 7.3), multiple shooting after Bock and Plitt (1984).
"""

from __future__ import annotations

import time
from copy import copy
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import torch
from torch.func import jvp, vmap

from identified.dataset import Dataset
from identified.effects.ground_contact import CONTACT_MARGIN
from identified.effects.pyramid_contact import NEWTON_ITERATIONS
from identified.engine import SpringRodEngine, SpringRodParams
from identified.engine.actuators import tendon_force_parts
from identified.evaluate import actuator_forces
from identified.fit.forward_mode import shape_only_meta
from identified.fit.window_solve import window_schur
from identified.model import IdentifiedModel
from identified.recording import Recording, RecordingError
from identified.recording.table import DROPPED
from identified.rotation import quat_exp, quat_multiply, quat_to_matrix
from identified.twin import params_from_model

__all__ = ["MarkerWindows", "marker_windows", "refine_markers"]


@dataclass
class MarkerWindows:
    """The recording cut into windows, aligned with the reconstructed states.

    ``W`` windows, ``H`` engine steps each, ``L`` frames observed, ``N`` sites, ``R`` rods.
    ``x0`` (W, R, 13): each window's initial state from the reconstruction (pos, quat, vel, angvel);
    ``states`` (W, H + 1, R, 13): the reconstructed states over the window (the moves of the rods
    that are not simulated); ``rest`` (W, H, S); ``at`` (W, L) float: the time of each observed
    frame in engine steps from its window's initial state (whole where the frames fall on the
    steps; a camera's clock need not: between two steps the sites are interpolated, :func:`frame_weights`);
    ``obs`` (W, L, N, 3) marker positions, ``seen`` (W, L, N) float (1 where seen and its rod is
    simulated); ``free`` (W, R) bool: the rods simulated in each window; ``site_rod`` (N,),
    ``site_offset`` (N, 3); ``window_time`` (W,) the recording's time of each window's start;
    ``force`` (W, H, S): the MuJoCo actuators' force on each tendon at each step (``None``: none);
    ``gained`` (W, H, U): where the fit estimates the actuators' gains, each one's ``g act`` at its
    start's gain, and ``force`` holds the biases alone (``None``: the gains are in ``force``).
    """

    x0: torch.Tensor
    states: torch.Tensor
    rest: torch.Tensor
    at: torch.Tensor
    obs: torch.Tensor
    seen: torch.Tensor
    free: torch.Tensor
    site_rod: torch.Tensor
    site_offset: torch.Tensor
    window_time: np.ndarray
    force: torch.Tensor | None = None
    gained: torch.Tensor | None = None

    @property
    def n_windows(self) -> int:
        return int(self.x0.shape[0])

    @property
    def n_steps(self) -> int:
        """H: the engine steps every window is stepped through (to its latest frame)."""
        return int(self.rest.shape[1])

    def subset(self, keep: np.ndarray) -> MarkerWindows:
        k = torch.as_tensor(keep)
        return replace(self, x0=self.x0[k], states=self.states[k], rest=self.rest[k], at=self.at[k], obs=self.obs[k],
                       seen=self.seen[k], free=self.free[k], window_time=self.window_time[keep],
                       force=None if self.force is None else self.force[k],
                       gained=None if self.gained is None else self.gained[k])


def near_ground(mjcf: str, topology, data: Dataset, margin: float = CONTACT_MARGIN) -> np.ndarray | None:
    """(E, T + 1, R) bool: rods with an end sphere within ``margin`` (m) of the ground (``None``
    when the model has no ground plane)."""
    from identified.effects import GeometryError
    from identified.effects.ground_contact import GroundContact
    from identified.state import RodState

    try:
        eff = GroundContact.for_system(topology, mjcf)
    except GeometryError:
        return None
    pos, quat = torch.as_tensor(data.pos), torch.as_tensor(data.quat)

    state = RodState(pos, quat, torch.as_tensor(data.vel), torch.as_tensor(data.angvel))
    return eff.rows_affected(state, SimpleNamespace(rot=quat_to_matrix(quat)), margin).numpy()


#: a frame within this share of a step of one is on it (1 µs at 1 ms: a clock's resolution, and the
#: rounding of times counted from an epoch, 2.4e-7 s at 1.7e9 s)
ON_STEP = 1e-3


def marker_windows(rec: Recording, data: Dataset, starts: list[float], topology, mjcf: str | None,
                   frames: int = 10, contact_frames: int = 3, margin: float = CONTACT_MARGIN,
                   forces: np.ndarray | None = None, gained: np.ndarray | None = None) -> MarkerWindows:
    """Cut a labelled recording into windows of ``frames`` frames over the reconstructed states
    ``data`` (take ``e``'s state ``n`` at the time ``starts[e] + n dt``).  A rod near the ground
    within ``contact_frames`` frames of a window is not simulated in it.  Each window starts at the
    engine's step at or before its first frame; its frames may fall anywhere between the steps (a
    camera's clock: 30 Hz frames 33.3 ms apart, or 33, 33 and 34 ms on a 1 ms grid), each at its
    own time (``at``).  A window whose frames span more than :data:`DROPPED` times the take's usual
    span (frames missing from the file) is skipped.  ``forces`` (E, T, S): the MuJoCo actuators'
    force on each tendon at each step of ``data``, cut into the windows alike (``None``: no
    actuators); ``gained`` (E, T, U): each actuator's ``g act`` where the gains are estimated
    (``forces`` then the biases alone), cut alike."""
    dt = data.dt
    sites = [(i, k, s) for i, r in enumerate(topology.rods) for k, s in enumerate(r.sites) if s in rec.marker_names]
    col = [rec.marker_names.index(s) for _, _, s in sites]
    site_rod = torch.as_tensor([i for i, _, _ in sites])
    site_offset = torch.as_tensor(np.array([topology.rods[i].site_offsets[k] for i, k, _ in sites]), dtype=torch.float64)
    near = near_ground(mjcf, topology, data, margin) if mjcf else None
    state = np.concatenate([data.pos, data.quat, data.vel, data.angvel], axis=-1)  # (E, T+1, R, 13)
    T = data.n_steps
    cut = []  # (take, first step, frames' steps from it, steps to the last, the frames' rows, the start time)
    for e, rows in enumerate(rec.episodes()):
        t = rec.time[rows]
        n = (t - starts[e]) / dt
        inside = (n > -ON_STEP) & (n < T + ON_STEP)
        rows, n, t = rows[inside], n[inside], t[inside]
        n = np.where(np.abs(n - np.round(n)) < ON_STEP, np.round(n), n)  # on the steps: exactly
        if n.size < frames:
            continue
        usual = (frames - 1) * float(np.median(np.diff(n)))
        for f in range(0, n.size - frames + 1, frames):
            a = int(np.floor(n[f]))
            at = n[f:f + frames] - a
            if at[-1] - at[0] > DROPPED * usual:
                continue  # frames missing from the file within the window: skipped
            cut.append((e, a, at, int(np.ceil(at[-1])), rows[f:f + frames], float(t[f])))
    if not cut:
        longest = max((int(r.size) for r in rec.episodes()), default=0)
        raise RecordingError(f"'{rec.source}': windows of {frames} frames do not fit in its takes (the longest has "
                             f"{longest} frames): fewer frames per window")
    H = max(span for _, _, _, span, _, _ in cut)
    x0, sts, rest, at_, obs, seen, free, wt, force, gain_force = [], [], [], [], [], [], [], [], [], []
    pad = lambda x, a, n: x[np.minimum(np.arange(a, a + n), x.shape[0] - 1)]  # past the take's end: its last
    for e, a, at, span, frows, t0 in cut:
        reach = contact_frames * (span // (frames - 1))
        lo, hi = max(0, a - reach), min(T, a + span + reach)
        fr = np.ones(topology.n_rods, dtype=bool) if near is None else ~near[e, lo:hi + 1].any(0)
        if not fr.any():
            continue
        m = rec.markers[frows][:, col]  # (L, N, 3)
        x0.append(state[e, a])
        sts.append(pad(state[e], a, H + 1))
        rest.append(pad(data.rest_length[e], a, H))
        if forces is not None:
            force.append(pad(forces[e], a, H))
        if gained is not None:
            gain_force.append(pad(gained[e], a, H))
        at_.append(at)
        obs.append(np.nan_to_num(m))
        seen.append(np.isfinite(m).all(-1).astype(float))
        free.append(fr)
        wt.append(t0)
    if not x0:
        raise ValueError("no window of the recording has a rod off the ground to simulate")
    tt = lambda x, dtype=torch.float64: torch.as_tensor(np.array(x), dtype=dtype)
    return MarkerWindows(tt(x0), tt(sts), tt(rest), tt(at_), tt(obs), tt(seen), tt(free, torch.bool),
                         site_rod, site_offset, np.array(wt), tt(force) if forces is not None else None,
                         tt(gain_force) if gained is not None else None)


#: units of the ground's free wrench in the unknowns (N, N m): of the order of a rod's weight
WRENCH_UNIT = 10.0


class _Wrench:
    """An engine effect: the free wrench on the rods near the ground, a polynomial in time over the
    window (Legendre: constant, then linear), world frame; ``n`` the step about to be taken."""

    def __init__(self, coef: torch.Tensor, steps: int, held_axis: torch.Tensor) -> None:
        self.coef, self.steps, self.n, self.held_axis = coef, steps, 0, held_axis

    def __call__(self, state, ctx) -> tuple[torch.Tensor, torch.Tensor]:
        s = 2.0 * (self.n + 0.5) / self.steps - 1.0
        w = self.coef[..., 0, :]
        if self.coef.shape[-2] > 1:
            w = w + s * self.coef[..., 1, :]
        if self.coef.shape[-2] > 2:
            w = w + 0.5 * (3 * s * s - 1) * self.coef[..., 2, :]
        # no torque about a rod's axis where its markers cannot see the spin about it
        axis = (ctx.rot @ self.held_axis.unsqueeze(-1)).squeeze(-1)
        torque = w[..., 3:] - (w[..., 3:] * axis).sum(-1, keepdim=True) * axis
        return w[..., :3], torque


def _impedances(names: list[str]) -> np.ndarray:
    """(n,) bool: which of the contact law's parameters are impedances (``imp_*``, in (0, 1): their
    unknowns are logits), the others positive (their unknowns are logarithms)."""
    return np.array([n.startswith("imp_") for n in names], dtype=bool)


def _law_transform(names: list[str], values: np.ndarray) -> np.ndarray:
    """The contact law's parameters as the windows' unknowns: logits ``log(v / (1 - v))`` of the
    impedances (:func:`_impedances`), logarithms ``log v`` of the others."""
    v = np.asarray(values, dtype=float)
    logit = _impedances(names)
    out = np.empty_like(v)
    out[logit] = np.log(v[logit] / (1 - v[logit]))
    out[~logit] = np.log(v[~logit])
    return out


class _Law:
    """An engine effect: the ground's contact law (``identified.effects``' ``pyramid_contact`` or
    ``ground_contact``, its geometry from the MJCF) at parameters given as a tensor, so that the
    windows' forward-mode derivatives go through it (:meth:`identified.effects.base.Effect.bind`
    for the call only: no dual tensor stays in the effect's cache)."""

    needs_base_acceleration = True

    def __init__(self, effect, theta: torch.Tensor) -> None:
        self.effect, self.theta = effect, theta

    def __call__(self, state, ctx) -> tuple[torch.Tensor, torch.Tensor]:
        self.effect.bind(self.theta)
        try:
            return self.effect.wrench(state, ctx)
        finally:
            self.effect.bind(None)


def coarse_steps(step: np.ndarray, substeps: int) -> np.ndarray:
    """The windows' integration grid in the reconstruction's steps: from 0 through every observed
    frame's step ``step`` (L,) to the last, each step at most ``substeps`` long.  Each frame
    interval of ``d`` steps is cut into ``ceil(d / substeps)`` steps as equal as whole steps allow
    (the longer first): all exactly ``substeps`` where it divides every interval; at 30 Hz on a
    1 ms reconstruction (intervals of 33 and 34 ms) and ``substeps`` 5, steps of 5 and 4 ms.
    ``substeps`` 1: every step (the reconstruction's own)."""
    if substeps < 1:
        raise ValueError(f"substeps {substeps!r}: the windows' step is a whole number (>= 1) of the reconstruction's")
    step = np.asarray(step, dtype=int)
    grid = [int(step[0])]
    for d in np.diff(step):
        m = -(-int(d) // substeps)  # ceil
        grid += [grid[-1] + int(d) // m * (j + 1) + min(j + 1, int(d) % m) for j in range(m)]
    return np.array(grid)


def window_grid(at: np.ndarray, substeps: int, steps: int) -> np.ndarray:
    """The windows' integration grid in the reconstruction's steps, from 0 to ``steps``, through
    every frame that falls on the same whole step in every window (every frame, where the frames
    keep one spacing on the steps), each step at most ``substeps`` long (:func:`coarse_steps`); a
    frame between two of its steps is sampled between them (:func:`frame_weights`).  ``at`` (W, L):
    the frames' times in steps from their window's start (:class:`MarkerWindows`)."""
    at = np.asarray(at, dtype=float)
    shared = (at == np.round(at)).all(0) & (at == at[:1]).all(0)
    return coarse_steps(np.unique(np.r_[0, at[0, shared], steps]).astype(int), substeps)


def frame_weights(at: np.ndarray, grid: np.ndarray) -> dict[int, list[tuple[int, torch.Tensor]]]:
    """How each window's frames are read off the states at the grid's steps: linearly between the
    two steps about the frame's time (the engine's semi-implicit Euler defines the states at its
    steps; between them a motion smooth over one step is linear to ``a h² / 8``, 1 µm at 1 ms and
    10 m/s², 31 µm at the Jacobians' 5 ms), on the step itself where the frame falls on one.
    Returns, for every step ``j`` of the grid that some frame reads, the frames ``l`` it serves and
    their weights (W, 1, 1) there (zero for a window whose frame ``l`` lies elsewhere)."""
    at = np.asarray(at, dtype=float)
    grid = np.asarray(grid, dtype=float)
    i = np.clip(np.searchsorted(grid, at, side="right") - 1, 0, grid.size - 1)
    on = at == grid[i]
    hi = np.where(on, i, np.minimum(i + 1, grid.size - 1))
    f = np.where(on, 0.0, (at - grid[i]) / (grid[hi] - grid[i] + on))
    out = {}
    for j in np.unique(np.r_[i.ravel(), hi.ravel()]):
        w = (1.0 - f) * (i == j) + f * (hi == j)
        frames = [(int(l), torch.as_tensor(w[:, l], dtype=torch.float64)[:, None, None])
                  for l in range(at.shape[1]) if (w[:, l] != 0).any()]
        if frames:
            out[int(j)] = frames
    return out


class _Problem:
    """The residuals of every window as a function of the parameters' logarithms and the windows'
    initial-state corrections."""

    def __init__(self, model: IdentifiedModel, win: MarkerWindows, dt: float, sigma: float,
                 hold_inertia: list[tuple[int, int]], wrench_order: int = 2, axial: bool = False,
                 contact=None, law_free: tuple[str, ...] = (), substeps: int = 1,
                 gains: tuple[tuple[str, ...], np.ndarray, np.ndarray] | None = None) -> None:
        """``axial``: the held moments (``hold_inertia``) are parameters too, each its own group (for
        a bound that shows they carry no information; never for a fit).  The spin about a held
        axis stays as reconstructed, not a free unknown: the axis's motion does not depend on it
        (``ȧ = L × a / I₁``), and the engine's steps couple it at 1e-3 of a transverse spin's
        effect (measured) -- a free unknown that small would project out whole directions.

        ``contact``: the ground's contact law (an effect of :mod:`identified.effects` with its
        ``values``, the start or the known law) acts in every window in place of the free wrench;
        every rod is then simulated (the windows of :func:`marker_windows` without ``mjcf``) and the
        windows' nuisances are their initial states alone.  ``law_free``: the law's parameters
        (names of its blocks) that are unknowns too, global like K, c, M (transformed:
        :func:`_law_transform`); the others are held at ``contact.values``.

        ``substeps``: the windows are stepped at up to ``substeps`` times ``dt`` (:func:`coarse_steps`;
        K, c, M are continuous-time, the same at any step); each coarse step holds the encoders'
        rest lengths at its start, as the engine's semi-implicit Euler holds its inputs over a step
        (and as the plant held each reading over its own step): ``substeps`` 1 is the windows at
        ``dt`` exactly, and the windows at ``k dt`` are those of a reconstruction sampled every
        ``k`` steps.

        ``gains`` ``(names, start gains (U,), spread (U, S))``: the MuJoCo actuators' gains are
        unknowns too, each the start's times the exponential of its unknown (forces: the global
        scale moves them with K, c, M), the windows' ``gained`` their forces at the start's gains
        (:func:`identified.engine.actuators.tendon_force_parts`); ``None``: held in ``win.force``."""
        self.model, self.win, self.dt, self.sigma = model, win, dt, sigma
        self.substeps = substeps
        self.grid, self.reads = self._sampling(substeps)
        self.contact = contact
        self.order = 0 if contact is not None else wrench_order
        self.n_x = 12 + 6 * self.order  # unknowns per window and rod
        self.base = params_from_model(model)
        if self.base.com is not None or self.base.inertia_products is not None:
            raise ValueError("the output-error refinement takes rods with a diagonal inertia at the frame's origin")
        R, S = model.topology.n_rods, model.topology.n_springs
        held = {(i, ax) for i, ax in hold_inertia}
        # inertia: one parameter per rod and observable group of axes; a rod whose spin about an
        # axis is not observable has its two other moments tied (its frame about that axis is arbitrary)
        groups: list[tuple[int, list[int]]] = []
        for i in range(R):
            ax_held = [ax for ax in range(3) if (i, ax) in held]
            if ax_held:
                groups.append((i, [ax for ax in range(3) if ax not in ax_held]))
                if axial:
                    groups += [(i, [ax]) for ax in ax_held]
            else:
                groups += [(i, [ax]) for ax in range(3)]
        self.groups = groups
        inertia = self.base.inertia
        theta0 = [self.base.stiffness.log(), self.base.damping.log(), self.base.mass.log(),
                  torch.stack([inertia[i, axes].mean().log() for i, axes in groups])]
        self.gain_names: tuple[str, ...] = () if gains is None else tuple(gains[0])
        U = len(self.gain_names)
        if U and win.gained is None:
            raise ValueError("the actuators' gains are unknowns, but the windows carry no forces at the start's gains")
        self.gain0 = torch.as_tensor(np.zeros(0) if gains is None else gains[1], dtype=torch.float64)
        self.spread = torch.as_tensor(np.zeros((0, S)) if gains is None else gains[2], dtype=torch.float64)
        theta0.append(torch.zeros(U, dtype=torch.float64))  # each gain relative to the start's
        self.sizes = [S, S, R, len(groups), U]
        self.n_spring_rod = sum(self.sizes)  # K, c, M, I and the gains: the parameters the global scale moves
        self.law_names: list[str] = []
        self.law_idx: list[int] = []
        if contact is not None:
            if contact.values is None:
                raise ValueError(f"the windows' contact law '{contact.name}' needs parameter values to start from")
            names = [b.name for b in contact.blocks]
            unknown = [n for n in law_free if n not in names]
            if unknown:
                raise ValueError(f"{contact.name} has no parameter {', '.join(unknown)} (it has {', '.join(names)})")
            self.law_idx = [names.index(n) for n in law_free]
            vals = np.asarray(contact.values, dtype=float)
            imp = _impedances(names)
            bad = [names[i] for i in self.law_idx if not vals[i] > 0 or (imp[i] and vals[i] >= 1)]
            if bad:
                raise ValueError(f"{contact.name}: {', '.join(bad)} must start positive (impedances below 1) to be estimated")
            self.law_names = [names[i] for i in self.law_idx]
            self.law_values = torch.as_tensor(vals, dtype=torch.float64)
            self.law_logit = torch.as_tensor(imp[self.law_idx])
            theta0.append(torch.as_tensor(_law_transform(self.law_names, vals[self.law_idx]), dtype=torch.float64))
        self.theta0 = torch.cat(theta0)
        self.names = (["stiffness"] * S + ["damping"] * S + ["mass"] * R + ["inertia"] * len(groups)
                      + ["gain"] * U + ["law"] * len(self.law_idx))
        gi = torch.zeros(R, 3, len(groups), dtype=torch.float64)
        for g, (i, axes) in enumerate(groups):
            gi[i, axes, g] = 1.0
        self.gi = gi  # (R, 3, G): which group sets each moment
        self.inertia_fixed = inertia * (gi.sum(-1) == 0)
        # a rod whose spin about a body axis is not observable keeps its initial state's spin about
        # it as reconstructed (none): the corrections of its rotation and angular velocity are
        # taken across that axis only
        self.axial = torch.zeros(win.n_windows, R, 3, dtype=torch.float64)
        self.held_axis = torch.zeros(R, 3, dtype=torch.float64)
        for i, ax in held:
            self.held_axis[i, ax] = 1.0
        rot0 = quat_to_matrix(win.x0[..., 3:7])  # (W, R, 3, 3)
        for i, ax in held:
            self.axial[:, i] = rot0[:, i, :, ax]

    def at_step(self, substeps: int) -> _Problem:
        """The same problem, its windows stepped at up to ``substeps`` of ``dt`` (:func:`coarse_steps`);
        itself at its own step (a caller then reads the cost's residuals off its Jacobian pass)."""
        if substeps == self.substeps:
            return self
        out = copy(self)
        out.substeps = substeps
        out.grid, out.reads = self._sampling(substeps)
        return out

    def _sampling(self, substeps: int) -> tuple[np.ndarray, dict[int, list[tuple[int, torch.Tensor]]]]:
        """The windows' grid at up to ``substeps`` of ``dt`` ((n + 1,) the steps' bounds in ``dt``,
        :func:`window_grid`) and where each frame is read off it (:func:`frame_weights`)."""
        grid = window_grid(self.win.at.numpy(), substeps, self.win.n_steps)
        return grid, frame_weights(self.win.at.numpy(), grid)

    def with_smoothing(self, width: float) -> _Problem:
        """The same problem through its contact law smoothed over ``width`` (m;
        :attr:`identified.effects.pyramid_contact.PyramidContact.smoothing`), for Jacobians: the law's
        solve stops at the exact law's Newton iterations (1e-3 of the force at 1 mm, twice as fast
        as to rounding); itself at 0 or without a law."""
        if width <= 0 or self.contact is None:
            return self
        out, law = copy(self), copy(self.contact)
        law.smoothing, law.smoothed_iterations = float(width), NEWTON_ITERATIONS
        out.contact = law
        return out

    def params(self, theta: torch.Tensor) -> SpringRodParams:
        K, c, M, Ig, _ = torch.split(theta[:self.n_spring_rod].exp(), self.sizes)
        inertia = self.inertia_fixed + (self.gi * Ig).sum(-1)
        return replace(self.base, stiffness=K, damping=c, mass=M, inertia=inertia)

    @property
    def gain_slice(self) -> slice:
        """Where the actuators' gains (logarithms relative to the start's) lie among the unknowns."""
        a = sum(self.sizes[:4])
        return slice(a, a + self.sizes[4])

    def tendon_force(self, theta: torch.Tensor, win: MarkerWindows, n: int) -> torch.Tensor | None:
        """(W, S) the actuators' force on each tendon at step ``n`` of the windows ``win`` at the
        unknowns ``theta`` (``None``: no actuators)."""
        if win.gained is None:
            return None if win.force is None else win.force[:, n]
        f = (win.gained[:, n] * theta[self.gain_slice].exp()) @ self.spread
        return f if win.force is None else f + win.force[:, n]

    @property
    def mass_slice(self) -> slice:
        """Where the rods' log-masses lie among the unknowns."""
        S, R = self.sizes[0], self.sizes[2]
        return slice(2 * S, 2 * S + R)

    def total_mass_row(self, mass: np.ndarray) -> np.ndarray:
        """(P,) the gradient of log(total mass) in the unknowns at the rods' masses ``mass`` (R,):
        the row of the known total mass's constraint (which also fixes the scale no marker sees)."""
        mass = np.asarray(mass, dtype=float)
        g = np.zeros(self.theta0.numel())
        g[self.mass_slice] = mass / mass.sum()
        return g

    def law_theta(self, theta: torch.Tensor) -> torch.Tensor:
        """The contact law's parameters (its natural units) at the unknowns ``theta``."""
        x = theta[self.n_spring_rod:]
        if not self.law_idx:
            return self.law_values
        v = torch.where(self.law_logit, torch.sigmoid(x), x.exp())
        put = torch.zeros(self.law_values.numel(), len(self.law_idx), dtype=torch.float64)
        put[self.law_idx, range(len(self.law_idx))] = 1.0  # the free parameters' places (a matrix: vmap-safe)
        return self.law_values * (1.0 - put.sum(-1)) + put @ v

    def residuals(self, theta: torch.Tensor, dx: torch.Tensor, win: MarkerWindows | None = None,
                  axial: torch.Tensor | None = None) -> torch.Tensor:
        """(W, L, N, 3) weighted residuals (site - marker) / σ at the seen samples of simulated rods;
        ``dx`` (W, R, 12): corrections of each window's initial state (position, rotation vector,
        velocity, angular velocity, world frame)."""
        win = self.win if win is None else win
        free = win.free.unsqueeze(-1)
        H = win.n_steps
        wrench = None
        if self.order > 0:  # the ground's wrench on each rod near it: free, polynomial in time
            coef = dx[..., 12:].unflatten(-1, (self.order, 6)) * (~free).unsqueeze(-1) * WRENCH_UNIT
            wrench = _Wrench(coef, H, self.held_axis)
        effects = [] if wrench is None else [wrench]
        if self.contact is not None:  # the contact law: every rod simulated, through its contacts
            effects = [_Law(self.contact, self.law_theta(theta))]
        params = self.params(theta)
        grid = self.grid  # a subset of the windows is stepped as the whole: its frames on the same steps
        reads = self.reads if win is self.win else frame_weights(win.at.numpy(), grid)
        engines = {int(h): SpringRodEngine(self.model.topology, params, int(h) * self.dt, effects=effects)
                   for h in np.unique(np.diff(grid))}
        eng = engines[int(grid[1] - grid[0])]
        x0 = win.x0
        axial = self.axial if axial is None else axial
        across = lambda v: v - (v * axial).sum(-1, keepdim=True) * axial
        dx = torch.cat([dx[..., 0:3], across(dx[..., 3:6]), dx[..., 6:9], across(dx[..., 9:12])], -1)
        q0 = quat_multiply(quat_exp(dx[..., 3:6]), x0[..., 3:7])
        q0 = q0 / q0.norm(dim=-1, keepdim=True)
        state = eng.state(x0[..., 0:3] + dx[..., 0:3], q0, x0[..., 7:10] + dx[..., 6:9], x0[..., 10:13] + dx[..., 9:12])
        frames: list[torch.Tensor | None] = [None] * win.at.shape[1]
        for j, n in enumerate(grid.tolist()):
            if j > 0:
                a = int(grid[j - 1])
                if wrench is not None:
                    wrench.n = (a + n) / 2 - 0.5  # the coarse step's middle
                state = engines[n - a].step(state, win.rest[:, a], tendon_force=self.tendon_force(theta, win, a))
                if self.order == 0 and self.contact is None:  # the rods near the ground move as reconstructed
                    rec = win.states[:, n]
                    state = type(state)(torch.where(free, state.pos, rec[..., 0:3]),
                                        torch.where(free, state.quat, rec[..., 3:7]),
                                        torch.where(free, state.vel, rec[..., 7:10]),
                                        torch.where(free, state.angvel, rec[..., 10:13]))
            if j in reads:
                rot = quat_to_matrix(state.quat)[:, win.site_rod]  # (W, N, 3, 3)
                sites = state.pos[:, win.site_rod] + (rot @ win.site_offset.unsqueeze(-1)).squeeze(-1)
                for l, w in reads[j]:
                    frames[l] = w * sites if frames[l] is None else frames[l] + w * sites
        pred = torch.stack(frames, dim=1)
        seen = win.seen if self.order > 0 else win.seen * win.free[:, win.site_rod].unsqueeze(1)
        return (pred - win.obs) * seen.unsqueeze(-1) / self.sigma

    def window_residuals(self, theta: torch.Tensor, dx: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """(W', m) the residuals of the windows ``keep`` (indices; ``None``: all) at their nuisances
        ``dx`` (W', R, n_x), without derivatives: a window's residuals depend on its own nuisances
        and the parameters only.  A window set whose contact law's solve breaks (a singular system:
        measured at 10 Hz, a trial step from states 40 mm off) costs infinity."""
        whole = keep is None or len(keep) == self.win.n_windows
        try:
            with torch.no_grad():
                if whole:
                    return self.residuals(theta, dx).reshape(dx.shape[0], -1)
                return self.residuals(theta, dx, win=self.win.subset(keep.numpy()),
                                      axial=self.axial[keep]).reshape(dx.shape[0], -1)
        except torch.linalg.LinAlgError:
            m = int(self.win.seen[0].numel()) * 3
            return torch.full((dx.shape[0], m), np.inf, dtype=torch.float64)

    def jacobians(self, theta: torch.Tensor, dx: torch.Tensor, chunk: int | None = None,
                  params: bool = True) -> tuple[torch.Tensor, ...]:
        """Residuals r (W, m), their Jacobian with respect to each window's own state (W, m, 12 R)
        and with respect to the parameters (W, m, P), by forward-mode differentiation (``params``
        false: the states' alone, the third ``None``)."""
        W, R = dx.shape[0], dx.shape[1]
        P = theta.numel()
        f = lambda th, d: self.residuals(th, d).reshape(W, -1)
        r = f(theta, dx).detach()
        k = self.n_x
        nx = k * R
        tangents_x = torch.eye(nx, dtype=dx.dtype).reshape(nx, 1, R, k).expand(nx, W, R, k)
        tangents = [(torch.zeros(P, dtype=theta.dtype).expand(nx, P), tangents_x)]
        if params:
            tangents.append((torch.eye(P, dtype=theta.dtype), torch.zeros(P, W, R, k, dtype=dx.dtype)))
        chunk = chunk or max(16, 60_000 // max(W * R, 1))  # tangents per batched pass (bounded memory)
        cols = []
        with shape_only_meta():  # the constants' zero tangents without torch's slow path (forward_mode)
            for tth, tdx in tangents:
                for k in range(0, tth.shape[0], chunk):
                    push = lambda a, b: jvp(f, (theta, dx), (a, b))[1]
                    cols.append(vmap(push)(tth[k:k + chunk], tdx[k:k + chunk]))
        J = torch.cat(cols, 0).permute(1, 2, 0)  # (W, m, nx + P)
        return r, J[..., :nx], J[..., nx:] if params else None


def window_problem(model: IdentifiedModel, rec: Recording, data: Dataset, starts: list[float], mjcf: str | None,
                   sigma: float, hold_inertia: list[tuple[int, int]] = (), frames: int = 10, max_windows: int = 256,
                   order: int = 2, axial: bool = False, margin: float = CONTACT_MARGIN, contact=None,
                   law_free: tuple[str, ...] = (), substeps: int = 1, block: tuple[int, int] = (0, 1),
                   free_gains: bool = False) -> tuple[MarkerWindows, int, _Problem, torch.Tensor, torch.Tensor]:
    """The output-error problem of a recording at ``model``'s parameters, as the refinement, the
    bound and the staged fit all set it up: up to ``max_windows`` windows of ``frames`` frames spread
    evenly over the recording (of ``available``), the :class:`_Problem` on them, the windows'
    starting nuisances ``dx`` (W, R, n_x) (zero corrections; the ground carrying the weight of the
    rods near it when there is a wrench, ``order`` > 0), and the mask of the nuisances that act
    (W, R n_x) float: every simulated rod's state, the wrench of a rod near the ground.
    With a ``contact`` law (:class:`_Problem`; ``law_free`` its unknown parameters) every rod is
    simulated in every window, through the law, and the nuisances are the initial states alone.
    ``substeps``: the windows stepped at up to that many of ``data.dt`` (:func:`coarse_steps`).
    ``block`` ``(b, B)``: of the windows spread over the recording, every ``B``-th from the ``b``-th
    (block ``b`` of ``B`` interleaved blocks; :mod:`identified.fit.marker_blocks`).
    ``free_gains``: the MuJoCo actuators' gains are unknowns too (their biases and filters held at
    the model's); else all three are held.
    Returns ``(windows, available, problem, dx, active)``."""
    if free_gains and model.actuators:
        gained, spread, forces = tendon_force_parts(data.ctrl, data.dt, data.actuator_names, model.actuators,
                                                    model.topology.spring_names)
        gains = (tuple(a["name"] for a in model.actuators), np.array([a["gain"] for a in model.actuators]), spread)
    else:
        forces, gained, gains = actuator_forces(model, data), None, None  # held at the model's
    if contact is not None:
        order = 0
    win = marker_windows(rec, data, starts, model.topology, None if contact is not None else mjcf, frames,
                         margin=margin, forces=forces, gained=gained)
    available = win.n_windows
    if win.n_windows > max_windows:
        win = win.subset(np.linspace(0, win.n_windows - 1, max_windows).round().astype(int))
    b, B = block
    if B > 1:
        if win.n_windows < 2 * B:
            raise RecordingError(f"'{rec.source}': {B} blocks of windows need at least two windows each; the fit "
                                 f"has {win.n_windows} (fewer blocks, or more windows)")
        win = win.subset(np.arange(b, win.n_windows, B))
    prob = _Problem(model, win, data.dt, float(sigma), list(hold_inertia), order, axial=axial, contact=contact,
                    law_free=tuple(law_free), substeps=substeps, gains=gains)
    W, R, k = win.n_windows, model.topology.n_rods, prob.n_x
    dx = torch.zeros(W, R, k, dtype=torch.float64)
    if order > 0:  # the ground starts out carrying the weight of the rods near it
        weight = -torch.as_tensor(model.mass)[:, None] * torch.as_tensor(np.asarray(model.gravity, dtype=float))
        dx[..., 12:15] = weight / WRENCH_UNIT
    near = ~win.free
    active = torch.cat([(win.free | (order > 0)).unsqueeze(-1).expand(W, R, 12),
                        near.unsqueeze(-1).expand(W, R, k - 12) & (order > 0)], -1).reshape(W, R * k).to(torch.float64)
    return win, available, prob, dx, active


def refine_markers(model: IdentifiedModel, rec: Recording, data: Dataset, starts: list[float], mjcf: str | None,
                   hold_inertia: list[tuple[int, int]] = (), frames: int = 10, max_windows: int = 256,
                   jacobians: int = 2, chord_steps: int = 4, sigma: float | None = None, order: int = 2,
                   fit_params: bool = True, known_noise: bool = False, progress: bool = False) -> IdentifiedModel:
    """The model with K, c, M and the observable moments of inertia refined against the markers
    (the module docstring), with Gauss-Newton standard errors.

    Up to ``max_windows`` windows of ``frames`` frames, spread evenly over the recording.  The
    Jacobian is computed ``jacobians`` times; after each, ``chord_steps`` Gauss-Newton steps reuse
    it (the chord method: each step costs one run of the windows), a step taken only where it
    lowers the cost.  The standard errors come from the last Jacobian, scaled by the residual's
    variance (``known_noise``: by ``sigma`` itself -- with ``fit_params`` false and the true
    parameters, the Cramer-Rao bound of the windows' markers).  Where the windows end more than
    :data:`OFF_MARKERS` times the markers' noise off them, or the refinement moves a parameter more
    than :data:`DISAGREE` combined standard errors, the regression's model is returned, its
    ``metrics.output_error.kept_regression`` saying why."""
    t0 = time.perf_counter()
    sig = float(sigma or rec.noise_pos or 1e-3)
    win, available, prob, dx, free_x = window_problem(model, rec, data, starts, mjcf, sig, hold_inertia, frames,
                                                      max_windows, order)
    theta = prob.theta0.clone()
    W, R, k = win.n_windows, model.topology.n_rods, prob.n_x
    P = theta.numel()
    u = torch.ones(P, 1, dtype=torch.float64) / np.sqrt(P)  # the global scale: invisible
    proj = torch.eye(P, dtype=torch.float64) - u @ u.T
    near = ~win.free

    r = prob.window_residuals(theta, dx)
    history = [float(r.square().sum())]
    cov = None
    for j in range(jacobians):
        _, Jx, Jp = prob.jacobians(theta, dx)
        Jp = Jp @ proj
        # each window's normal matrix; the states of the rods it does not simulate held by a unit
        # diagonal, the directions no marker sees (a rod's spin about its markers' line) by a ridge
        A = Jx.transpose(1, 2) @ Jx + torch.diag_embed(1.0 - free_x)
        A = A + torch.diag_embed(1e-10 * torch.diagonal(A, dim1=-2, dim2=-1).amax(-1, keepdim=True).expand(-1, A.shape[-1]))
        sc = window_schur(A, Jx.transpose(1, 2) @ Jp, (Jp.transpose(1, 2) @ Jp).sum(0))
        Sreg = sc.S + (u @ u.T) * sc.S.diagonal().mean()
        if j == jacobians - 1:
            cov = proj @ torch.linalg.pinv(proj @ sc.S @ proj, hermitian=True) @ proj
        for _ in range(chord_steps):
            Aig, gs = sc.reduce(Jx.transpose(1, 2) @ r.unsqueeze(-1), (Jp.transpose(1, 2) @ r.unsqueeze(-1)).sum(0))
            dp = -torch.linalg.solve(Sreg, gs) * float(fit_params)
            dxs = sc.back_substitute(Aig, dp)
            step = 1.0
            while step > 0.1:
                th_new = theta + step * (proj @ dp).squeeze(-1)
                dx_new = dx + step * (dxs.squeeze(-1) * free_x).reshape(W, R, k)
                r_new = prob.window_residuals(th_new, dx_new)
                c_new = float(r_new.square().sum())
                if np.isfinite(c_new) and c_new < history[-1]:
                    break
                step *= 0.5
            if step <= 0.1:
                break
            theta, dx, r = th_new, dx_new, r_new
            gain = history[-1] - c_new
            history.append(c_new)
            if progress:
                print(f"output-error: Jacobian {j + 1}, cost {c_new:.6g} (step {step:g})", flush=True)
            if gain < 1e-7 * c_new:
                break
    seen = win.seen if order > 0 else win.seen * win.free[:, win.site_rod].unsqueeze(1)
    m_obs = float(seen.sum()) * 3
    held_rods = {i for i, _ in hold_inertia}
    per_rod = torch.tensor([10.0 if i in held_rods else 12.0 for i in range(R)], dtype=torch.float64)
    simulated = torch.ones_like(win.free) if order > 0 else win.free
    n_x = float((simulated * per_rod).sum()) + 6 * order * float(near.sum())
    dof = m_obs - n_x - (P - 1)
    s2 = 1.0 if known_noise else history[-1] / max(dof, 1.0)  # the residual variance in units of σ²
    fit_s2 = history[-1] / max(dof, 1.0)
    out = _result(model, prob, theta, cov * s2, history, win, fit_s2, sig, time.perf_counter() - t0)
    out.metrics["output_error"]["windows_available"] = available
    if not fit_params:
        return out
    off = float(np.sqrt(fit_s2))  # the windows' residual RMS in units of the markers' noise
    if off > OFF_MARKERS:
        # the windows do not follow the recording (started too far, a rate too low for the engine's
        # windows): their Gauss-Newton error bars, taken at such a residual, say nothing
        return _kept_regression(model, out, f"the windows leave the markers {off * sig:.3g} m off, more than "
                                            f"{OFF_MARKERS:g} times their noise ({sig:.3g} m): the engine's windows "
                                            f"do not follow this recording")
    moved = _disagreement(model, out)
    if moved > DISAGREE:  # two estimates of the same data that their error bars cannot reconcile
        return _kept_regression(model, out, f"the refinement moved a parameter {moved:.1f} combined standard errors "
                                            f"from the regression (more than {DISAGREE:g}): too few windows for its "
                                            f"linearisation")
    return out


def _kept_regression(model: IdentifiedModel, refined: IdentifiedModel, why: str) -> IdentifiedModel:
    """The regression's ``model``, with the refinement's report and why it was not taken
    (``metrics.output_error.kept_regression``)."""
    kept = replace(model, metrics=dict(model.metrics))
    kept.metrics["output_error"] = refined.metrics["output_error"] | {"kept_regression": why}
    return kept


#: the windows' residual RMS, in units of the markers' noise, beyond which the refinement is not
#: trusted (at 100 Hz and 1 mm it is 1.0; from a 10 Hz regression, whose windows diverge, ~900)
OFF_MARKERS = 10.0

#: combined standard errors by which the refinement may move a parameter from the regression
#: before its result is distrusted (its Gauss-Newton error bars assume it is near linear)
DISAGREE = 5.0


def _disagreement(a: IdentifiedModel, b: IdentifiedModel) -> float:
    """The largest |a - b| / sqrt(se_a² + se_b²) over K, c and M where both have error bars."""
    worst = 0.0
    for k in ("stiffness", "damping", "mass"):
        if k not in a.stderr or k not in b.stderr:
            continue
        se = np.hypot(np.asarray(a.stderr[k], dtype=float), np.asarray(b.stderr[k], dtype=float))
        z = np.abs(np.asarray(getattr(a, k)) - np.asarray(getattr(b, k))) / se
        z = z[np.isfinite(z)]
        worst = max(worst, float(z.max()) if z.size else 0.0)
    return worst


def _result(model: IdentifiedModel, prob: _Problem, theta: torch.Tensor, cov: torch.Tensor, history: list[float],
            win: MarkerWindows, s2: float, sigma: float, seconds: float) -> IdentifiedModel:
    """The refined model rescaled to the regression's anchor, with its standard errors."""
    R = model.topology.n_rods
    S = model.topology.n_springs
    th = theta.clone()
    P = th.numel()
    # rescale: the total mass of the regression (its anchor) kept
    msl = slice(2 * S, 2 * S + R)
    M = th[msl].exp()
    shift = float(np.log(model.mass.sum()) - torch.log(M.sum()))
    th = th + shift
    w = (M / M.sum()).numpy()
    G = np.eye(P)
    G[:, msl] -= w[None, :]  # d(th + log Mtot - log Σ M)/d th
    C = G @ cov.numpy() @ G.T
    se_log = np.sqrt(np.clip(np.diag(C), 0, None))
    vals = th.exp().numpy()
    p = prob.params(th)
    K, c, Mv = p.stiffness.numpy(), p.damping.numpy(), p.mass.numpy()
    inertia = p.inertia.detach().numpy()
    se = {"stiffness": K * se_log[:S], "damping": c * se_log[S:2 * S], "mass": Mv * se_log[2 * S:2 * S + R]}
    ise = np.full((R, 3), np.nan)
    for g, (i, axes) in enumerate(prob.groups):
        ise[i, axes] = vals[2 * S + R + g] * se_log[2 * S + R + g]
    old = dict(model.stderr)
    stderr = dict(old)
    stderr.update(se)
    if "inertia" in old:
        ise = np.where(np.isnan(ise), np.asarray(old["inertia"], dtype=float), ise)
    stderr["inertia"] = ise
    out = replace(model, stiffness=K, damping=c, mass=Mv, inertia=inertia, stderr=stderr, metrics=dict(model.metrics))
    out.metrics["output_error"] = {
        "regression": {k: np.asarray(getattr(model, k)).tolist() for k in ("stiffness", "damping", "mass")}
        | {f"{k}_stderr": np.asarray(old[k]).tolist() for k in ("stiffness", "damping", "mass") if k in old},
        "windows": win.n_windows, "frames_per_window": int(win.at.shape[1]),
        "cost_before": history[0], "cost_after": history[-1], "iterations": len(history) - 1,
        "residual_rms_m": float(np.sqrt(s2) * sigma), "seconds": round(seconds, 3),
    }
    return out
