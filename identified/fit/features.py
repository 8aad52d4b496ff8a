"""Regression features: the equations of motion written linearly in the physical parameters.

Every step ``t`` of every rod ``i`` gives six equations (paper, eqs. 1-4, with the Euler
discretisation of the integration module):

* translation (world frame):  ``M_i (a_i - g) - sum_j T_j s_ij u_j - h f_u = 0``
* rotation (rod frame):       ``I a_b + w_b x (I w_b) - R^T( sum_j r_ij x T_j s_ij u_j + r_u x h f_u ) = 0``

with the spring tension reduced to 1D, ``T_j = K_j x_j + c_j xdot_j`` (stretch ``x_j`` beyond the
rest length, dead-banded for cables, and stretch rate ``xdot_j``), ``s_ij = +1/-1`` for the two
ends and ``u_j`` the unit vector along the spring.  Accelerations come from consecutive recorded
states exactly as a semi-implicit Euler step produces them: ``a = (v[t+1]-v[t])/dt`` and
``a_b = (R[t+1]^T w[t+1] - R[t]^T w[t])/dt``.  Every term is linear in
``(K, c, M, Ixx, Iyy, Izz, h)``, so the unknowns follow by linear least squares.

The spring geometry is the engine's own (:mod:`identified.engine.forces`): one place for the physics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from identified.engine.forces import endpoint_kinematics, spring_geometry
from identified.fit.layout import ParameterLayout
from identified.rotation import quat_to_matrix
from identified.topology import Topology

__all__ = ["Chunk", "equation_rows", "block_columns"]


@dataclass
class Chunk:
    """A slab of consecutive steps, flattened over (episode, time): ``N`` steps.

    ``pos, quat, vel, angvel``: (N, R, .) at instant t; ``vel_next, angvel_next, quat_next``: at
    t + 1; ``rest``: (N, S); ``push_force``, ``push_point``: (N, R, 3).
    """

    pos: torch.Tensor
    quat: torch.Tensor
    vel: torch.Tensor
    angvel: torch.Tensor
    quat_next: torch.Tensor
    vel_next: torch.Tensor
    angvel_next: torch.Tensor
    rest: torch.Tensor
    push_force: torch.Tensor
    push_point: torch.Tensor


def block_columns(topology: Topology, layout: ParameterLayout) -> list[np.ndarray]:
    """Columns of the full parameter vector that each equation block can touch.

    Blocks are ordered ``[trans rod0, rot rod0, trans rod1, rot rod1, ...]``; restricting each
    block's QR to its own columns keeps the work proportional to the graph's degree.
    """
    cols = []
    for i in range(topology.n_rods):
        js = np.array(topology.springs_of_rod(i), dtype=np.int64)
        springs = np.concatenate([layout.k(js), layout.c(js)])
        cols.append(np.sort(np.concatenate([springs, [layout.m(i), layout.h]])))
        rot = [layout.inertia(i, a) for a in range(3)]
        cols.append(np.sort(np.concatenate([springs, rot, [layout.h]])))
    return cols


def equation_rows(
    topology: Topology,
    layout: ParameterLayout,
    chunk: Chunk,
    dt: float,
    gravity: torch.Tensor,
) -> torch.Tensor:
    """The regression matrix of a chunk: (N, R, 6, n_full); rows 0-2 translation, 3-5 rotation.

    The equations are homogeneous (``A theta = 0``): the scale is fixed later by an anchor.
    """
    N, R = chunk.pos.shape[:2]
    S = topology.n_springs
    dtype, device = chunk.pos.dtype, chunk.pos.device
    A = torch.zeros(N, R, layout.n_full, 6, dtype=dtype, device=device)  # rows last for indexing

    rot = quat_to_matrix(chunk.quat)  # (N, R, 3, 3)
    ends = endpoint_kinematics(topology, chunk.pos, chunk.quat, chunk.vel, chunk.angvel)
    length, rate, unit = spring_geometry(ends)
    stretch = length - chunk.rest
    pull = torch.as_tensor(topology.pull_only, device=device)
    stretch = torch.where(pull, stretch.clamp_min(0.0), stretch)

    end_rods = topology.endpoint_rods
    js = np.arange(S)
    for e, sign in ((0, 1.0), (1, -1.0)):
        on_rod = end_rods[:, e] >= 0
        if not on_rod.any():
            continue
        j = torch.as_tensor(js[on_rod], device=device)
        ri = torch.as_tensor(end_rods[on_rod, e], device=device)
        u = sign * unit[:, j]  # (N, s, 3) direction of the force on this end per unit tension
        lever = ends.lever[:, j, e]  # (N, s, 3) world lever arm from the rod's COM
        rot_i = rot[:, ri]  # (N, s, 3, 3)
        fk = -stretch[:, j, None] * u
        fc = -rate[:, j, None] * u
        A[:, ri, layout.k(j), 0:3] = fk
        A[:, ri, layout.c(j), 0:3] = fc
        A[:, ri, layout.k(j), 3:6] = _to_body(rot_i, torch.cross(lever, fk, dim=-1))
        A[:, ri, layout.c(j), 3:6] = _to_body(rot_i, torch.cross(lever, fc, dim=-1))

    # mass: M (a - g)
    acc = (chunk.vel_next - chunk.vel) / dt
    rods = torch.arange(R, device=device)
    A[:, rods, layout.m(rods), 0:3] = acc - gravity
    # inertia: I a_b + w_b x (I w_b), linear in (Ixx, Iyy, Izz)
    w = _to_body(rot, chunk.angvel)
    w_next = _to_body(quat_to_matrix(chunk.quat_next), chunk.angvel_next)
    alpha = (w_next - w) / dt
    wx, wy, wz = w.unbind(-1)
    A[:, rods, layout.inertia(rods, 0), 3:6] = torch.stack([alpha[..., 0], wz * wx, -wx * wy], -1)
    A[:, rods, layout.inertia(rods, 1), 3:6] = torch.stack([-wy * wz, alpha[..., 1], wx * wy], -1)
    A[:, rods, layout.inertia(rods, 2), 3:6] = torch.stack([wy * wz, -wz * wx, alpha[..., 2]], -1)
    # control force scalar h: - h f_u, torque - R^T (R r_u x h f_u)
    lever_u = torch.einsum("nrab,nrb->nra", rot, chunk.push_point)
    A[:, :, layout.h, 0:3] = -chunk.push_force
    A[:, :, layout.h, 3:6] = -_to_body(rot, torch.cross(lever_u, chunk.push_force, dim=-1))
    return A.transpose(-1, -2)


def _to_body(rot: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """R^T v for batched rotation matrices (..., 3, 3) and vectors (..., 3)."""
    return torch.einsum("...ba,...b->...a", rot, v)
