"""Inputs and targets the learned baselines share: reduced spring features per rod end, states as
flat vectors, and acceleration targets that the integration module turns back into states.

* :func:`end_features` — the paper's pre-processing (eq. 1): for every spring end on a rod, the
  reduced relative position ``Δp̂ = (L - L0) u`` and velocity ``Δv̂ = (Δv·u) u``, with ``u`` the
  unit vector from this end to the spring's other end, so that the spring's force on the end is
  ``K Δp̂ + c Δv̂`` (eq. 2); plus the half-rod vector ``r`` (world, to the rod's "+" end).
* :func:`acceleration_targets` — the linear and angular acceleration that, integrated by the
  semi-implicit Euler module (:func:`identified.engine.integration.semi_implicit_euler`), maps
  ``S_t`` exactly to ``S_{t+1}``: ``a = (v⁺ - v)/dt``, ``α = R_t (R_{t+1}ᵀ w⁺ - R_tᵀ w)/dt``
  (world frame).
* :func:`integrate` — that module, taking the world-frame ``(a, α)`` a baseline predicts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from identified.engine.forces import SpringGraph, endpoint_kinematics, spring_geometry, spring_stretch
from identified.engine.integration import RodState, semi_implicit_euler
from identified.rotation import matrix_apply, matrix_apply_transpose, quat_to_matrix
from identified.topology import Topology

__all__ = ["EndSlots", "acceleration_targets", "end_features", "integrate", "state_vector", "vector_state"]


@dataclass(frozen=True)
class EndSlots:
    """Which spring ends sit on each rod, in a fixed order.

    ``index`` (R, n) long: flat index ``2 j + e`` of spring ``j``'s end ``e`` (0 where padded);
    ``valid`` (R, n) bool; ``plus`` (R, n) bool: the end is the rod's "+" end (along ``half``);
    ``half`` (R, 3): half-rod vector in the rod frame, from the centre to the "+" end.
    Slots are ordered "+" end first, then by spring index.
    """

    index: torch.Tensor
    valid: torch.Tensor
    plus: torch.Tensor
    half: torch.Tensor

    @classmethod
    def from_topology(cls, topo: Topology) -> EndSlots:
        R = topo.n_rods
        half = np.zeros((R, 3))
        for i, rod in enumerate(topo.rods):
            o = rod.site_offsets
            d = np.linalg.norm(o[:, None] - o[None], axis=-1)
            a, b = np.unravel_index(np.argmax(d), d.shape)
            h = 0.5 * (o[a] - o[b])
            k = int(np.argmax(np.abs(h)))  # orient "+" along the dominant rod-frame axis
            half[i] = h if h[k] > 0 else -h
        slots: list[list[tuple[bool, int]]] = [[] for _ in range(R)]
        for j, s in enumerate(topo.springs):
            for e in (0, 1):
                i = s.rods[e]
                if i >= 0:
                    slots[i].append((bool(np.dot(s.offsets[e], half[i]) > 0), 2 * j + e))
        n = max(len(x) for x in slots) if slots else 0
        index = np.zeros((R, n), dtype=np.int64)
        valid = np.zeros((R, n), dtype=bool)
        plus = np.zeros((R, n), dtype=bool)
        for i, x in enumerate(slots):
            x.sort(key=lambda t: (not t[0], t[1]))
            for k, (p, idx) in enumerate(x):
                index[i, k], valid[i, k], plus[i, k] = idx, True, p
        return cls(torch.as_tensor(index), torch.as_tensor(valid), torch.as_tensor(plus), torch.as_tensor(half))


def end_features(graph: SpringGraph, slots: EndSlots, state: RodState, rest: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(r, dp, dv)``: half-rod vectors (..., R, 3) and the reduced spring features of every
    slot of :class:`EndSlots` (..., R, n, 3) each (zero in padded slots), eq. 1.

    ``state`` tensors (..., R, ·); ``rest`` (..., S) rest lengths.
    """
    pos, quat, vel, angvel = state
    rot = quat_to_matrix(quat)
    ends = endpoint_kinematics(graph, pos, quat, vel, angvel, rot=rot)
    geom = spring_geometry(ends)
    stretch = spring_stretch(geom.length, rest, graph.pull_only)
    p = (stretch.unsqueeze(-1) * geom.unit)  # (..., S, 3): from end 0 towards end 1
    v = (geom.rate.unsqueeze(-1) * geom.unit)
    sign = torch.tensor([1.0, -1.0], dtype=p.dtype, device=p.device).view(2, 1)
    p_end = (p.unsqueeze(-2) * sign).flatten(-3, -2)  # (..., 2S, 3): end e sees the other end
    v_end = (v.unsqueeze(-2) * sign).flatten(-3, -2)
    idx = slots.index.to(p.device)
    mask = slots.valid.to(p.device).unsqueeze(-1).to(p.dtype)
    dp = p_end[..., idx, :] * mask
    dv = v_end[..., idx, :] * mask
    r = matrix_apply(rot, slots.half.to(dtype=p.dtype, device=p.device))
    return r, dp, dv


def acceleration_targets(s0: RodState, s1: RodState, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """World ``(a, α)`` (..., R, 3) each, that semi-implicit Euler turns ``s0`` into ``s1`` with."""
    r0, r1 = quat_to_matrix(s0.quat), quat_to_matrix(s1.quat)
    a = (s1.vel - s0.vel) / dt
    alpha_b = (matrix_apply_transpose(r1, s1.angvel) - matrix_apply_transpose(r0, s0.angvel)) / dt
    return a, matrix_apply(r0, alpha_b)


def integrate(s: RodState, a: torch.Tensor, alpha: torch.Tensor, dt: float) -> RodState:
    """The integration module (semi-implicit Euler) driven by world ``a``, ``α`` (..., R, 3)."""
    rot = quat_to_matrix(s.quat)
    return semi_implicit_euler(s.pos, s.quat, s.vel, matrix_apply_transpose(rot, s.angvel), a,
                               matrix_apply_transpose(rot, alpha), dt)


def state_vector(s: RodState) -> torch.Tensor:
    """``S_t`` as (..., R, 13): position, quaternion w-x-y-z, velocity, angular velocity."""
    return torch.cat([s.pos, s.quat, s.vel, s.angvel], dim=-1)


def vector_state(x: torch.Tensor) -> RodState:
    """Inverse of :func:`state_vector`; the quaternion is normalised (a predicted one may not be)."""
    q = x[..., 3:7]
    return RodState(x[..., 0:3], q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12), x[..., 7:10], x[..., 10:13])
