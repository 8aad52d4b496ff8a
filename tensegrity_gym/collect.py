"""Data collection: roll the MuJoCo plant with exciting inputs and record a dataset.

Exciting inputs, as in the paper's experiments:

* random initial states around the model's nominal pose (position, orientation, linear and angular
  velocity perturbations of every rod);
* smooth random commands to the actuated cables: a target rest length that glides between random
  way points inside the motor's range (the motor's speed limit smooths it further); MuJoCo tendon
  actuators get commands that glide the same way inside their ``ctrlrange``, recorded as ``ctrl``;
* random pushes (the paper's control force ``f_u``) every ``push_every`` steps: a force of random
  direction and known magnitude on a rod (in shuffled rounds, so every rod is pushed as often)
  at a random point of its surface (a random point
  along its axis, at the rod's radius in a random direction: so pushes also spin a rod about its
  axis and excite the axial inertia), held for ``push_duration`` steps.

Sensor noise (``noise_pos`` etc.) is added to what is recorded, never to the simulation.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from identified.dataset import Dataset
from identified.rotation import quat_exp, quat_multiply
from identified.state import RodState
from tensegrity_gym.limits import MujocoWarnings, check_memory, collect_bytes
from tensegrity_gym.plant import MujocoPlant

__all__ = ["CollectConfig", "RecordConfig", "collect", "perturb_states", "record_markers", "twin_recordings"]


@dataclass(frozen=True)
class CollectConfig:
    """How the plant is excited and what noise is added to the record."""

    episodes: int = 10
    steps: int = 2000
    seed: int = 0
    push_every: int | None = None  # steps between pushes; None: no pushes
    push_magnitude: float = 50.0  # N
    push_duration: int = 10  # physics steps a push is held
    command_period: float = 0.5  # s between random cable way points
    init_pos_std: float = 0.03  # m
    init_rot_std: float = 0.05  # rad
    init_vel_std: float = 0.3  # m/s
    init_angvel_std: float = 1.0  # rad/s
    noise_pos: float = 0.0  # m
    noise_vel: float = 0.0  # m/s
    noise_quat: float = 0.0  # rad (random rotation of this std, kept unit)
    noise_angvel: float = 0.0  # rad/s
    integrator: str | None = None

    def validate(self) -> None:
        if self.episodes < 1 or self.steps < 1:
            raise ValueError(f"episodes and steps must be >= 1 (got {self.episodes}, {self.steps})")
        if self.push_every is not None and self.push_every < 1:
            raise ValueError(f"--push-every must be >= 1 step, got {self.push_every}")
        if self.push_every is not None and self.push_duration < 1:
            raise ValueError(f"--push-duration must be >= 1 step, got {self.push_duration} (no push would be recorded)")
        if not 0 <= self.seed < 2**63:
            raise ValueError(f"--seed must be a whole number in 0..2**63-1, got {self.seed}")
        for name in ("push_magnitude", "noise_pos", "noise_vel", "noise_quat", "noise_angvel",
                     "init_pos_std", "init_rot_std", "init_vel_std", "init_angvel_std"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name.replace('_', '-')} must be a finite number >= 0, got {v}")


def perturb_states(s: RodState, rng: np.random.Generator, pos_std: float, rot_std: float,
                   vel_std: float, angvel_std: float) -> RodState:
    """Random initial state: every rod moved, turned and set moving independently."""
    R = s.pos.shape[0]
    q = quat_multiply(quat_exp(rng.normal(0, rot_std, (R, 3))), s.quat)
    return RodState(
        pos=s.pos + rng.normal(0, pos_std, (R, 3)),
        quat=q / np.linalg.norm(q, axis=-1, keepdims=True),
        vel=s.vel + rng.normal(0, vel_std, (R, 3)),
        angvel=s.angvel + rng.normal(0, angvel_std, (R, 3)),
    )


def _command_schedule(rng: np.random.Generator, steps: int, dt: float, period: float,
                      lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(steps, A) smooth targets: cosine-blended random way points in [lo, hi]."""
    A = lo.size
    if A == 0:
        return np.zeros((steps, 0))
    every = max(1, round(period / dt))
    n_way = steps // every + 2
    way = lo + (hi - lo) * rng.uniform(0, 1, (n_way, A))
    t = np.arange(steps)
    k, frac = t // every, (t % every) / every
    blend = 0.5 - 0.5 * np.cos(np.pi * frac)
    return way[k] * (1 - blend[:, None]) + way[k + 1] * blend[:, None]


