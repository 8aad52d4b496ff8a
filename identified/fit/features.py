"""Regression features: the equations of motion written linearly in the physical parameters.

Every step ``t`` of every rod ``i`` gives six equations (paper, eqs. 1-4, with the Euler
discretisation of the integration module):

* translation (world frame):  ``M_i (a_i - g) - sum_j T_j s_ij u_j - h f_u = 0``
* rotation (rod frame):       ``I a_b + w_b x (I w_b) - R^T( sum_j r_ij x T_j s_ij u_j + r_u x h f_u ) = 0``

with the spring tension reduced to 1D, ``T_j = K_j x_j + c_j xdot_j`` (stretch ``x_j`` beyond the
rest length, dead-banded for cables, and stretch rate ``xdot_j``), ``s_ij = +1/-1`` for the two
ends and ``u_j`` the unit vector along the spring.  The accelerations ``a`` and ``a_b`` come from
the recorded states (:mod:`identified.samples`).  Every term is linear in
``(K, c, M, Ixx, Iyy, Izz, h)``, so the unknowns follow by linear least squares.

A passive spring's rest length ``l0`` is not an input but a parameter: its tension while taut is
``K (l - l_ref) - P`` with ``P = K (l0 - l_ref)`` (``l_ref`` a fixed reference length), linear in
``(K, P)``; a pull-only cable is taut while ``l > l0`` (``chunk.rest`` holds the fit's current
estimate of ``l0`` for the passive springs, :func:`identified.fit.identify.identify`).  A MuJoCo
tendon actuator adds ``-(g act + b)`` to its tendon's tension (:mod:`identified.engine.actuators`),
linear in its gain ``g`` and bias ``b``, and ``-g dtau (d act / d tau)`` for the Gauss-Newton step of
a filter's time constant (:mod:`identified.fit.actuation`).

A plant on MuJoCo's implicit integrators (``implicit``, ``implicitfast``) steps with
``(M - dt D) qacc = f`` (:mod:`identified.engine.integration`); its equations keep the same form
with two extra terms that are still linear in the parameters: each damper sees the stretch rate
``xdot_j + dt rho_j`` (``rho_j`` the rate of change of ``xdot_j`` from its own rod's acceleration),
and the rotation gains ``dt (w_b x (I a_b) + a_b x (I w_b))`` (``implicit_dt`` in
:func:`equation_rows`).

The spring geometry and the implicit terms are the engine's own (:mod:`identified.engine.forces`,
:mod:`identified.engine.integration`): one place for the physics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from identified.effects.base import Effect
from identified.engine.engine import StepContext
from identified.engine.forces import (
    SpringGeometry,
    SpringGraph,
    endpoint_kinematics,
    spring_geometry,
    spring_stretch,
)
from identified.engine.integration import (
    RodState,
    gyroscopic_derivative,
    implicit_rate_correction,
    spring_rate_rows,
)
from identified.fit.layout import ParameterLayout
from identified.rotation import matrix_apply, matrix_apply_transpose, quat_to_matrix
from identified.samples import Chunk
from identified.topology import Topology

__all__ = ["RodColumns", "chunk_context", "effect_rows", "equation_rows", "fit_context", "step_context"]


@dataclass(frozen=True)
class RodColumns:
    """Per-rod local columns: ``[K of its springs (D), c of its springs (D), M, Ixx, Iyy, Izz, h]``,
    then (when the layout identifies rest lengths) ``P = K l0`` of its springs (D) and, when an
    effect's law reads them, their rest-length steps (D), then the actuators', then the effects'.

    ``D`` is the largest number of springs on one rod; unused slots (rods with fewer springs, and
    the ``P`` slot of an actuated cable, whose rest length is its command) map to full index -1
    and stay zero.  Building the equations in this compact form keeps the work
    proportional to the graph's degree, not to the total number of parameters.
    """

    full: np.ndarray  # (R, 2D + 5 + E) full-vector index of each local column, -1 for padding
    slot: np.ndarray  # (S, 2) local slot of spring j on the rod at each of its ends (-1 for anchors)
    degree: int
    effect_start: tuple[int, ...] = ()  # first local column of each joint effect
    preload: bool = False  # the P columns follow h (passive springs' rest lengths identified)
    #: the rest-length step columns (D) follow the P columns: d(law)/d l0 of the joint effect that
    #: reads the rest length (``Effect.reads_rest_length``), per unit ``q = -kappa dl0``
    rest_steps: bool = False
    #: (S,) a reference length per spring, m: a passive spring's columns are ``l - l_ref`` (K) and
    #: ``-1`` (``P = K (l0 - l_ref)``) while taut, which keeps K and P apart where ``l`` varies little
    length_ref: np.ndarray | None = None
    #: MuJoCo tendon actuators (layout order): the spring each acts on, (U,), and the local slot of
    #: its columns on the rod at each end of that spring (U, 2; -1 for anchors); the rod's columns
    #: ``gain`` (W), ``bias`` (W), ``gain x d tau`` (W) start at ``actuator_start``
    actuator_spring: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    actuator_slot: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    actuator_start: int = 0
    actuator_width: int = 0
    #: the rod's first moment ``M c`` (3) and products of inertia (3) start here (-1: the layout
    #: has no full inertia)
    inertial_start: int = -1

    @classmethod
    def build(cls, topology: Topology, layout: ParameterLayout, length_ref: np.ndarray | None = None) -> RodColumns:
        """The columns of ``layout`` on ``topology``; ``length_ref`` (S,): the reference lengths of
        the preload columns (0 when not given: ``P = K l0``)."""
        R, S = topology.n_rods, topology.n_springs
        per_rod = [topology.springs_of_rod(i) for i in range(R)]
        D = max(len(x) for x in per_rod)
        widths = [D * e.width if e.kind == "spring" else e.width for e in layout.effects]
        P = D if layout.rest_lengths else 0
        Q = D if layout.rest_steps else 0
        U = len(layout.actuators)
        a_spring = np.array([topology.spring_names.index(next(a.tendon for a in topology.actuators if a.name == n))
                             for n in layout.actuators], dtype=np.int64)
        per_rod_act = [[a for a in range(U) if i in topology.springs[a_spring[a]].rods] for i in range(R)]
        W = max((len(x) for x in per_rod_act), default=0)
        F = 6 if layout.full_inertia else 0
        full = -np.ones((R, 2 * D + 5 + P + Q + 3 * W + F + sum(widths)), dtype=np.int64)
        slot = -np.ones((S, 2), dtype=np.int64)
        for i, js in enumerate(per_rod):
            for k, j in enumerate(js):
                full[i, k], full[i, D + k] = layout.k(j), layout.c(j)
                if P and not topology.springs[j].actuated:
                    full[i, 2 * D + 5 + k] = layout.preload(j)
                if Q and not topology.springs[j].actuated:
                    full[i, 2 * D + 5 + P + k] = layout.rest_step(j)
                for e in range(2):
                    if topology.springs[j].rods[e] == i:
                        slot[j, e] = k
            full[i, 2 * D] = layout.m(i)
            full[i, 2 * D + 1 : 2 * D + 4] = [layout.inertia(i, a) for a in range(3)]
            full[i, 2 * D + 4] = layout.h
        a0 = 2 * D + 5 + P + Q
        a_slot = -np.ones((U, 2), dtype=np.int64)
        for i, acts in enumerate(per_rod_act):
            for k, a in enumerate(acts):
                full[i, a0 + k], full[i, a0 + W + k], full[i, a0 + 2 * W + k] = (
                    layout.gain(a), layout.bias(a), layout.gain_dtau(a))
                for e in range(2):
                    if topology.springs[a_spring[a]].rods[e] == i:
                        a_slot[a, e] = k
        if F:
            for i in range(R):
                full[i, a0 + 3 * W : a0 + 3 * W + F] = [layout.first_moment(i, k) for k in range(F)]
        starts, col = [], a0 + 3 * W + F
        for k, (eff, w) in enumerate(zip(layout.effects, widths)):
            off = layout.effect_offset(k)
            starts.append(col)
            for i, js in enumerate(per_rod):
                if eff.kind == "global":
                    full[i, col : col + w] = off + np.arange(w)
                elif eff.kind == "rod":
                    full[i, col : col + w] = off + i * w + np.arange(w)
                else:  # slot k of the rod, component c -> parameter (spring js[k], c)
                    W = eff.width
                    full[i, col : col + len(js) * W] = (off + np.array(js, dtype=np.int64)[:, None] * W
                                                        + np.arange(W)).reshape(-1)
            col += w
        ref = np.zeros(S) if length_ref is None else np.asarray(length_ref, dtype=float).reshape(S)
        return cls(full=full, slot=slot, degree=D, effect_start=tuple(starts), preload=bool(P),
                   rest_steps=bool(Q), length_ref=ref if P else None, actuator_spring=a_spring, actuator_slot=a_slot,
                   actuator_start=a0, actuator_width=W, inertial_start=a0 + 3 * W if F else -1)

    def block_columns(self, rod: int, rotation: bool) -> np.ndarray:
        """Local columns used by the translation (M) or rotation (I) rows of a rod, padding dropped."""
        D = self.degree
        springs = [k for k in range(2 * D) if self.full[rod, k] >= 0]
        own = [2 * D + 1, 2 * D + 2, 2 * D + 3] if rotation else [2 * D]
        extra = [k for k in range(2 * D + 5, self.full.shape[1]) if self.full[rod, k] >= 0]
        return np.array(springs + own + [2 * D + 4] + extra, dtype=np.int64)


def equation_rows(
    topology: Topology,
    columns: RodColumns,
    chunk: Chunk,
    gravity: torch.Tensor,
    implicit_dt: float | None = None,
    effects: Sequence[Effect | None] = (),
    dt: float = 0.0,
) -> torch.Tensor:
    """The regression rows of a chunk in the compact per-rod layout: (N, R, 6, L) with the local
    columns of :class:`RodColumns`.

    Rows 0-2 are translation (world frame), rows 3-5 rotation (rod frame).  The equations are
    homogeneous (``A theta = 0``): the scale is fixed later by an anchor.  ``implicit_dt``: the
    time step of a plant on MuJoCo's implicit integrators (adds their terms), ``None`` for Euler.
    ``effects``: the jointly fitted effects of the layout, in order; their columns hold minus the
    force (translation rows) and minus the rod-frame torque (rotation rows) per unit parameter
    (``None`` in place of an effect: its columns left at 0, :func:`effect_rows` makes them).
    """
    N, R = chunk.pos.shape[:2]
    D = columns.degree
    L = columns.full.shape[1]
    dtype, device = chunk.pos.dtype, chunk.pos.device
    A = torch.zeros(N, 6, R, L, dtype=dtype, device=device)  # rows before rods: contiguous writes

    rot = quat_to_matrix(chunk.quat)  # (N, R, 3, 3)
    ends = endpoint_kinematics(topology, chunk.pos, chunk.quat, chunk.vel, chunk.angvel, rot=rot)
    length, rate, unit = spring_geometry(ends)
    stretch = spring_stretch(length, chunk.rest, torch.as_tensor(topology.pull_only, device=device))
    rate_e = rate.unsqueeze(-1).expand(*rate.shape, 2)  # the stretch rate each end's damper sees
    if implicit_dt:
        graph = SpringGraph.from_topology(topology, dtype=dtype, device=device)
        rows, _ = spring_rate_rows(graph, unit, ends.lever, rot)
        rate_e = rate_e + implicit_rate_correction(graph, rows, chunk.acc, chunk.alpha_body, implicit_dt)

    # springs: force per unit K (stretch) and per unit c (rate) on each end, and its torque
    sign = torch.tensor([1.0, -1.0], dtype=dtype, device=device).view(1, 1, 2, 1)
    u = sign * unit.unsqueeze(-2)  # (N, S, 2, 3): direction of the force on each end
    per_unit = [stretch, rate_e]  # what multiplies K and c in each end's tension
    starts = [0, D]  # their first local column
    if columns.preload:  # a passive spring: K l - P while taut (a cable: while longer than its rest)
        passive = torch.as_tensor(~np.array([s.actuated for s in topology.springs], dtype=bool), device=device)
        pull = torch.as_tensor(topology.pull_only, device=device)
        taut = torch.where(pull, length > chunk.rest, True).to(dtype)
        ref = torch.as_tensor(columns.length_ref, dtype=dtype, device=device)
        per_unit[0] = torch.where(passive, (length - ref) * taut, stretch)
        per_unit.append(torch.where(passive, -taut, 0.0))
        starts.append(2 * D + 5)
    n_kinds = len(per_unit)
    f = torch.stack([-(x if x.dim() == 3 else x[..., None])[..., None] * u for x in per_unit])  # (n, N, S, 2, 3)
    rods_e = torch.as_tensor(np.maximum(topology.endpoint_rods, 0), device=device)  # (S, 2)
    rot_e = rot[:, rods_e]  # (N, S, 2, 3, 3)
    tau = _to_body(rot_e, torch.cross(ends.lever.expand_as(f), f, dim=-1))
    on = np.flatnonzero(topology.endpoint_rods.reshape(-1) >= 0)  # ends on a rod (not anchors)
    flat_rod = topology.endpoint_rods.reshape(-1)[on]
    flat_slot = columns.slot.reshape(-1)[on]
    idx = torch.as_tensor(np.concatenate([flat_rod * L + c0 + flat_slot for c0 in starts]), device=device)
    pick = torch.as_tensor(on, device=device)
    vals = torch.cat([f, tau], dim=-1).reshape(n_kinds, N, -1, 6)[:, :, pick]  # (n, N, ends, 6)
    vals = torch.cat(tuple(vals), dim=1).transpose(1, 2)  # (N, 6, n * ends)
    A.view(N, 6, R * L).index_copy_(2, idx, vals)
    if len(columns.actuator_spring):
        _actuator_columns(A, columns, chunk, u, ends.lever, rot_e, topology.endpoint_rods)

    # mass: M (a - g)
    A[:, 0:3, :, 2 * D] = (chunk.acc - gravity).transpose(1, 2)
    # inertia: I a_b + w_b x (I w_b), linear in (Ixx, Iyy, Izz)
    alpha = chunk.alpha_body
    wx, wy, wz = chunk.angvel_body.unbind(-1)
    A[:, 3:6, :, 2 * D + 1] = torch.stack([alpha[..., 0], wz * wx, -wx * wy], 1)
    A[:, 3:6, :, 2 * D + 2] = torch.stack([-wy * wz, alpha[..., 1], wx * wy], 1)
    A[:, 3:6, :, 2 * D + 3] = torch.stack([wy * wz, -wz * wx, alpha[..., 2]], 1)
    if columns.inertial_start >= 0:
        if implicit_dt:
            raise ValueError("a rod's centre of mass and products of inertia are identified for the euler and "
                             "rk4 integrators, not the implicit one")
        _full_inertia_columns(A, columns.inertial_start, rot, chunk.acc - gravity, alpha, chunk.angvel_body)
    if implicit_dt:  # + dt G(I) a_b, column k with I = e_k
        eye = torch.eye(3, dtype=dtype, device=device)
        w, a, basis = torch.broadcast_tensors(chunk.angvel_body.unsqueeze(-2), alpha.unsqueeze(-2), eye)
        gyro = implicit_dt * gyroscopic_derivative(w, a, basis)  # (N, R, k, 3)
        A[:, 3:6, :, 2 * D + 1 : 2 * D + 4] += gyro.permute(0, 3, 1, 2)
    # control force scalar h: - h f_u, torque - R^T (R r_u x h f_u)
    A[:, 0:3, :, 2 * D + 4] = -chunk.push_force.transpose(1, 2)
    A[:, 3:6, :, 2 * D + 4] = -chunk.push_torque_body.transpose(1, 2)
    if any(e is not None for e in effects):
        ctx = step_context(topology, chunk, rot, ends, SpringGeometry(length, rate, unit), dt=dt)
        state = RodState(chunk.pos, chunk.quat, chunk.vel, chunk.angvel)
        for eff, c0 in zip(effects, columns.effect_start):
            if eff is not None:
                _effect_columns(A, eff, c0, state, ctx, rot, topology, columns, on, flat_rod, flat_slot)
        if columns.rest_steps:
            reader = [e for e in effects if e is not None and e.reads_rest_length]
            step = _RestStep(reader[0]) if len(reader) == 1 else None
            if step is None or reader[0].kind != "spring" or reader[0].width != 1:
                raise ValueError("the fit takes one effect whose law reads a spring's rest length, with one "
                                 f"parameter per spring; got {[e.name for e in reader]}")
            _effect_columns(A, step, 2 * D + 5 + D, state, ctx, rot, topology, columns, on, flat_rod, flat_slot)
    A = A.permute(0, 2, 1, 3)
    if chunk.row_weight is not None:
        A = A * chunk.row_weight[:, :, None, None]
    return A


def fit_context(topology: Topology, chunk: Chunk, dt: float = 0.0) -> tuple[RodState, StepContext, torch.Tensor]:
    """What an effect's columns are built from at a chunk's recorded instants, as
    :func:`equation_rows` builds them: the states, the step context and the rotations."""
    rot = quat_to_matrix(chunk.quat)
    ends = endpoint_kinematics(topology, chunk.pos, chunk.quat, chunk.vel, chunk.angvel, rot=rot)
    ctx = step_context(topology, chunk, rot, ends, spring_geometry(ends), dt=dt)
    return RodState(chunk.pos, chunk.quat, chunk.vel, chunk.angvel), ctx, rot


def effect_rows(topology: Topology, columns: RodColumns, chunk: Chunk, context: tuple[RodState, StepContext, torch.Tensor],
                effect: Effect, k: int) -> torch.Tensor:
    """The columns of the layout's ``k``-th effect alone, (N, R, 6, w) from its first local column
    ``columns.effect_start[k]``, weighted as :func:`equation_rows` weighs its rows: what that
    function writes there (``context``: :func:`fit_context` of the chunk)."""
    starts = columns.effect_start
    w = (starts[k + 1] if k + 1 < len(starts) else columns.full.shape[1]) - starts[k]
    state, ctx, rot = context
    N, R = chunk.pos.shape[:2]
    A = torch.zeros(N, 6, R, w, dtype=chunk.pos.dtype, device=chunk.pos.device)
    on = np.flatnonzero(topology.endpoint_rods.reshape(-1) >= 0)
    _effect_columns(A, effect, 0, state, ctx, rot, topology, columns, on, topology.endpoint_rods.reshape(-1)[on],
                    columns.slot.reshape(-1)[on])
    A = A.permute(0, 2, 1, 3)
    if chunk.row_weight is not None:
        A = A * chunk.row_weight[:, :, None, None]
    return A


def _actuator_columns(A: torch.Tensor, columns: RodColumns, chunk: Chunk, u: torch.Tensor, lever: torch.Tensor,
                      rot_e: torch.Tensor, end_rods: np.ndarray) -> None:
    """Write the MuJoCo tendon actuators' columns into ``A`` (N, 6, R, L).

    An actuator's force ``F = g act + b`` on its tendon (positive: lengthening, MuJoCo's
    convention; ``g`` its gain times gear, ``b`` its constant bias times gear) acts on the tendon's
    ends as a tension ``-F``; per unit ``g`` the tension is ``-act``, per unit ``b`` it is ``-1``,
    and per unit ``g dtau`` it is ``-d act / d tau`` (the Gauss-Newton column of the filter's time
    constant).  ``chunk.ctrl`` holds the activations (N, U) then their derivatives (N, U)."""
    U, W, a0 = len(columns.actuator_spring), columns.actuator_width, columns.actuator_start
    act, dact = chunk.ctrl[:, :U], chunk.ctrl[:, U : 2 * U]
    js = torch.as_tensor(columns.actuator_spring, device=A.device)
    for k, x in enumerate((act, torch.ones_like(act), dact)):  # tension per unit parameter: -x
        f = x[..., None, None] * u[:, js]  # minus (minus tension along u): (N, U, 2, 3)
        tau = _to_body(rot_e[:, js], torch.cross(lever[:, js], f, dim=-1))
        vals = torch.cat([f, tau], dim=-1)  # (N, U, 2, 6)
        for a in range(U):
            for e in range(2):
                slot = int(columns.actuator_slot[a, e])
                if slot < 0:
                    continue
                rod = int(end_rods[columns.actuator_spring[a], e])
                A[:, :, rod, a0 + k * W + slot] += vals[:, a, e]


def _full_inertia_columns(A: torch.Tensor, c0: int, rot: torch.Tensor, acc_g: torch.Tensor, alpha: torch.Tensor,
                          w: torch.Tensor) -> None:
    """Write each rod's first-moment and product-of-inertia columns into ``A`` (N, 6, R, L).

    Newton-Euler about the rod frame's origin with the centre of mass at ``c`` (rod frame), the
    terms linear in ``M c`` and in the inertia's products (layout module docstring):

    * translation (world): ``+ R (α_b × Mc + w_b × (w_b × Mc))``;
    * rotation (rod frame): ``+ Mc × Rᵀ (a - g)`` and ``+ J_p α_b + w_b × (J_p w_b)`` for each
      product ``p`` (``J_p`` the symmetric unit matrix of entry ``xy``, ``xz`` or ``yz``).

    ``acc_g`` (N, R, 3) is ``a - g`` of the origin (world), ``alpha`` and ``w`` (N, R, 3) rod frame.
    """
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    a_b = matrix_apply_transpose(rot, acc_g)
    for k in range(3):
        e = eye[k].expand_as(w)
        lin = matrix_apply(rot, torch.cross(alpha, e, dim=-1) + torch.cross(w, torch.cross(w, e, dim=-1), dim=-1))
        A[:, 0:3, :, c0 + k] = lin.transpose(1, 2)
        A[:, 3:6, :, c0 + k] = torch.cross(e, a_b, dim=-1).transpose(1, 2)
    for k, (p, q) in enumerate(((0, 1), (0, 2), (1, 2))):
        J_alpha, J_w = _unit_product(alpha, p, q), _unit_product(w, p, q)
        A[:, 3:6, :, c0 + 3 + k] = (J_alpha + torch.cross(w, J_w, dim=-1)).transpose(1, 2)


def _unit_product(v: torch.Tensor, p: int, q: int) -> torch.Tensor:
    """``E v`` for the symmetric unit matrix ``E`` of entry ``(p, q)`` (ones at (p, q) and (q, p))."""
    out = torch.zeros_like(v)
    out[..., p], out[..., q] = v[..., q], v[..., p]
    return out


def step_context(topology: Topology, chunk: Chunk, rot: torch.Tensor, ends: Any,
                 geometry: SpringGeometry, params: Any = None, dt: float = 0.0) -> StepContext:
    """The engine's :class:`~identified.engine.StepContext` built from recorded states (no tension,
    no pushes, the recorded accelerations): what an effect's features read in the fit and in the
    engine alike."""
    graph = SpringGraph.from_topology(topology, dtype=chunk.pos.dtype, device=chunk.pos.device)
    return StepContext(params, dt, graph, rot, chunk.angvel_body, ends, geometry, None, chunk.rest, None, None,
                       recorded_lin_acc=chunk.acc, recorded_ang_acc_body=chunk.alpha_body)


def _effect_columns(A: torch.Tensor, eff: Effect, c0: int, state: RodState, ctx: StepContext, rot: torch.Tensor,
                    topology: Topology, columns: RodColumns, on: np.ndarray, flat_rod: np.ndarray,
                    flat_slot: np.ndarray) -> None:
    """Write an effect's columns (minus its force, minus its rod-frame torque) into ``A`` (N, 6, R, L)."""
    N, _, R, L = A.shape
    if eff.kind == "spring":
        f = eff.end_features(state, ctx)  # (N, S, 2, 3), or (N, S, 2, W, 3) for W parameters per spring
        if f.dim() == 4:
            f = f.unsqueeze(-2)
        W = f.shape[-2]
        rot_e = rot[:, torch.as_tensor(np.maximum(topology.endpoint_rods, 0), device=A.device)].unsqueeze(-3)
        tau = _to_body(rot_e, torch.cross(ctx.ends.lever.unsqueeze(-2).expand_as(f), f, dim=-1))
        vals = -torch.cat([f, tau], dim=-1).reshape(N, -1, W, 6)[:, torch.as_tensor(on, device=A.device)]
        idx = flat_rod[:, None] * L + c0 + flat_slot[:, None] * W + np.arange(W)
        A.view(N, 6, R * L).index_add_(2, torch.as_tensor(idx.reshape(-1), device=A.device),
                                       vals.reshape(N, -1, 6).transpose(1, 2))
        return
    force, torque = eff.features(state, ctx)  # (N, R, W, 3) world
    W = force.shape[-2]
    A[:, 0:3, :, c0 : c0 + W] -= force.permute(0, 3, 1, 2)
    A[:, 3:6, :, c0 : c0 + W] -= _to_body(rot.unsqueeze(-3), torque).permute(0, 3, 1, 2)


