"""Input checks of the plant and of every backend: one place, below both.

The MuJoCo plant (:mod:`tensegrity_gym.plant`) and the backends (:mod:`tensegrity_gym.backends`)
call these at their entry points, so a bad shape or a NaN gives the same one-line ``ValueError``
whichever physics is behind the env.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tensegrity_gym.cables import MotorSpec

__all__ = ["check_push", "check_rest_lengths", "check_substeps", "check_targets"]


def check_substeps(n_substeps: Any) -> int:
    """``n_substeps`` as an int >= 1 (ValueError otherwise)."""
    if int(n_substeps) != n_substeps or n_substeps < 1:
        raise ValueError(f"n_substeps must be an integer >= 1, got {n_substeps}")
    return int(n_substeps)


def check_targets(target_rest: Any, n_actuated: int) -> np.ndarray:
    """(A,) finite motor targets as float64 (ValueError on a bad shape or a non-finite value)."""
    t = np.asarray(target_rest, dtype=float)
    if t.shape != (n_actuated,):
        raise ValueError(f"targets must have shape ({n_actuated},), got {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError("targets must be finite")
    return t


def check_rest_lengths(rest_lengths: Any, n: int, actuated_index: np.ndarray, motor: MotorSpec) -> np.ndarray:
    """(n,) rest lengths as float64: finite, positive, actuated ones inside the motor bounds."""
    r = np.asarray(rest_lengths, dtype=float)
    if r.shape != (n,) or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"rest_lengths must be {n} finite positive numbers, got shape {r.shape}")
    act = r[actuated_index]
    if np.any(act < motor.rest_min - 1e-12) or np.any(act > motor.rest_max + 1e-12):
        raise ValueError("rest_lengths of actuated cables must lie inside the motor bounds (rest_bounds())")
    return r


def check_push(push_force: Any, push_point: Any, n_rods: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The optional push: (R, 3) finite world force and (R, 3) finite rod-frame point, float64;
    a point without a force is an error."""
    if push_force is None:
        if push_point is not None:
            raise ValueError("push_point given without push_force")
        return None, None
    f = np.asarray(push_force, dtype=float)
    if f.shape != (n_rods, 3) or not np.isfinite(f).all():
        raise ValueError(f"push_force must be finite with shape ({n_rods}, 3), got {f.shape}")
    if push_point is None:
        return f, None
    p = np.asarray(push_point, dtype=float)
    if p.shape != (n_rods, 3) or not np.isfinite(p).all():
        raise ValueError(f"push_point must be finite with shape ({n_rods}, 3), got {p.shape}")
    return f, p
