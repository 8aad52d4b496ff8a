"""Samples of the equations of motion from a recorded dataset: the state at each instant with the
accelerations over its step.

The equations of :mod:`identified.fit.features` use the accelerations of step ``t`` exactly as a
semi-implicit Euler step produces them (MuJoCo's default integrator):
``a = (v[t+1] - v[t]) / dt`` and ``a_b = (R[t+1]^T w[t+1] - R[t]^T w[t]) / dt``, evaluated at the
state of instant ``t`` (the ``"forward"`` scheme).  On clean data of such a plant this recovers the parameters to machine
precision.

A plant on another integrator (RK4) does not step like that; for it the ``"central"``
scheme uses ``a = (v[t+1] - v[t-1]) / (2 dt)`` at instant ``t`` (and the mean of the pushes of steps
``t-1`` and ``t``, which is what the central difference integrates; their torques, held in the
world as the plant applies them, in the rod frame half way through each step), accurate to ``O(dt^2)``
for any consistent integrator instead of ``O(dt)``.  MuJoCo's implicit integrators update the
velocity exactly as Euler does, from an implicitly solved acceleration, so the ``"forward"``
differences are exact for them too (the equations gain the implicit terms in
:func:`identified.fit.features.equation_rows`).

Every user of recorded accelerations reads them here: the regression (:mod:`identified.fit`),
the residual wrench of a model on data, the diagnosis.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import torch

from identified.dataset import Dataset
from identified.rotation import matrix_apply, matrix_apply_transpose, quat_normalize, quat_to_matrix

__all__ = ["SCHEMES", "Chunk", "iter_chunks", "run_steps"]

SCHEMES = ("forward", "central")


@dataclass
class Chunk:
    """A slab of steps, flattened over (episode, time): ``N`` steps.

    ``pos, quat, vel, angvel``: (N, R, .) the state at instant t (world-frame angular velocity);
    ``angvel_body``: (N, R, 3) the same in the rod frame; ``acc``: (N, R, 3) linear acceleration
    and ``alpha_body``: (N, R, 3) rod-frame angular acceleration over step t (see
    :func:`iter_chunks`); ``rest``: (N, S); ``push_force``: (N, R, 3) world and
    ``push_torque_body``: (N, R, 3) its torque about the COM in the rod frame (both per unit ``h``).
    """

    pos: torch.Tensor
    quat: torch.Tensor
    vel: torch.Tensor
    angvel: torch.Tensor
    angvel_body: torch.Tensor
    acc: torch.Tensor
    alpha_body: torch.Tensor
    rest: torch.Tensor
    push_force: torch.Tensor
    push_torque_body: torch.Tensor
    row_weight: torch.Tensor | None = None  # (N, R): 0 drops a rod's equations at an instant
    ctrl: torch.Tensor | None = None  # (N, U): the dataset's ``ctrl`` of step t (None: no actuators)


def run_steps(data: Dataset, chunk_steps: int = 4096, scheme: str = "forward") -> list[int]:
    """The steps of each independent run that :func:`iter_chunks` yields, in order: an episode, or
    each slab of ``chunk_steps`` of an episode longer than that (its chunks are cut there)."""
    E = data.n_episodes
    return [ts.stop - ts.start for ep, ts in _spans(E, data.n_steps, chunk_steps, scheme)
            for _ in range(*ep.indices(E))]


def _spans(E: int, T: int, chunk_steps: int, scheme: str, min_steps: int = 1) -> list[tuple[slice, slice]]:
    """The (episodes, steps) of each of :func:`iter_chunks`' slabs: several whole episodes of at
    most ``chunk_steps`` steps in all, or ``chunk_steps`` of one episode longer than that; the last
    piece of such an episode, where it is shorter than ``min_steps``, joins the piece before it."""
    first = 1 if scheme == "central" else 0  # the central difference needs instant t - 1
    n = T - first
    per = max(1, chunk_steps // max(n, 1))
    if per > 1 or n <= chunk_steps:
        return [(slice(e, min(e + per, E)), slice(first, T)) for e in range(0, E, per)]
    cuts = list(range(first, T, chunk_steps)) + [T]
    if len(cuts) > 2 and cuts[-1] - cuts[-2] < min_steps:
        del cuts[-2]
    return [(slice(e, e + 1), slice(a, b)) for e in range(E) for a, b in pairwise(cuts)]


def iter_chunks(
    data: Dataset,
    chunk_steps: int = 4096,
    scheme: str = "forward",
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
    min_steps: int = 1,
) -> Iterator[tuple[Chunk, int]]:
    """Slabs of at most ``chunk_steps`` steps, each a block of (episodes x consecutive steps).

    Yields ``(chunk, n_episodes)``: the chunk flattened over (episode, time) and how many
    episodes it holds (for :func:`identified.fit.derivatives.weak_form`).  An episode longer than
    ``chunk_steps`` is cut into pieces of ``chunk_steps``; a last piece shorter than ``min_steps``
    (the weak form's window: it would hold none) joins the one before it, a slab of fewer than
    ``chunk_steps + min_steps`` steps.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {', '.join(SCHEMES)}, got '{scheme}'")
    E, T = data.n_episodes, data.n_steps
    if T - (1 if scheme == "central" else 0) < 1:
        raise ValueError("the central scheme needs at least 2 steps per episode")
    spans = _spans(E, T, chunk_steps, scheme, min_steps)

    def cut(arr: np.ndarray, ep: slice, ts: slice, shift: int = 0) -> torch.Tensor:
        x = arr[ep, ts.start + shift : ts.stop + shift]
        return torch.as_tensor(x.reshape(-1, *x.shape[2:]), dtype=dtype, device=device)

    def body(ep: slice, ts: slice, shift: int) -> torch.Tensor:
        return matrix_apply_transpose(quat_to_matrix(cut(data.quat, ep, ts, shift)), cut(data.angvel, ep, ts, shift))

    def push_torque(ep: slice, ts: slice, shift: int) -> torch.Tensor:
        """WORLD torque of the push of step t + shift about the COM, held over the step as the
        plant applies it: (R r) x f with the rotation at the step's start."""
        rot = quat_to_matrix(cut(data.quat, ep, ts, shift))
        return torch.cross(matrix_apply(rot, cut(data.push_point, ep, ts, shift)), cut(data.push_force, ep, ts, shift), dim=-1)

    def mid_rotation(ep: slice, ts: slice, shift: int) -> torch.Tensor:
        """The rotation half way through step t + shift (normalised mean of its end quaternions)."""
        q0, q1 = cut(data.quat, ep, ts, shift), cut(data.quat, ep, ts, shift + 1)
        q1 = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -q1, q1)
        return quat_to_matrix(quat_normalize(q0 + q1))

    has_ctrl = data.ctrl.ndim == 3 and data.ctrl.shape[0] == E and data.ctrl.shape[2] > 0
    for ep, ts in spans:
        quat, angvel, vel = cut(data.quat, ep, ts), cut(data.angvel, ep, ts), cut(data.vel, ep, ts)
        rot = quat_to_matrix(quat)
        w_body = matrix_apply_transpose(rot, angvel)
        if scheme == "central":
            # the pushes of steps t-1 and t, each in the rod frame half way through its step
            torque = 0.5 * (matrix_apply_transpose(mid_rotation(ep, ts, -1), push_torque(ep, ts, -1))
                            + matrix_apply_transpose(mid_rotation(ep, ts, 0), push_torque(ep, ts, 0)))
            chunk = Chunk(
                pos=cut(data.pos, ep, ts), quat=quat, vel=vel, angvel=angvel, angvel_body=w_body,
                acc=(cut(data.vel, ep, ts, 1) - cut(data.vel, ep, ts, -1)) / (2 * data.dt),
                alpha_body=(body(ep, ts, 1) - body(ep, ts, -1)) / (2 * data.dt),
                rest=cut(data.rest_length, ep, ts),
                push_force=0.5 * (cut(data.push_force, ep, ts, -1) + cut(data.push_force, ep, ts)),
                push_torque_body=torque,
                # a push switching at instant t is a jump in the rod's acceleration, across which
                # the central difference is only first order: those equations are left out
                row_weight=(cut(data.push_force, ep, ts, -1) == cut(data.push_force, ep, ts)).all(-1).to(dtype)
                * (cut(data.weight, ep, ts) if data.has_weight else 1.0),
                ctrl=0.5 * (cut(data.ctrl, ep, ts, -1) + cut(data.ctrl, ep, ts)) if has_ctrl else None,
            )
            yield chunk, len(range(*ep.indices(E)))
            continue
        w_next = body(ep, ts, 1)
        chunk = Chunk(
            pos=cut(data.pos, ep, ts),
            quat=quat,
            vel=vel,
            angvel=angvel,
            angvel_body=w_body,
            acc=(cut(data.vel, ep, ts, 1) - vel) / data.dt,
            alpha_body=(w_next - w_body) / data.dt,
            rest=cut(data.rest_length, ep, ts),
            push_force=cut(data.push_force, ep, ts),
            push_torque_body=matrix_apply_transpose(rot, push_torque(ep, ts, 0)),
            ctrl=cut(data.ctrl, ep, ts) if has_ctrl else None,
            row_weight=cut(data.weight, ep, ts) if data.has_weight else None,
        )
        yield chunk, len(range(*ep.indices(E)))
