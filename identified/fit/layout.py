"""Where each physical parameter sits in the regression's parameter vector.

The full vector is ``[K (S), c (S), M (R), I (R x 3: Ixx, Iyy, Izz), h]``.  ``single`` regressors tie
all springs to one K and one c and all rods to one M and one I (paper, uniform parameters);
``multiple`` keeps one per spring and per rod (paper, non-uniform: 54 parameters + inertias for
the icosahedron).  The tie is a 0/1 matrix ``G`` with ``theta_full = G @ theta_free``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identified.topology import Topology

__all__ = ["REGRESSORS", "ParameterLayout"]

REGRESSORS = ("single", "multiple")
AXES = ("xx", "yy", "zz")


@dataclass(frozen=True)
class ParameterLayout:
    """Index bookkeeping between physical parameters and regression columns."""

    n_springs: int
    n_rods: int
    regressors: str
    spring_names: tuple[str, ...]
    rod_names: tuple[str, ...]

    @classmethod
    def for_topology(cls, topology: Topology, regressors: str = "multiple") -> ParameterLayout:
        if regressors not in REGRESSORS:
            raise ValueError(f"regressors must be one of {', '.join(REGRESSORS)}, got '{regressors}'")
        return cls(topology.n_springs, topology.n_rods, regressors, topology.spring_names, topology.rod_names)

    # ---------------------------------------------------------------- full-vector column indices
    @property
    def n_full(self) -> int:
        return 2 * self.n_springs + 4 * self.n_rods + 1

    def k(self, j: int | np.ndarray) -> int | np.ndarray:
        return j

    def c(self, j: int | np.ndarray) -> int | np.ndarray:
        return self.n_springs + j

    def m(self, i: int | np.ndarray) -> int | np.ndarray:
        return 2 * self.n_springs + i

    def inertia(self, i: int | np.ndarray, axis: int) -> int | np.ndarray:
        return 2 * self.n_springs + self.n_rods + 3 * i + axis

    @property
    def h(self) -> int:
        return self.n_full - 1

    @property
    def full_names(self) -> list[str]:
        names = [f"{s}.stiffness" for s in self.spring_names]
        names += [f"{s}.damping" for s in self.spring_names]
        names += [f"{r}.mass" for r in self.rod_names]
        names += [f"{r}.inertia_{a}" for r in self.rod_names for a in AXES]
        return names + ["control_scale"]

    # ---------------------------------------------------------------- tying
    @property
    def tie(self) -> np.ndarray:
        """``G`` (n_full, n_free): full parameters as a function of the free ones."""
        if self.regressors == "multiple":
            return np.eye(self.n_full)
        S, R = self.n_springs, self.n_rods
        G = np.zeros((self.n_full, 7))
        G[0:S, 0] = 1.0  # K
        G[S : 2 * S, 1] = 1.0  # c
        G[2 * S : 2 * S + R, 2] = 1.0  # M
        for a in range(3):
            G[[self.inertia(i, a) for i in range(R)], 3 + a] = 1.0
        G[self.h, 6] = 1.0
        return G

    @property
    def free_names(self) -> list[str]:
        if self.regressors == "multiple":
            return self.full_names
        return ["stiffness", "damping", "mass", "inertia_xx", "inertia_yy", "inertia_zz", "control_scale"]

    def describe_free(self, weights: np.ndarray, threshold: float = 0.1) -> list[str]:
        """Names of free parameters that carry a direction vector (for rank-deficiency messages)."""
        w = np.abs(weights) / max(np.abs(weights).max(), 1e-300)
        return [n for n, x in zip(self.free_names, w) if x > threshold]
