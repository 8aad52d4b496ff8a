"""Recorded rollouts of a spring-rod plant: the ``.npz`` dataset format, its loader and writer.

One array per key, SI units, quaternions w-x-y-z, angular velocity in the WORLD frame.
``E`` episodes, ``T`` steps (states at ``T + 1`` instants), ``R`` rods, ``S`` springs/tendons,
``A`` actuated cables.

=================  ===============  ==========================================================
key                shape            meaning
=================  ===============  ==========================================================
``format``         ()               ``"tensegrity-dataset/1"``
``dt``             ()               time between consecutive states, s
``gravity``        (3,)             gravitational acceleration of the experiment, m/s^2
``rod_names``      (R,)             MJCF body names of the rods
``tendon_names``   (S,)             MJCF tendon names of the springs/cables
``actuated_names`` (A,)             the actuated cables (a subset of ``tendon_names``)
``pos``            (E, T+1, R, 3)   rod centre-of-mass position, m
``quat``           (E, T+1, R, 4)   rod orientation, unit quaternion w-x-y-z
``vel``            (E, T+1, R, 3)   rod linear velocity, world frame, m/s
``angvel``         (E, T+1, R, 3)   rod angular velocity, world frame, rad/s
``command``        (E, T, A)        target rest length sent to each actuated cable's motor, m
``rest_length``    (E, T, S)        actual rest length of every spring during step t, m
``push_force``     (E, T, R, 3)     external push on each rod during step t, world frame, N
``push_point``     (E, T, R, 3)     where the push acts, in the rod frame, m
``noise``          (4,)             sensor-noise std added to pos, vel, quat, angvel (0 = clean)
``seed``           ()               seed of the collection run (-1 if unknown)
``actuator_names`` (U,)             optional: MJCF names of MuJoCo tendon actuators
``ctrl``           (E, T, U)        optional: command sent to each actuator during step t
``weight``         (E, T, R)        optional: how much each rod's equations of step t count in a
                                    fit, in [0, 1] (states reconstructed from markers: 0 where the
                                    rod's markers were missing); absent: 1 everywhere
=================  ===============  ==========================================================

Step ``t`` takes the state at instant ``t`` to instant ``t + 1`` under ``rest_length[:, t]`` and
``push_force[:, t]``.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass, field, fields, replace

import numpy as np

__all__ = ["FORMAT", "Dataset", "DatasetError", "atomic_write", "load_dataset", "save_dataset"]

FORMAT = "tensegrity-dataset/1"
QUAT_TOL = 1e-6


class DatasetError(ValueError):
    """The dataset file is missing, foreign, truncated or inconsistent."""


@dataclass(frozen=True)
class Dataset:
    """Recorded rod states, commands and pushes; see the module docstring for shapes."""

    dt: float
    gravity: np.ndarray
    rod_names: tuple[str, ...]
    tendon_names: tuple[str, ...]
    actuated_names: tuple[str, ...]
    pos: np.ndarray
    quat: np.ndarray
    vel: np.ndarray
    angvel: np.ndarray
    command: np.ndarray
    rest_length: np.ndarray
    push_force: np.ndarray
    push_point: np.ndarray
    noise: np.ndarray = field(default_factory=lambda: np.zeros(4))
    seed: int = -1
    actuator_names: tuple[str, ...] = ()
    ctrl: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    weight: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    #: copies of this dataset's states measured once more with fresh sensor noise (never saved):
    #: how states reconstructed from noisy markers would scatter, for the fit's errors in variables
    #: (:mod:`identified.fit.noise`)
    replicas: tuple[Dataset, ...] = ()

    @property
    def n_episodes(self) -> int:
        return int(self.pos.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.pos.shape[1]) - 1

    @property
    def n_rods(self) -> int:
        return int(self.pos.shape[2])

    @property
    def n_tendons(self) -> int:
        return int(self.rest_length.shape[2])

    def select(self, episodes: slice | np.ndarray | list[int] = slice(None), steps: int | None = None) -> Dataset:
        """A sub-dataset: some episodes, and/or the first ``steps`` steps of each."""
        t = self.n_steps if steps is None else int(steps)
        if not 1 <= t <= self.n_steps:
            raise DatasetError(f"steps must be in 1..{self.n_steps}, got {t}")
        return self.span(episodes, 0, t)

    def span(self, episodes: slice | np.ndarray | list[int], start: int, stop: int) -> Dataset:
        """A sub-dataset: some episodes, their steps ``start .. stop - 1`` (the states at instants
        ``start .. stop``) -- every per-step array cut alike, the noise replicas too."""
        if not 0 <= start < stop <= self.n_steps:
            raise DatasetError(f"a span of steps must lie in 0..{self.n_steps}, got {start}..{stop}")
        ep, s, t = episodes, int(start), int(stop)
        return replace(
            self,
            pos=self.pos[ep, s: t + 1],
            quat=self.quat[ep, s: t + 1],
            vel=self.vel[ep, s: t + 1],
            angvel=self.angvel[ep, s: t + 1],
            command=self.command[ep, s:t],
            rest_length=self.rest_length[ep, s:t],
            push_force=self.push_force[ep, s:t],
            push_point=self.push_point[ep, s:t],
            ctrl=self.ctrl[ep, s:t] if self.ctrl.ndim == 3 and self.ctrl.shape[0] else self.ctrl,
            weight=self.weight[ep, s:t] if self.has_weight else self.weight,
            replicas=tuple(r.span(episodes, s, t) for r in self.replicas),
        )

    @property
    def has_weight(self) -> bool:
        """Whether the dataset weighs its rods' equations per step (``weight``)."""
        return self.weight.ndim == 3 and self.weight.size > 0

    def validate(self) -> Dataset:
        """Check shapes, finiteness and unit quaternions; raise DatasetError naming what is wrong."""
        _validate(self)
        return self