class _RestStep:
    """The Gauss-Newton column of a law that reads each spring's rest length: ``d f / d l0`` of its
    end features (one parameter per spring), so that ``kappa f(l0 + dl0) = kappa f(l0) + q d f / d l0``
    with the linear ``q = kappa dl0``; ``q -> 0`` as the rest-length estimate settles."""

    kind = "spring"

    def __init__(self, effect: Effect) -> None:
        self.effect = effect

    def end_features(self, state: RodState, ctx: StepContext) -> torch.Tensor:
        rest = ctx.rest_length
        law = lambda r: self.effect.end_features(state, ctx._replace(rest_length=r))
        return torch.func.jvp(law, (rest,), (torch.ones_like(rest),))[1]


def _to_body(rot: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """R^T v for batched rotation matrices (..., 3, 3) and vectors (..., 3)."""
    return matrix_apply_transpose(rot, v)


def chunk_context(topology: Topology, ch: Chunk, params: Any = None) -> StepContext:
    """The :class:`~identified.engine.StepContext` of a chunk of recorded instants (rotation,
    spring end kinematics and geometry from the recorded states; :func:`step_context`)."""
    rot = quat_to_matrix(ch.quat)
    ends = endpoint_kinematics(topology, ch.pos, ch.quat, ch.vel, ch.angvel, rot=rot)
    return step_context(topology, ch, rot, ends, spring_geometry(ends), params)
