"""The cable motor model, in one place for the MuJoCo plant and the identified twin.

A motor reels its cable so that the cable's rest length follows a target at bounded speed and
within bounds (per step of length dt):

    rest' = clip(rest + clip(target - rest, -v dt, +v dt), rest_min, rest_max)

The motor specification (which tendons are actuated, v, rest_min, rest_max) is read from the MJCF
``<custom>`` section, from the XML text alone (no MuJoCo needed; parsed by :mod:`identified.mjcf`)
or from a compiled ``MjModel``:

    <text    name="tensegrity_actuated"    data="cable0 cable3 ..."/>
    <numeric name="tensegrity_motor_speed" data="v"/>            (m/s)
    <numeric name="tensegrity_rest_min"    data="..."/>          (m, one per actuated cable)
    <numeric name="tensegrity_rest_max"    data="..."/>          (m, one per actuated cable)

This module also holds :func:`scripted_roll_targets`, the documented open-loop cable sequence that
rolls the ``ico/robot`` preset over to a neighbouring face (pure numpy, so the twin can run it too).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from identified.mjcf import ACTUATED_KEY, custom_entries, parse_mjcf, read_mjcf_text

__all__ = [
    "ACTUATED_KEY",
    "REST_MAX_KEY",
    "REST_MIN_KEY",
    "ROBOT_ROLL_SEQUENCE",
    "SPEED_KEY",
    "MotorSpec",
    "motor_step",
    "read_motor_spec",
    "scripted_roll_targets",
]

SPEED_KEY = "tensegrity_motor_speed"
REST_MIN_KEY = "tensegrity_rest_min"
REST_MAX_KEY = "tensegrity_rest_max"


def motor_step(rest: Any, target: Any, speed: float, dt: float, rest_min: Any, rest_max: Any) -> Any:
    """Rest lengths after one motor step of ``dt`` seconds.

    ``rest + clip(target - rest, -speed*dt, speed*dt)``, then clipped to ``[rest_min, rest_max]``.
    Shapes broadcast (``(..., A)``); works on numpy arrays and on torch tensors alike (bounds of the
    same kind).
    """
    dv = speed * dt
    if isinstance(rest, np.ndarray):  # ufuncs: a few times faster than ndarray.clip on short vectors
        nxt = rest + np.minimum(np.maximum(target - rest, -dv), dv)
        return np.minimum(np.maximum(nxt, rest_min), rest_max)
    nxt = rest + (target - rest).clip(-dv, dv)
    return nxt.clip(rest_min, rest_max)


@dataclass(frozen=True)
class MotorSpec:
    """Which cables have motors and how those motors are limited.

    Attributes:
        names: (A,) actuated tendon names, in command order.
        speed: largest rest-length rate, m/s.
        rest_min, rest_max: (A,) rest-length bounds, m.
    """

    names: tuple[str, ...]
    speed: float
    rest_min: np.ndarray
    rest_max: np.ndarray

    def __post_init__(self) -> None:
        A = len(self.names)
        lo = np.asarray(self.rest_min, dtype=float).reshape(-1)
        hi = np.asarray(self.rest_max, dtype=float).reshape(-1)
        if A and lo.size == 1:
            lo = np.full(A, lo[0])
        if A and hi.size == 1:
            hi = np.full(A, hi[0])
        if lo.shape != (A,) or hi.shape != (A,):
            raise ValueError(
                f"motor bounds need one value per actuated cable ({A}); "
                f"got {lo.size} minima and {hi.size} maxima"
            )
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
            raise ValueError("motor bounds must be finite with rest_min <= rest_max for every actuated cable")
        if A and not (np.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"motor speed must be a finite number > 0 m/s, got {self.speed}")
        object.__setattr__(self, "rest_min", lo)
        object.__setattr__(self, "rest_max", hi)
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def n(self) -> int:
        """Number of actuated cables A."""
        return len(self.names)

    def advance(self, rest: np.ndarray, target: np.ndarray, dt: float) -> np.ndarray:
        """(..., A) rest lengths after one step of ``dt`` toward ``target`` (see :func:`motor_step`)."""
        return motor_step(np.asarray(rest, float), np.asarray(target, float), self.speed, dt,
                          self.rest_min, self.rest_max)

    def clip(self, target: np.ndarray) -> np.ndarray:
        """Targets clipped into the motor's range."""
        return np.clip(np.asarray(target, dtype=float), self.rest_min, self.rest_max)


def _spec_from_xml(text: str) -> MotorSpec:
    texts, numeric = custom_entries(parse_mjcf(text))
    return _assemble(texts.get(ACTUATED_KEY, "").split(), numeric)


