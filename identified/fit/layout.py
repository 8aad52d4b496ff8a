"""Where each physical parameter sits in the regression's parameter vector.

The full vector is a concatenation of parameter *blocks* (:class:`~identified.effects.base.ParamBlock`):
the paper's ``K (S), c (S), M (R), I (R x 3: Ixx, Iyy, Izz), h``, with ``rest_lengths=True`` the
preload ``P = K l0 (S)`` of every spring (a passive spring's tension ``K (l - l0) = K l - P`` is
linear in ``K`` and ``P``, so its rest length ``l0 = P / K`` is identified; an actuated cable's rest
length is its command, an input, and its ``P`` column stays empty), then one block group per effect
fitted jointly with them (:mod:`identified.effects`); offsets follow from the block sizes.
``single`` regressors tie all springs to one K and one c and all rods to one M and one I (paper,
uniform parameters); ``multiple`` keeps one per spring and per rod (paper, non-uniform: 54
parameters + inertias for the icosahedron).  The tie is a 0/1 matrix ``G`` with
``theta_full = G @ theta_free``; preloads (each spring's rest length is its own geometry, not a
material parameter: the paper's simple system has springs of 1 m and 1.414 m), actuators and effect
parameters are never tied.

With ``full_inertia`` each rod's inertial parameters are the standard ten of rigid-body
identification (Atkeson, An & Hollerbach 1986): the mass ``M``, the first moment ``M c`` (3, the
centre of mass ``c`` in the rod frame) and the inertia tensor about the rod frame's origin (its
diagonal ``Ixx, Iyy, Izz`` in the ``inertia`` block, its products ``Jxy, Jxz, Jyz`` here); the
Newton-Euler equations about the origin are linear in all ten.  The block of first moments and
products follows the rest-length steps; without it the rod frame is taken at the centre of mass
along the principal axes (the diagonal model, the special case ``M c = 0``, no products).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identified.effects.base import Effect, ParamBlock
from identified.topology import Topology

__all__ = ["BASE_BLOCKS", "REGRESSORS", "ParameterLayout"]

REGRESSORS = ("single", "multiple")
AXES = ("xx", "yy", "zz")
PRODUCTS = ("xy", "xz", "yz")
#: the full-inertia block per rod: first moment M c (x, y, z), then the products of inertia
INERTIAL = ("first_moment_x", "first_moment_y", "first_moment_z", "inertia_xy", "inertia_xz", "inertia_yz")

#: the spring-rod model's own blocks, in order (paper eqs. 1-4)
BASE_BLOCKS = (
    ParamBlock("stiffness", "spring", unit="N/m"),
    ParamBlock("damping", "spring", unit="N s/m"),
    ParamBlock("mass", "rod", unit="kg"),
    ParamBlock("inertia", "rod", width=3, unit="kg m^2"),
    ParamBlock("control_scale", "global", mass_scaled=False),
)


@dataclass(frozen=True)
class ParameterLayout:
    """Index bookkeeping between physical parameters and regression columns."""

    n_springs: int
    n_rods: int
    regressors: str
    spring_names: tuple[str, ...]
    rod_names: tuple[str, ...]
    effects: tuple[Effect, ...] = field(default=())
    rest_lengths: bool = False  # the preload block P = K l0 is part of the vector
    actuators: tuple[str, ...] = ()  # MuJoCo tendon actuators: gain, bias, gain x d(time constant)
    #: the rest-length step block (S): a joint effect's law switches at a passive spring's rest length
    #: (``Effect.reads_rest_length``), and its Gauss-Newton column in that rest length is fitted with it
    rest_steps: bool = False
    #: each rod's first moment and products of inertia are identified (module docstring)
    full_inertia: bool = False

    @classmethod
    def for_topology(cls, topology: Topology, regressors: str = "multiple",
                     effects: Sequence[Effect] = (), rest_lengths: bool = False,
                     actuators: bool = False, full_inertia: bool = False) -> ParameterLayout:
        """The layout of a topology; ``rest_lengths``: identify passive springs' rest lengths
        (the preload block, and the rest-length step block when an effect's law reads them);
        ``actuators``: identify the force law of its MuJoCo tendon actuators; ``full_inertia``:
        every rod's centre of mass and products of inertia."""
        if regressors not in REGRESSORS:
            raise ValueError(f"regressors must be one of {', '.join(REGRESSORS)}, got '{regressors}'")
        forces = tuple(a.name for a in topology.force_actuators) if actuators else ()
        steps = bool(rest_lengths) and any(e.reads_rest_length for e in effects)
        return cls(topology.n_springs, topology.n_rods, regressors, topology.spring_names, topology.rod_names,
                   tuple(effects), bool(rest_lengths), forces, steps, bool(full_inertia))

    # ---------------------------------------------------------------- blocks and offsets
    @property
    def n_base(self) -> int:
        """Size of the spring-rod blocks ``[K, c, M, I, h]`` (and ``P`` when rest lengths are identified)."""
        return self._inertial_offset + 6 * self.n_rods * self.full_inertia

    @property
    def _inertial_offset(self) -> int:
        """Full-vector index of the first-moment/products block (its end when there is none)."""
        return (sum(b.size(self.n_rods, self.n_springs) for b in BASE_BLOCKS) + self.n_springs * self.rest_lengths
                + 3 * len(self.actuators) + self.n_springs * self.rest_steps)

    def effect_offset(self, k: int) -> int:
        """Full-vector index of the first parameter of effect ``k``."""
        return self.n_base + sum(e.n_params for e in self.effects[:k])

    def effect_slice(self, k: int) -> slice:
        o = self.effect_offset(k)
        return slice(o, o + self.effects[k].n_params)

    @property
    def n_full(self) -> int:
        return self.n_base + sum(e.n_params for e in self.effects)

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
        return 2 * self.n_springs + 4 * self.n_rods

    def preload(self, j: int | np.ndarray) -> int | np.ndarray:
        """Full-vector index of spring ``j``'s preload ``P = K l0`` (only with ``rest_lengths``)."""
        if not self.rest_lengths:
            raise ValueError("this layout does not identify rest lengths")
        return self.h + 1 + j

    def gain(self, a: int | np.ndarray) -> int | np.ndarray:
        """Full-vector index of actuator ``a``'s gain (force on its tendon per unit activation, N)."""
        return self.h + 1 + self.n_springs * self.rest_lengths + a

    def bias(self, a: int | np.ndarray) -> int | np.ndarray:
        """Full-vector index of actuator ``a``'s constant bias force on its tendon, N."""
        return self.gain(a) + len(self.actuators)

    def gain_dtau(self, a: int | np.ndarray) -> int | np.ndarray:
        """Full-vector index of ``gain x d tau`` of actuator ``a`` (the Gauss-Newton step of its
        filter's time constant, :mod:`identified.fit.actuation`)."""
        return self.gain(a) + 2 * len(self.actuators)

    def rest_step(self, j: int | np.ndarray) -> int | np.ndarray:
        """Full-vector index of spring ``j``'s rest-length step ``q = -kappa dl0`` (only with
        ``rest_steps``): the Gauss-Newton column of the law that reads the rest length, held at 0
        once the rest lengths settle."""
        if not self.rest_steps:
            raise ValueError("this layout has no rest-length steps")
        return self.gain(0) + 3 * len(self.actuators) + j

    def first_moment(self, i: int | np.ndarray, axis: int) -> int | np.ndarray:
        """Full-vector index of rod ``i``'s first moment ``M c`` along a rod-frame axis (kg m; only
        with ``full_inertia``)."""
        if not self.full_inertia:
            raise ValueError("this layout does not identify centres of mass")
        return self._inertial_offset + 6 * i + axis

    def product(self, i: int | np.ndarray, k: int) -> int | np.ndarray:
        """Full-vector index of rod ``i``'s product of inertia ``k`` (0: xy, 1: xz, 2: yz) about
        the rod frame's origin, kg m² (only with ``full_inertia``)."""
        return self.first_moment(i, 3 + k)

    def inertial(self, i: int) -> list[int]:
        """Full-vector indices of rod ``i``'s ten inertial parameters ``[M, Ixx, Iyy, Izz, Mcx,
        Mcy, Mcz, Jxy, Jxz, Jyz]`` about the rod frame's origin (the order of
        :func:`identified.model.com_and_tensor`; only with ``full_inertia``)."""
        return [self.m(i), *(self.inertia(i, a) for a in range(3)), *(self.first_moment(i, k) for k in range(6))]

    @property
    def signed(self) -> np.ndarray:
        """(n_full,) bool: parameters that may be negative (the rest are physical magnitudes)."""
        out = np.zeros(self.n_full, dtype=bool)
        if self.rest_lengths:  # P = K (l0 - l_ref): negative where the spring is stretched on average
            out[self.preload(np.arange(self.n_springs))] = True
        if self.actuators:  # bias and the time-constant step
            U = np.arange(len(self.actuators))
            out[self.bias(U)] = out[self.gain_dtau(U)] = True
        if self.rest_steps:
            out[self.rest_step(np.arange(self.n_springs))] = True
        if self.full_inertia:
            out[self._inertial_offset:self.n_base] = True
        for k, e in enumerate(self.effects):
            out[self.effect_slice(k)] = e.signed_mask()
        return out

    @property
    def full_names(self) -> list[str]:
        names = [f"{s}.stiffness" for s in self.spring_names]
        names += [f"{s}.damping" for s in self.spring_names]
        names += [f"{r}.mass" for r in self.rod_names]
        names += [f"{r}.inertia_{a}" for r in self.rod_names for a in AXES]
        names += ["control_scale"]
        if self.rest_lengths:
            names += [f"{s}.preload" for s in self.spring_names]
        for kind in ("gain", "bias", "gain_dtau"):
            names += [f"{a}.{kind}" for a in self.actuators]
        if self.rest_steps:
            names += [f"{s}.rest_step" for s in self.spring_names]
        if self.full_inertia:
            names += [f"{r}.{x}" for r in self.rod_names for x in INERTIAL]
        for e in self.effects:
            names += e.param_names(self.rod_names, self.spring_names)
        return names

    # ---------------------------------------------------------------- tying
    @property
    def tie(self) -> np.ndarray:
        """``G`` (n_full, n_free): full parameters as a function of the free ones."""
        if self.regressors == "multiple":
            return np.eye(self.n_full)
        S, R = self.n_springs, self.n_rods
        n_eff = self.n_full - self.n_base
        U = len(self.actuators)
        n_own = S * self.rest_lengths + 3 * U + S * self.rest_steps  # one column each
        n_tied = 7 + n_own
        n_inert = 6 * self.full_inertia  # one rod's first moment and products, shared by all rods
        G = np.zeros((self.n_full, n_tied + n_inert + n_eff))
        G[0:S, 0] = 1.0  # K
        G[S : 2 * S, 1] = 1.0  # c
        G[2 * S : 2 * S + R, 2] = 1.0  # M
        for a in range(3):
            G[[self.inertia(i, a) for i in range(R)], 3 + a] = 1.0
        G[self.h, 6] = 1.0
        G[self.h + 1 : self._inertial_offset, 7:n_tied] = np.eye(n_own)  # preloads, actuators, rest steps
        for k in range(n_inert):
            G[[self.first_moment(i, k) for i in range(R)], n_tied + k] = 1.0
        G[self.n_base:, n_tied + n_inert:] = np.eye(n_eff)
        return G

    @property
    def free_names(self) -> list[str]:
        if self.regressors == "multiple":
            return self.full_names
        base = ["stiffness", "damping", "mass", "inertia_xx", "inertia_yy", "inertia_zz", "control_scale"]
        base += self.full_names[self.h + 1 : self._inertial_offset]  # preloads, actuators, rest steps: untied
        base += list(INERTIAL) if self.full_inertia else []
        return base + self.full_names[self.n_base:]

    def describe_free(self, weights: np.ndarray, threshold: float = 0.1) -> list[str]:
        """Names of free parameters that carry a direction vector (for rank-deficiency messages)."""
        w = np.abs(weights) / max(np.abs(weights).max(), 1e-300)
        return [n for n, x in zip(self.free_names, w) if x > threshold]