#: largest magnitude (SI units) a recorded value may have: beyond it a fit can only fail numerically
PLAUSIBLE = {"pos": 1e6, "quat": 2.0, "vel": 1e6, "angvel": 1e6, "command": 1e6, "rest_length": 1e6,
             "push_force": 1e9, "push_point": 1e6}
_STATE_KEYS = ("pos", "quat", "vel", "angvel")
_STEP_KEYS = ("command", "rest_length", "push_force", "push_point")


def _validate(d: Dataset) -> None:
    if not (np.isfinite(d.dt) and 0 < d.dt <= 10):
        raise DatasetError(f"'dt' must be a positive finite time step (at most 10 s), got {d.dt}")
    if np.shape(d.gravity) != (3,) or not np.all(np.abs(d.gravity) <= 1e3):
        raise DatasetError(f"'gravity' must be 3 finite numbers (at most 1e3 m/s^2), got {d.gravity}")
    if d.pos.ndim != 4:
        raise DatasetError(f"'pos' must have shape (E, T+1, R, 3), got {d.pos.shape}")
    E, T1, R, _ = d.pos.shape
    S, A = len(d.tendon_names), len(d.actuated_names)
    U = len(d.actuator_names)
    if U == 0 and np.size(d.ctrl) == 0 and np.shape(d.ctrl) != (E, T1 - 1, 0):
        object.__setattr__(d, "ctrl", np.zeros((E, T1 - 1, 0)))  # no actuators: an empty record
    if np.size(d.weight):
        w = np.asarray(d.weight)
        if w.shape != (E, T1 - 1, R):
            raise DatasetError(f"'weight' must have shape {(E, T1 - 1, R)} (one per rod and step), got {w.shape}")
        if not np.all((w >= 0) & (w <= 1)):
            raise DatasetError("'weight' holds values outside [0, 1]")
    ctrl = np.asarray(d.ctrl)
    if ctrl.shape != (E, T1 - 1, U):
        raise DatasetError(f"'ctrl' must have shape {(E, T1 - 1, U)} (one command per actuator and step), "
                           f"got {ctrl.shape}")
    if U and not np.all(np.isfinite(ctrl)):
        raise DatasetError("'ctrl' holds non-finite values")
    if T1 < 2:
        raise DatasetError("the dataset holds fewer than 2 instants per episode: no step to learn from")
    if E < 1 or R < 1:
        raise DatasetError(f"the dataset holds {E} episodes of {R} rods: nothing to learn from")
    if R != len(d.rod_names):
        raise DatasetError(f"'pos' has {R} rods but 'rod_names' names {len(d.rod_names)}")
    if not set(d.actuated_names) <= set(d.tendon_names):
        raise DatasetError("'actuated_names' must be a subset of 'tendon_names'")
    expected = {
        "pos": (E, T1, R, 3),
        "quat": (E, T1, R, 4),
        "vel": (E, T1, R, 3),
        "angvel": (E, T1, R, 3),
        "command": (E, T1 - 1, A),
        "rest_length": (E, T1 - 1, S),
        "push_force": (E, T1 - 1, R, 3),
        "push_point": (E, T1 - 1, R, 3),
    }
    for key, shape in expected.items():
        arr = getattr(d, key)
        if arr.shape != shape:
            raise DatasetError(f"'{key}' has shape {arr.shape}, expected {shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise DatasetError(f"'{key}' holds a non-finite value ({arr[idx]}) at index {idx}")
        big = np.abs(arr) > PLAUSIBLE[key]
        if big.any():
            idx = tuple(int(i) for i in np.argwhere(big)[0])
            raise DatasetError(f"'{key}' holds {arr[idx]:.3g} at index {idx}: beyond any plausible value "
                               f"(|x| <= {PLAUSIBLE[key]:g} in SI units)")
    noise = np.asarray(d.noise, dtype=float)
    if noise.shape != (4,) or not np.all(np.isfinite(noise)) or np.any(noise < 0) or noise[2] > np.pi:
        raise DatasetError(f"'noise' must be 4 finite standard deviations >= 0 (pos, vel, quat <= pi, angvel), "
                           f"got {noise.tolist()}")
    norm = np.linalg.norm(d.quat, axis=-1)
    tol = max(QUAT_TOL, 6.0 * float(d.noise[2]))
    off = np.abs(norm - 1.0) > tol
    if off.any():
        idx = tuple(int(i) for i in np.argwhere(off)[0])
        raise DatasetError(f"'quat' is not a unit quaternion at index {idx} (norm {norm[idx]:.6g})")
    if np.any(d.rest_length < 0):
        idx = tuple(int(i) for i in np.argwhere(d.rest_length < 0)[0])
        raise DatasetError(f"'rest_length' is negative at index {idx}")


def load_dataset(path: str | os.PathLike) -> Dataset:
    """Load and validate a dataset written by :func:`save_dataset` (or ``tensegrity collect``)."""
    p = os.fspath(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            files = set(z.files)
            if "format" not in files:
                raise DatasetError(f"'{p}' is not a tensegrity dataset (no 'format' key)")
            fmt = str(z["format"])
            if fmt != FORMAT:
                raise DatasetError(f"'{p}' has format '{fmt}', this version reads '{FORMAT}'")
            required = {"dt", "gravity", "rod_names", "tendon_names", "actuated_names", *_STATE_KEYS, *_STEP_KEYS}
            missing = sorted(required - files)
            if missing:
                raise DatasetError(f"'{p}' lacks the key(s) {', '.join(missing)}")
            arrays = {k: z[k] for k in files}
    except DatasetError:
        raise
    except FileNotFoundError:
        raise DatasetError(f"dataset '{p}' does not exist") from None
    except ValueError as exc:
        if "pickle" in str(exc):  # numpy's advice to load it unsafely as a pickle is not for a dataset
            raise DatasetError(f"'{p}' is not an .npz dataset (neither a zip archive nor a numpy array)") from None
        raise DatasetError(f"'{p}' is not a readable .npz dataset (truncated or foreign): {exc}") from None
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"'{p}' is not a readable .npz dataset (truncated or foreign): {exc}") from None
    try:
        d = _from_arrays(arrays)
    except (TypeError, ValueError, OverflowError) as exc:  # names not a list, dt or seed not a number
        raise DatasetError(f"'{p}': a key has the wrong type ({exc})") from None
    try:
        return d.validate()
    except DatasetError as exc:
        raise DatasetError(f"'{p}': {exc}") from None


def _from_arrays(arrays: dict[str, np.ndarray]) -> Dataset:
    for k in ("rod_names", "tendon_names", "actuated_names"):
        if np.ndim(arrays[k]) != 1:
            raise TypeError(f"'{k}' must be a list of names, got an array of shape {np.shape(arrays[k])}")
    return Dataset(
        dt=float(arrays["dt"]),
        gravity=np.asarray(arrays["gravity"], dtype=np.float64),
        rod_names=tuple(str(x) for x in arrays["rod_names"]),
        tendon_names=tuple(str(x) for x in arrays["tendon_names"]),
        actuated_names=tuple(str(x) for x in arrays["actuated_names"]),
        noise=np.asarray(arrays.get("noise", np.zeros(4)), dtype=np.float64).reshape(4),
        seed=int(arrays.get("seed", -1)),
        actuator_names=tuple(str(x) for x in np.atleast_1d(arrays.get("actuator_names", np.array([], dtype=str)))),
        ctrl=np.asarray(arrays.get("ctrl", np.zeros((0, 0, 0))), dtype=np.float64),
        weight=np.asarray(arrays.get("weight", np.zeros((0, 0, 0))), dtype=np.float64),
        **{k: np.asarray(arrays[k], dtype=np.float64) for k in (*_STATE_KEYS, *_STEP_KEYS)},
    )


def save_dataset(path: str | os.PathLike, d: Dataset) -> None:
    """Validate and write ``d`` atomically (temporary file in the same folder, then rename)."""
    d.validate()
    arrays = {f.name: getattr(d, f.name) for f in fields(d) if f.name != "replicas"}
    arrays["format"] = np.array(FORMAT)
    for k in ("rod_names", "tendon_names", "actuated_names", "actuator_names"):
        arrays[k] = np.array(arrays[k], dtype=str)
    arrays["dt"] = np.array(d.dt)
    arrays["seed"] = np.array(d.seed)

    def write(fh) -> None:
        np.savez_compressed(fh, **arrays)

    atomic_write(path, write, binary=True)


def atomic_write(path: str | os.PathLike, writer, binary: bool = False) -> None:
    """Call ``writer(fh)`` on a temporary file beside ``path``, then rename it into place.

    Nothing is left behind on failure or interrupt, and an existing file is replaced only whole.
    """
    p = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(p)
    if not os.path.isdir(folder):
        raise OSError(f"cannot write '{path}': folder '{folder}' does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.basename(p), dir=folder)
    except OSError as exc:  # name the user's path, not the temporary file's
        raise OSError(f"cannot write '{path}': {exc.strerror or exc}") from None
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would hide the file from other users
        with os.fdopen(fd, "wb" if binary else "w", **({} if binary else {"encoding": "utf-8"})) as fh:
            writer(fh)
        os.replace(tmp, p)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError) and tmp in str(exc):
            raise OSError(f"cannot write '{path}': {exc.strerror or exc}") from None
        raise
