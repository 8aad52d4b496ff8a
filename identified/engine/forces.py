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

from identified.rotation import matrix_apply, quat_to_matrix
from identified.topology import Topology

__all__ = [
    "EndpointKinematics",
    "SpringGeometry",
    "SpringGraph",
    "endpoint_kinematics",
    "spring_end_forces",
    "spring_geometry",
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
    """

    n_rods: int
    n_springs: int
    endpoint_rods: torch.Tensor
    on_rod: torch.Tensor
    offsets: torch.Tensor
    pull_only: torch.Tensor
    end_index: torch.Tensor
    end_rod: torch.Tensor

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
        return cls(
            n_rods=int(n_rods),
            n_springs=int(S),
            endpoint_rods=torch.as_tensor(np.where(on_rod, rods, 0), device=device),
            on_rod=torch.as_tensor(on_rod, device=device),
            offsets=torch.as_tensor(offsets, dtype=dtype, device=device),
            pull_only=torch.as_tensor(pull, device=device),
            end_index=torch.as_tensor(flat, device=device),
            end_rod=torch.as_tensor(rods.reshape(-1)[flat], device=device),
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
    computed.  Returns :class:`EndpointKinematics` with fields (..., S, 2, 3).
    """
    g = as_graph(graph, pos)
    if rot is None:
        rot = quat_to_matrix(quat)
    S = g.n_springs
    idx = g.endpoint_rods.reshape(-1)  # (2S,)
    on = g.on_rod.reshape(-1, 1)  # (2S, 1)
    off = g.offsets.reshape(-1, 3)  # (2S, 3)
    lever = matrix_apply(rot.index_select(-3, idx), off)
    lever = torch.where(on, lever, 0.0)
    point = torch.where(on, pos.index_select(-2, idx) + lever, off)
    velocity = vel.index_select(-2, idx) + torch.cross(angvel.index_select(-2, idx), lever, dim=-1)
    velocity = torch.where(on, velocity, 0.0)
    shape = point.shape[:-2] + (S, 2, 3)
    return EndpointKinematics(point.reshape(shape), velocity.reshape(shape), lever.reshape(shape))


def spring_geometry(ends: EndpointKinematics) -> SpringGeometry:
    """Eq. 1: length ``L = |p_1 - p_0|``, rate ``L̇ = (v_1 - v_0)·u`` and unit ``u`` of each spring.

    A zero-length spring has no direction: its ``unit`` and ``rate`` are NaN (no exception).
    """
    delta = ends.point[..., 1, :] - ends.point[..., 0, :]
    length = torch.linalg.vector_norm(delta, dim=-1)
    unit = delta / length.unsqueeze(-1)
    rate = ((ends.velocity[..., 1, :] - ends.velocity[..., 0, :]) * unit).sum(-1)
    return SpringGeometry(length, rate, unit)


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
    """Eq. 2 back to 3D: the force on each end, (..., S, 2, 3): ``+T u`` on end 0, ``-T u`` on end 1."""
    f0 = tension.unsqueeze(-1) * unit
    return torch.stack((f0, -f0), dim=-2)
