"""Force generation module (paper, Sec. "Force Generation Module", eqs. 1-2).

Each spring ``j`` joins two end points; an end is a point fixed in a rod (given in the rod frame)
or a fixed anchor (given in the world frame).  The module reduces every spring from 3D to 1D along
its axis (eq. 1) and projects the 1D tension back to 3D (eq. 2):

* end kinematics   ``p_e = p[rod] + R(q[rod]) o_e``,  ``v_e = v[rod] + w[rod] × (R o_e)``
  (anchors: ``p_e = o_e``, ``v_e = 0``); ``R o_e`` is the end's world *lever arm*;
* geometry (eq. 1) ``Δ = p_1 - p_0``, ``L = |Δ|``, ``u = Δ / L``, ``L̇ = (v_1 - v_0)·u``;
* tension (eq. 2)  ``T = K s + c L̇`` with stretch ``s = L - L0``, or ``s = max(L - L0, 0)`` for a
  pull-only cable (MuJoCo's dead-band tendon ``springlength="0 L0"``).  Like MuJoCo, the damping
  term ``c L̇`` acts whether or not a cable is slack (MuJoCo's tendon damper is independent of the
  dead band), so a slack cable still resists changes of its length;
* end forces       ``f_0 = +T u`` on end 0 and ``f_1 = -T u`` on end 1 (a positive tension pulls the
  two ends together).

The paper writes eq. 2 as ``|f| = -K|Δp̂| ∓ c|Δv̂|`` with the sign of the force along ``Δp``; the
signed form above is the same law with tension counted positive.

Shapes: ``S`` springs, ``R`` rods, ``...`` any leading (batch) dimensions shared by the state, the
rest lengths and (broadcastably) the parameters.  Everything is vectorised over springs through
index tensors built once in :class:`SpringGraph`; no Python loop over rods or springs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from identified.engine.smallmat import Mat, Vec, gather, mat, mv, unvec, vadd, vcross, vdot, vec, vsub
from identified.rotation import quat_to_matrix
from identified.topology import Topology

__all__ = [
    "EndpointKinematics",
    "SpringGeometry",
    "SpringGraph",
    "end_kinematics",
    "endpoint_kinematics",
    "spring_end_forces",
    "spring_end_forces_components",
    "spring_geometry",
    "spring_geometry_components",
    "spring_stretch",
    "spring_tension",
]


@dataclass(frozen=True)
class SpringGraph:
    """The topology as index tensors, built once (on a dtype and device) and reused every step.

    ``endpoint_rods`` (S, 2) long: rod of each spring end, anchors replaced by 0 so gathers stay in
    range; ``on_rod`` (S, 2) bool: the end is on a rod (False: fixed anchor); ``offsets`` (S, 2, 3):
    rod-frame point, or the anchor's world position; ``pull_only`` (S,) bool; ``end_index`` (E,)
    long: flat index ``2 j + e`` of every end that is on a rod; ``end_rod`` (E,) long: its rod.

    The same in the component form of the fused step (ends END-MAJOR: the S ends 0, then the S
    ends 1): ``ends_rod`` (2S,) long (anchors 0), ``ends_on`` (2S,) bool, ``ends_offset`` (3, 2S);
    ``rod_ends`` (R, K) long: the end-major index of every end on each rod, padded with 0 to the
    largest count K, and ``rod_ends_weight`` (R, K): 1 for an end, 0 for padding (the sum of the
    forces on a rod's ends is a gather and a short sum, no scatter).
    """

    n_rods: int
    n_springs: int
    endpoint_rods: torch.Tensor
    on_rod: torch.Tensor
    offsets: torch.Tensor
    pull_only: torch.Tensor
    end_index: torch.Tensor
    end_rod: torch.Tensor
    ends_rod: torch.Tensor
    ends_on: torch.Tensor
    ends_offset: torch.Tensor
    rod_ends: torch.Tensor
    rod_ends_weight: torch.Tensor

    @classmethod
    def from_topology(
        cls,
        topology: Topology,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> SpringGraph:
        return cls.from_arrays(
            topology.n_rods, topology.endpoint_rods, topology.endpoint_offsets, topology.pull_only,
            dtype=dtype, device=device,
        )

    @classmethod
    def from_arrays(
        cls,
        n_rods: int,
        endpoint_rods: np.ndarray,
        endpoint_offsets: np.ndarray,
        pull_only: np.ndarray,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> SpringGraph:
        """From plain arrays: (S, 2) int rods (-1 = anchor), (S, 2, 3) offsets, (S,) bool."""
        rods = np.asarray(endpoint_rods, dtype=np.int64).reshape(-1, 2)
        S = rods.shape[0]
        offsets = np.asarray(endpoint_offsets, dtype=np.float64).reshape(S, 2, 3)
        pull = np.asarray(pull_only, dtype=bool).reshape(S)
        if np.any(rods >= n_rods) or np.any(rods < -1):
            raise ValueError(f"endpoint_rods must lie in [-1, {n_rods - 1}]")
        on_rod = rods >= 0
        flat = np.flatnonzero(on_rod.reshape(-1))
        em_rods, em_on = rods.T.reshape(-1), on_rod.T.reshape(-1)  # end-major
        lists = [np.flatnonzero(em_on & (em_rods == r)) for r in range(int(n_rods))]
        K = max([len(x) for x in lists] + [1])
        rod_ends = np.zeros((int(n_rods), K), dtype=np.int64)
        weight = np.zeros((int(n_rods), K))
        for r, ends in enumerate(lists):
            rod_ends[r, :len(ends)] = ends
            weight[r, :len(ends)] = 1.0
        return cls(
            n_rods=int(n_rods),
            n_springs=int(S),
            endpoint_rods=torch.as_tensor(np.where(on_rod, rods, 0), device=device),
            on_rod=torch.as_tensor(on_rod, device=device),
            offsets=torch.as_tensor(offsets, dtype=dtype, device=device),
            pull_only=torch.as_tensor(pull, device=device),
            end_index=torch.as_tensor(flat, device=device),
            end_rod=torch.as_tensor(rods.reshape(-1)[flat], device=device),
            ends_rod=torch.as_tensor(np.where(em_on, em_rods, 0), device=device),
            ends_on=torch.as_tensor(em_on, device=device),
            ends_offset=torch.as_tensor(offsets.transpose(2, 1, 0).reshape(3, 2 * S).copy(), dtype=dtype,
                                        device=device),
            rod_ends=torch.as_tensor(rod_ends, device=device),
            rod_ends_weight=torch.as_tensor(weight, dtype=dtype, device=device),
        )

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> SpringGraph:
        """The same graph with its float tensors in ``dtype`` and all tensors on ``device``."""
        dev = self.offsets.device if device is None else torch.device(device)
        return SpringGraph(
            n_rods=self.n_rods,
            n_springs=self.n_springs,
            endpoint_rods=self.endpoint_rods.to(dev),
            on_rod=self.on_rod.to(dev),
            offsets=self.offsets.to(device=dev, dtype=dtype or self.offsets.dtype),
            pull_only=self.pull_only.to(dev),
            end_index=self.end_index.to(dev),
            end_rod=self.end_rod.to(dev),
            ends_rod=self.ends_rod.to(dev),
            ends_on=self.ends_on.to(dev),
            ends_offset=self.ends_offset.to(device=dev, dtype=dtype or self.offsets.dtype),
            rod_ends=self.rod_ends.to(dev),
            rod_ends_weight=self.rod_ends_weight.to(device=dev, dtype=dtype or self.offsets.dtype),
        )


def as_graph(graph: SpringGraph | Topology, like: torch.Tensor) -> SpringGraph:
    """``graph`` as a :class:`SpringGraph` with the dtype and device of ``like``."""
    if isinstance(graph, SpringGraph):
        if graph.offsets.dtype == like.dtype and graph.offsets.device == like.device:
            return graph
        return graph.to(like.dtype, like.device)
    return SpringGraph.from_topology(graph, dtype=like.dtype, device=like.device)


class EndpointKinematics(NamedTuple):
    """World position, velocity and lever arm of every spring end, each (..., S, 2, 3).

    ``lever[..., j, e]`` is ``R(q) o`` of end ``e`` of spring ``j`` (the world vector from its rod's
    centre of mass to the end); zero for a fixed anchor.  ``velocity`` is zero for anchors.
    """

    point: torch.Tensor
    velocity: torch.Tensor
    lever: torch.Tensor


class SpringGeometry(NamedTuple):
    """The 1D reduction of every spring (eq. 1): ``length`` (..., S), ``rate`` (..., S) = dL/dt,
    ``unit`` (..., S, 3) from end 0 to end 1."""

    length: torch.Tensor
    rate: torch.Tensor
    unit: torch.Tensor


def endpoint_kinematics(
    graph: SpringGraph | Topology,
    pos: torch.Tensor,
    quat: torch.Tensor,
    vel: torch.Tensor,
    angvel: torch.Tensor,
    rot: torch.Tensor | None = None,
) -> EndpointKinematics:
    """End points of every spring from the rod states.

    ``pos`` (..., R, 3), ``quat`` (..., R, 4) w-x-y-z, ``vel`` (..., R, 3) world, ``angvel``
    (..., R, 3) WORLD frame; ``rot`` (..., R, 3, 3), optional, ``quat_to_matrix(quat)`` if already
    computed.  Returns :class:`EndpointKinematics` with fields (..., S, 2, 3).  The formulas are
    :func:`end_kinematics` (component form), stacked.
    """
    g = as_graph(graph, pos)
    if rot is None:
        rot = quat_to_matrix(quat)
    point, velocity, lever = end_kinematics(g, vec(pos), vec(vel), vec(angvel), mat(rot))
    S = g.n_springs

    def spring_major(v: Vec) -> torch.Tensor:  # (..., 2S) x 3, end-major -> (..., S, 2, 3)
        return unvec(v).unflatten(-2, (2, S)).transpose(-3, -2)

    return EndpointKinematics(spring_major(point), spring_major(velocity), spring_major(lever))


def end_kinematics(g: SpringGraph, pos: Vec, vel: Vec, angvel: Vec, rot: Mat) -> tuple[Vec, Vec, Vec]:
    """Component form of :func:`endpoint_kinematics`: rod states as components (..., R) (``rot``
    the nine entries of ``R(q)``) -> world point, velocity and lever arm of every spring end,
    components (..., 2S), END-MAJOR (the S ends 0, then the S ends 1).

    ``lever = R o``, ``point = p + lever``, ``velocity = v + w × lever`` for an end on a rod; an
    anchor's point is its world position, its lever and velocity zero."""
    idx, on = g.ends_rod, g.ends_on
    off = tuple(g.ends_offset.unbind(0))
    lever = tuple(torch.where(on, x, 0.0) for x in mv(gather(rot, idx), off))
    point = tuple(torch.where(on, p + lv, o) for p, lv, o in zip(gather(pos, idx), lever, off))
    velocity = vadd(gather(vel, idx), vcross(gather(angvel, idx), lever))
    velocity = tuple(torch.where(on, x, 0.0) for x in velocity)
    return point, velocity, lever


def spring_geometry(ends: EndpointKinematics) -> SpringGeometry:
    """Eq. 1: length ``L = |p_1 - p_0|``, rate ``L̇ = (v_1 - v_0)·u`` and unit ``u`` of each spring.

    A zero-length spring has no direction: its ``unit`` and ``rate`` are NaN (no exception).
    The formulas are :func:`spring_geometry_components`.
    """
    length, rate, unit = spring_geometry_components(
        vec(ends.point[..., 0, :]), vec(ends.point[..., 1, :]),
        vec(ends.velocity[..., 0, :]), vec(ends.velocity[..., 1, :]))
    return SpringGeometry(length, rate, unvec(unit))


def spring_geometry_components(p0: Vec, p1: Vec, v0: Vec, v1: Vec) -> tuple[torch.Tensor, torch.Tensor, Vec]:
    """Eq. 1 in component form: end points and velocities (..., S) each -> ``L``, ``L̇`` (..., S)
    and the unit vector's components."""
    delta = vsub(p1, p0)
    length = torch.sqrt(vdot(delta, delta))
    unit = (delta[0] / length, delta[1] / length, delta[2] / length)
    return length, vdot(vsub(v1, v0), unit), unit


def spring_stretch(length: torch.Tensor, rest_length: torch.Tensor, pull_only: torch.Tensor) -> torch.Tensor:
    """Stretch ``s = L - L0``, dead-banded ``max(L - L0, 0)`` where ``pull_only`` (S,) is True.

    ``length`` (..., S), ``rest_length`` (..., S) -> (..., S).
    """
    stretch = length - rest_length
    return torch.where(pull_only, stretch.clamp_min(0.0), stretch)


def spring_tension(
    length: torch.Tensor,
    rate: torch.Tensor,
    rest_length: torch.Tensor,
    stiffness: torch.Tensor,
    damping: torch.Tensor,
    pull_only: torch.Tensor,
) -> torch.Tensor:
    """Eq. 2 in 1D: tension ``T = K s + c L̇`` (positive = pulling the ends together), (..., S).

    ``length``, ``rate``, ``rest_length`` (..., S); ``stiffness``, ``damping`` (S,) or
    broadcastable (..., S); ``pull_only`` (S,) bool.  The damping acts on slack cables too (as in
    MuJoCo, whose tendon damper ignores the spring's dead band).
    """
    return stiffness * spring_stretch(length, rest_length, pull_only) + damping * rate


def spring_end_forces(unit: torch.Tensor, tension: torch.Tensor) -> torch.Tensor:
    """Eq. 2 back to 3D: the force on each end, (..., S, 2, 3): ``+T u`` on end 0, ``-T u`` on end 1
    (:func:`spring_end_forces_components`, stacked)."""
    S = tension.shape[-1]
    return unvec(spring_end_forces_components(vec(unit), tension)).unflatten(-2, (2, S)).transpose(-3, -2)


def spring_end_forces_components(unit: Vec, tension: torch.Tensor) -> Vec:
    """Component form of :func:`spring_end_forces`: unit components and tension (..., S) -> the end
    forces' components (..., 2S), end-major."""
    return tuple(torch.cat((tension * u, -(tension * u)), -1) for u in unit)