def _push_frames(ends: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each rod's middle, axis and two directions across it, in the rod frame (for rods along z:
    the rod frame's own x and y)."""
    mid = ends.mean(axis=1)
    axis = ends[:, 1] - ends[:, 0]
    half = 0.5 * np.linalg.norm(axis, axis=1)
    axis = axis / np.maximum(2.0 * half, 1e-12)[:, None]
    across1 = np.empty_like(axis)
    for i, a in enumerate(axis):
        pick = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        v = pick - (pick @ a) * a
        across1[i] = v / np.linalg.norm(v)
    across2 = np.cross(axis, across1)
    return mid, axis * half[:, None], across1, across2


def _pushes(rng: np.random.Generator, cfg: CollectConfig, steps: int, n_rods: int,
            ends: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    force = np.zeros((steps, n_rods, 3))
    point = np.zeros((steps, n_rods, 3))
    if cfg.push_every is None:
        return force, point
    mid, half_axis, across1, across2 = _push_frames(ends)
    starts = range(cfg.push_every, steps, cfg.push_every)
    # rods in shuffled rounds: every rod is pushed as often as any other (±1)
    order = np.concatenate([rng.permutation(n_rods) for _ in range(len(starts) // n_rods + 1)])
    for start, rod in zip(starts, order):
        d = rng.normal(size=3)
        f = cfg.push_magnitude * d / np.linalg.norm(d)
        z = rng.uniform(-1, 1)
        phi = rng.uniform(0, 2 * np.pi)
        stop = min(start + cfg.push_duration, steps)
        force[start:stop, rod] = f
        point[start:stop, rod] = (mid[rod] + z * half_axis[rod]
                                  + radii[rod] * (np.cos(phi) * across1[rod] + np.sin(phi) * across2[rod]))
    return force, point


def _add_noise(rng: np.random.Generator, cfg: CollectConfig, pos, quat, vel, angvel):
    if cfg.noise_pos:
        pos = pos + rng.normal(0, cfg.noise_pos, pos.shape)
    if cfg.noise_vel:
        vel = vel + rng.normal(0, cfg.noise_vel, vel.shape)
    if cfg.noise_angvel:
        angvel = angvel + rng.normal(0, cfg.noise_angvel, angvel.shape)
    if cfg.noise_quat:
        quat = quat_multiply(quat_exp(rng.normal(0, cfg.noise_quat, quat.shape[:-1] + (3,))), quat)
        quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return pos, quat, vel, angvel


def collect(model: str | os.PathLike, cfg: CollectConfig, progress: bool = False) -> Dataset:
    """Roll the plant ``cfg.episodes`` times for ``cfg.steps`` physics steps and record it."""
    cfg.validate()
    plant = MujocoPlant(model, integrator=cfg.integrator)
    rng = np.random.default_rng(cfg.seed)
    E, T, R, S = cfg.episodes, cfg.steps, len(plant.rod_names), len(plant.tendon_names)
    A, U = len(plant.actuated_names), len(plant.actuators)
    if R == 0 or S == 0:
        raise ValueError(f"'{model}' has {R} rods (free bodies) and {S} spatial tendons: a spring-rod model "
                         "needs both (see the MJCF conventions in DESIGN.md)")
    check_memory(collect_bytes(E, T, R, S, A), f"--episodes {E} x --steps {T} ({R} rods, {S} tendons)")
    pos = np.empty((E, T + 1, R, 3))
    quat = np.empty((E, T + 1, R, 4))
    vel = np.empty((E, T + 1, R, 3))
    angvel = np.empty((E, T + 1, R, 3))
    command = np.empty((E, T, A))
    ctrl = np.empty((E, T, U))
    ctrl_lo, ctrl_hi = plant.ctrl_bounds() if U else (np.zeros(0), np.zeros(0))
    rest = np.empty((E, T, S))
    push_force = np.zeros((E, T, R, 3))
    push_point = np.zeros((E, T, R, 3))
    lo, hi = plant.rest_bounds() if A else (np.zeros(0), np.zeros(0))
    ends, radii = plant.rod_ends(), plant.rod_radii()

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=E * T, desc="collect", unit="step", mininterval=0.5)
    try:
        with MujocoWarnings() as caught:  # MuJoCo's instability warnings become an error (in _roll)
            _roll(plant, cfg, rng, bar, caught, pos, quat, vel, angvel, command, rest, push_force,
                  push_point, lo, hi, ends, radii, ctrl, ctrl_lo, ctrl_hi)
    finally:
        if bar is not None:
            bar.close()
    pos, quat, vel, angvel = _add_noise(rng, cfg, pos, quat, vel, angvel)
    return Dataset(
        dt=plant.dt,
        gravity=np.array(plant.model.opt.gravity, dtype=float),
        rod_names=tuple(plant.rod_names),
        tendon_names=tuple(plant.tendon_names),
        actuated_names=tuple(plant.actuated_names),
        pos=pos, quat=quat, vel=vel, angvel=angvel,
        command=command, rest_length=rest, push_force=push_force, push_point=push_point,
        noise=np.array([cfg.noise_pos, cfg.noise_vel, cfg.noise_quat, cfg.noise_angvel]),
        seed=int(cfg.seed),
        actuator_names=plant.actuator_names,
        ctrl=ctrl,
    ).validate()


def _roll(plant, cfg, rng, bar, caught, pos, quat, vel, angvel, command, rest, push_force, push_point,
          lo, hi, ends, radii, ctrl, ctrl_lo, ctrl_hi) -> None:
    """Fill the record episode by episode; raise naming the episode where MuJoCo warned or diverged."""
    E, T, R, A = pos.shape[0], pos.shape[1] - 1, pos.shape[2], command.shape[2]
    for e in range(E):
        plant.reset()
        plant.set_states(perturb_states(plant.states(), rng, cfg.init_pos_std, cfg.init_rot_std,
                                        cfg.init_vel_std, cfg.init_angvel_std))
        command[e] = _command_schedule(rng, T, plant.dt, cfg.command_period, lo, hi)
        push_force[e], push_point[e] = _pushes(rng, cfg, T, R, ends, radii)
        U = ctrl.shape[2]
        if U:  # drawn after the pushes: a model without actuators records what it always did
            ctrl[e] = _command_schedule(rng, T, plant.dt, cfg.command_period, ctrl_lo, ctrl_hi)
        for t in range(T):
            s = plant.states()
            pos[e, t], quat[e, t], vel[e, t], angvel[e, t] = s.pos, s.quat, s.vel, s.angvel
            if A:
                plant.set_targets(command[e, t])
            if U:
                plant.set_ctrl(ctrl[e, t])
            pushing = push_force[e, t].any()
            plant.step(push_force[e, t] if pushing else None, push_point[e, t] if pushing else None)
            rest[e, t] = plant.rest_lengths()  # the rest lengths used during step t
            if caught.messages:
                raise RuntimeError(f"the plant became unstable in episode {e}, step {t} (MuJoCo: "
                                   f"{caught.messages[0]}); lower --push-magnitude or the excitation")
        s = plant.states()
        pos[e, T], quat[e, T], vel[e, T], angvel[e, T] = s.pos, s.quat, s.vel, s.angvel
        if not np.all(np.isfinite(pos[e])):
            raise RuntimeError(f"the plant diverged in episode {e}; lower the excitation or the time step")
        if bar is not None:
            bar.update(T)


@dataclass(frozen=True)
class RecordConfig:
    """What a lab's sensors would see of a collection: end-cap markers at ``rate`` Hz with
    Gaussian noise ``noise_pos`` (m) per coordinate, a share ``dropout`` of samples missing in runs
    of ``dropout_run`` frames on average, and the actuated cables' rest lengths (spool encoders).
    ``unlabelled``: anonymous marker columns whose identities are shuffled every ``swap_every``
    seconds, plus ``ghosts`` spurious markers per frame.  ``encoder_rate``: the encoders' own rate
    (Hz), written as rows between the camera frames (``None``: at the frames).  ``lengths``: the
    cables whose length a sensor of their own measures (a stretch sensor, a string encoder along
    the cable; ``("all",)`` every cable), read with the encoders, with Gaussian noise
    ``noise_length`` (m)."""

    rate: float = 100.0
    noise_pos: float = 0.0
    dropout: float = 0.0
    dropout_run: float = 5.0
    unlabelled: bool = False
    swap_every: float = 0.5
    ghosts: int = 0
    encoder_rate: float | None = None
    lengths: tuple[str, ...] = ()
    noise_length: float = 0.0

    def validate(self, dt: float) -> None:
        if not (np.isfinite(self.rate) and 0 < self.rate <= 1.0 / dt):
            raise ValueError(f"--rate must be in (0, {1.0 / dt:g}] Hz (the plant steps every {dt:g} s), got {self.rate}")
        if not (np.isfinite(self.noise_pos) and self.noise_pos >= 0):
            raise ValueError(f"--noise-pos must be a finite number >= 0, got {self.noise_pos}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"--dropout must be in [0, 1), got {self.dropout}")
        if self.encoder_rate is not None and not (np.isfinite(self.encoder_rate) and 0 < self.encoder_rate <= 1.0 / dt):
            raise ValueError(f"--encoder-rate must be in (0, {1.0 / dt:g}] Hz (the plant steps every {dt:g} s), "
                             f"got {self.encoder_rate}")
        if self.ghosts < 0:
            raise ValueError(f"--ghosts must be >= 0, got {self.ghosts}")
        if not (np.isfinite(self.noise_length) and self.noise_length >= 0):
            raise ValueError(f"--noise-length must be a finite number >= 0, got {self.noise_length}")

    def length_sensors(self, tendons: Sequence[str]) -> tuple[str, ...]:
        """The cables of ``tendons`` that :attr:`lengths` names, in the model's order; an unknown
        name is refused, naming the option."""
        if tuple(self.lengths) == ("all",):
            return tuple(tendons)
        unknown = [n for n in self.lengths if n not in tendons]
        if unknown:
            raise ValueError(f"--lengths: '{unknown[0]}' is not a tendon of the model (its tendons: "
                             f"{', '.join(tendons)}; or 'all')")
        return tuple(n for n in tendons if n in self.lengths)


def record_markers(data: Dataset, model: str | os.PathLike, rec: RecordConfig, seed: int = 0):
    """The recording a lab would make of ``data`` (clean states of the plant): markers at every rod
    site sampled at ``rec.rate``, noisy, with gaps in runs; the commands sent to the MuJoCo
    actuators (``.ctrl``, read at the encoders' rate: the lab's own log); every tendon's rest length (the
    actuated cables' from their encoders, a passive spring's as measured once).  Returns an :class:`identified.recording.Recording`."""
    from identified.recording import Encoders, Recording, site_world_positions, with_encoders
    from identified.topology import Topology

    rec.validate(data.dt)
    topo = Topology.from_mjcf(model)
    rng = np.random.default_rng([seed, 7])
    sites = tuple(s for r in topo.rods for s in r.sites)
    T = data.n_steps
    idx = _sample_steps(T, data.dt, rec.rate)
    times, episodes, marks, rests, ctrls = [], [], [], [], []
    for e in range(data.n_episodes):
        m = site_world_positions(topo, data.pos[e, idx], data.quat[e, idx], sites)
        m = m + rng.normal(0.0, rec.noise_pos, m.shape) if rec.noise_pos else m
        m[_dropout_mask(rng, idx.size, len(sites), rec.dropout, rec.dropout_run)] = np.nan
        times.append(idx * data.dt)
        episodes.append(np.full(idx.size, e))
        marks.append(m)
        rests.append(data.rest_length[e][idx])
        ctrls.append(data.ctrl[e][idx] if data.actuator_names else np.zeros((idx.size, 0)))
    markers = np.concatenate(marks)
    names = sites
    if rec.unlabelled:
        names, markers = _anonymise(rng, np.concatenate(times), np.concatenate(episodes), markers, rec)
    sensors = rec.length_sensors(data.tendon_names)
    eidx = idx if rec.encoder_rate is None else _sample_steps(T, data.dt, rec.encoder_rate)
    lengths = _cable_lengths(model, data, eidx, sensors)
    if sensors and rec.noise_length:  # drawn last: the markers' noise and gaps are those without sensors
        lengths = lengths + rng.normal(0.0, rec.noise_length, lengths.shape)
    encoders = None
    if rec.encoder_rate is not None:
        E, K = data.n_episodes, eidx.size
        encoders = Encoders(time=np.tile(eidx * data.dt, E), episode=np.repeat(np.arange(E), K),
                            rest=data.rest_length[:, eidx].reshape(E * K, -1),
                            ctrl=data.ctrl[:, eidx].reshape(E * K, -1) if data.actuator_names else np.zeros((E * K, 0)),
                            length=lengths)
    out = Recording(time=np.concatenate(times), episode=np.concatenate(episodes), marker_names=names,
                    markers=markers, rest_names=tuple(data.tendon_names), rest=np.concatenate(rests),
                    ctrl_names=tuple(data.actuator_names), ctrl=np.concatenate(ctrls), length_names=sensors,
                    length=lengths if encoders is None else np.zeros((len(markers), len(sensors))),
                    noise_pos=rec.noise_pos, encoders=encoders)
    # the frames' cable lengths, as a reader of the written file finds them: the sensors' samples
    # interpolated at the frames
    return out if encoders is None else replace(out, length=with_encoders(out, encoders).length)


def _cable_lengths(model: str | os.PathLike, data: Dataset, steps: np.ndarray, cables: Sequence[str]) -> np.ndarray:
    """(E * len(steps), len(cables)) the named cables' lengths (m) at ``steps`` of every episode of
    ``data``, as the plant's MuJoCo model measures its tendons (``ten_length``) at those states."""
    out = np.zeros((data.n_episodes * steps.size, len(cables)))
    if not cables:
        return out
    plant = MujocoPlant(model)
    cols = [list(plant.tendon_names).index(n) for n in cables]
    row = 0
    for e in range(data.n_episodes):
        for t in steps:
            plant.set_states(RodState(data.pos[e, t], data.quat[e, t], data.vel[e, t], data.angvel[e, t]))
            out[row] = plant.tendon_lengths()[cols]
            row += 1
    plant.close()
    return out


def _sample_steps(T: int, dt: float, rate: float) -> np.ndarray:
    """The steps (< ``T``) a sensor at ``rate`` Hz reads: the nearest to every ``1 / rate`` s (the rest
    length of step t is that read at instant t)."""
    idx = np.unique(np.round(np.arange(0, T * dt + 1e-12, 1.0 / rate) / dt).astype(int))
    return idx[idx < T]


def _dropout_mask(rng: np.random.Generator, F: int, n: int, p: float, run: float) -> np.ndarray:
    """(F, n) bool: missing samples, a two-state Markov chain per marker with stationary share ``p``
    and mean run length ``run`` frames."""
    if p <= 0:
        return np.zeros((F, n), dtype=bool)
    leave = 1.0 / max(run, 1.0)
    enter = leave * p / (1.0 - p)
    out = np.zeros((F, n), dtype=bool)
    state = rng.uniform(size=n) < p
    u = rng.uniform(size=(F, n))
    for f in range(F):
        state = np.where(state, u[f] >= leave, u[f] < enter)
        out[f] = state
    return out


def _anonymise(rng: np.random.Generator, time: np.ndarray, episode: np.ndarray, markers: np.ndarray,
               rec: RecordConfig) -> tuple[tuple[str, ...], np.ndarray]:
    """Anonymous columns: identities shuffled every ``swap_every`` s, ghosts added near the robot."""
    F, n, _ = markers.shape
    out = np.full((F, n + rec.ghosts, 3), np.nan)
    perm, last = rng.permutation(n), -np.inf
    for f in range(F):
        if f == 0 or episode[f] != episode[f - 1] or time[f] - last >= rec.swap_every:
            perm, last = rng.permutation(n), time[f]
        out[f, perm] = markers[f]
        if rec.ghosts:
            centre = np.nanmean(markers[f], axis=0)
            out[f, n:] = centre + rng.uniform(-1.0, 1.0, (rec.ghosts, 3))
    return tuple(f"marker{k + 1}" for k in range(n + rec.ghosts)), out


def twin_recordings(model, data: Dataset, mjcf: str | os.PathLike, like, noise_pos: float,
                    seeds: Sequence[int]) -> list:
    """The recordings the identified ``model``'s own motion would give, made as ``like`` was made:
    the model free-run once (:func:`identified.evaluate.rollout`, the identified engine) from every
    take's first state in ``data`` (the rod states reconstructed from ``like``) under its recorded
    rest lengths and pushes, then recorded by :func:`record_markers` at ``like``'s rate, with its
    share of missing samples and markers' noise ``noise_pos``, one draw of the noise and gaps per
    seed of ``seeds``.  They hold no effect the model lacks: what a diagnosis finds in them is what
    reconstructing markers makes up (``diagnose``'s null, :func:`tensegrity_gym.loop.recording_null`)."""
    from identified.evaluate import rollout

    states = rollout(model, data)
    twin = replace(data, pos=states.pos.numpy(), quat=states.quat.numpy(), vel=states.vel.numpy(),
                   angvel=states.angvel.numpy(), weight=np.zeros((0, 0, 0)), replicas=())
    if not np.isfinite(twin.pos).all():
        raise ValueError("the identified model's own free run diverged under the recording's inputs")
    cfg = RecordConfig(rate=min(like.rate_hz(), 1.0 / data.dt), noise_pos=noise_pos,
                      dropout=min(like.missing_fraction(), 0.5))
    return [record_markers(twin, mjcf, cfg, seed=int(s)) for s in seeds]