def _spec_from_mjmodel(model: Any) -> MotorSpec:
    import mujoco

    names: list[str] = []
    numeric: dict[str, np.ndarray] = {}
    for i in range(model.ntext):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_TEXT, i)
        if name == ACTUATED_KEY:
            a, n = model.text_adr[i], model.text_size[i]
            names = bytes(model.text_data[a : a + n]).decode().rstrip("\x00").split()
    for i in range(model.nnumeric):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_NUMERIC, i)
        a, n = model.numeric_adr[i], model.numeric_size[i]
        numeric[name] = np.array(model.numeric_data[a : a + n], dtype=float)
    return _assemble(names, numeric)


def _assemble(names: list[str], numeric: dict[str, np.ndarray]) -> MotorSpec:
    if not names:
        return MotorSpec((), 0.0, np.zeros(0), np.zeros(0))
    missing = [k for k in (SPEED_KEY, REST_MIN_KEY, REST_MAX_KEY) if k not in numeric]
    if missing:
        raise ValueError(
            f"the model lists actuated cables but has no <numeric name=\"{missing[0]}\"> in <custom>"
        )
    speed = numeric[SPEED_KEY]
    if speed.size != 1:
        raise ValueError(f"{SPEED_KEY} must hold one number (m/s), got {speed.size}")
    return MotorSpec(tuple(names), float(speed[0]), numeric[REST_MIN_KEY], numeric[REST_MAX_KEY])


def read_motor_spec(source: str | os.PathLike | Any) -> MotorSpec:
    """The motor specification of a model: an MJCF path, MJCF text, or a ``mujoco.MjModel``.

    Paths and text are parsed with ``xml.etree`` (MuJoCo is not imported). A model without
    ``tensegrity_actuated`` has no motors (``MotorSpec.n == 0``).
    """
    if not isinstance(source, (str, os.PathLike)):
        return _spec_from_mjmodel(source)
    return _spec_from_xml(read_mjcf_text(source))


#: Cables of the ``ico/robot`` preset reeled in, one per roll, by :func:`scripted_roll_targets`.
#: Each is an edge of the closed triangle the robot stands on at that moment (found by simulating
#: every edge of the supporting face and keeping the one that moves the robot furthest along +x):
#: roll 1 ``cable2`` (rod0_end0-rod4_end0), then ``cable4`` (rod0_end1-rod3_end0), ``cable22``
#: (rod3_end1-rod5_end0), ``cable15`` (rod1_end1-rod5_end1). Centre-of-mass displacement after each
#: roll from the nominal pose (x, y) ~ (0.84, -0.18), (1.52, 0.35), (2.36, 0.17), (3.04, 0.70) m
#: (zig-zag: consecutive closed faces of the icosahedron alternate their orientation).
ROBOT_ROLL_SEQUENCE: tuple[str, ...] = ("cable2", "cable4", "cable22", "cable15")


def scripted_roll_targets(
    spec: MotorSpec,
    neutral: np.ndarray,
    dt: float,
    rolls: int = 1,
    contract_time: float = 2.0,
    release_time: float = 2.5,
    sequence: tuple[str, ...] = ROBOT_ROLL_SEQUENCE,
) -> np.ndarray:
    """(T, A) open-loop motor targets that roll the ``ico/robot`` preset from its nominal pose.

    Roll k: the cable ``sequence[k]``, an edge of the closed triangle the robot stands on, is reeled
    in to its ``rest_min`` for ``contract_time`` seconds while every other cable holds its neutral
    rest length (the motor needs (neutral - rest_min) / speed = 1.5 s to get there). Shortening that
    edge pulls two ground contacts toward each other and folds the structure over the third side;
    the centre of mass leaves the support triangle and the robot tips onto the neighbouring closed
    face, its centre of mass about 0.85 m further on (roll 1 goes along +x, 0.84 m in x, -0.18 m
    in y). Then all targets return to neutral for ``release_time`` seconds (1.5 s of motor travel,
    then settling) and the robot stands in its nominal shape on the new face.
    ``T = rolls * (round(contract_time / dt) + round(release_time / dt))``.

    Args:
        spec: the robot's motor spec (names give the cable order of the targets).
        neutral: (A,) rest lengths held outside a contraction (the model's rest lengths).
        dt: physics time step, s.
        rolls: how many rolls, 1 .. len(sequence).
        sequence: cable names reeled in, one per roll.
    """
    neutral = np.asarray(neutral, dtype=float)
    if neutral.shape != (spec.n,):
        raise ValueError(f"neutral must have shape ({spec.n},), got {neutral.shape}")
    if not 1 <= rolls <= len(sequence):
        raise ValueError(f"rolls must be between 1 and {len(sequence)}, got {rolls}")
    index = {n: i for i, n in enumerate(spec.names)}
    missing = [c for c in sequence[:rolls] if c not in index]
    if missing:
        raise ValueError(f"cable '{missing[0]}' of the roll sequence is not actuated in this model")
    n_c, n_r = round(contract_time / dt), round(release_time / dt)
    out = np.tile(neutral, (rolls * (n_c + n_r), 1))
    for k, name in enumerate(sequence[:rolls]):
        j = index[name]
        start = k * (n_c + n_r)
        out[start : start + n_c, j] = spec.rest_min[j]
    return out
