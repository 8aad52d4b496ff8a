"""The state of every rod of a spring-rod system: one name, :class:`RodState`, for numpy and torch.

The engine steps it as torch tensors; the plant, the env backends and the env read it as numpy
arrays.  Either way the fields are the same four, world frame, SI units:

* ``pos`` (..., R, 3) centre-of-mass position, m;
* ``quat`` (..., R, 4) orientation w-x-y-z (body frame -> world; rod axis = body z);
* ``vel`` (..., R, 3) linear velocity of the centre of mass, m/s;
* ``angvel`` (..., R, 3) angular velocity in the WORLD frame, rad/s.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

__all__ = ["RodState"]

_WIDTHS = (("pos", 3), ("quat", 4), ("vel", 3), ("angvel", 3))


class RodState(NamedTuple):
    """Rod states (see the module docstring): numpy arrays or torch tensors, (..., R, ·) each."""

    pos: Any
    quat: Any
    vel: Any
    angvel: Any

    def copy(self) -> RodState:
        """A copy whose arrays (or tensors) the caller may change."""
        return RodState(*(x.clone() if hasattr(x, "clone") else np.array(x, copy=True) for x in self))

    def validate(self, n_rods: int) -> RodState:
        """The states as float64 numpy arrays (R, ·) after checking shapes, finiteness and that no
        quaternion is zero; ValueError naming the bad field."""
        out = []
        for (name, width), x in zip(_WIDTHS, self, strict=True):
            a = np.asarray(x, dtype=float)
            if a.shape != (n_rods, width):
                raise ValueError(f"RodState.{name} must have shape ({n_rods}, {width}), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"RodState.{name} has non-finite values")
            out.append(a)
        if np.any(np.linalg.norm(out[1], axis=-1) < 1e-9):
            raise ValueError("RodState.quat has a zero quaternion")
        return RodState(*out)
