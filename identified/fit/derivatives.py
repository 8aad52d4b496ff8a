"""Accelerations from recorded states, and the weak form of the equations for noisy data.

The equations of :mod:`identified.fit.features` use the accelerations of step ``t`` exactly as a
semi-implicit Euler step produces them (MuJoCo's default integrator):
``a = (v[t+1] - v[t]) / dt`` and ``a_b = (R[t+1]^T w[t+1] - R[t]^T w[t]) / dt``, evaluated at the
state of instant ``t``.  On clean data of such a plant this recovers the parameters to machine
precision.

On noisy data a forward difference amplifies velocity noise by ``1/dt`` and correlates it with the
regressors (``v[t]`` appears in both).  The *weak form* (test-function or integral form, as in
weak SINDy) sums every equation over a window with a smooth bump ``phi``: because the equations
are linear in the parameters, ``sum_t phi_t A_t theta = 0`` is still exact on clean data, while
``sum_t phi_t (v[t+1] - v[t]) / dt = -sum_t (phi_t - phi_{t-1}) v[t] / dt`` turns the
differentiated noise into a small boundary term, uncorrelated with the (symmetrically weighted)
regressors.  Pushes, which switch on and off, are summed exactly like the accelerations they
cause.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from identified.dataset import Dataset
from identified.fit.features import Chunk
from identified.rotation import matrix_apply_transpose, quat_to_matrix

__all__ = ["iter_chunks", "weak_form", "default_window"]


def default_window(dt: float) -> int:
    """Weak-form window (odd number of samples) spanning about 0.3 s.

    Longer windows damp the differentiated velocity noise (as ``window**-1.5``) and lose only
    information above ``~1/window`` in frequency; the equations stay exact whatever the window.
    """
    n = max(7, int(round(0.3 / dt)))
    return n + 1 - n % 2


def weak_form(A: torch.Tensor, n_episodes: int, window: int, stride: int | None = None) -> torch.Tensor:
    """Sum equation rows ``A`` (N = n_episodes x T, ...) over windows with a Hann bump.

    Windows never cross an episode boundary.  Returns (n_episodes x n_windows, ...).
    """
    N = A.shape[0]
    T = N // n_episodes
    if T < window:
        raise ValueError(f"episodes of {T} steps are shorter than the weak-form window ({window} steps)")
    stride = stride or max(1, window // 4)
    phi = torch.hann_window(window + 2, periodic=False, dtype=A.dtype, device=A.device)[1:-1]
    phi = phi / phi.sum()
    x = A.reshape(n_episodes, T, -1).transpose(1, 2).reshape(-1, 1, T)
    y = torch.nn.functional.conv1d(x, phi.view(1, 1, -1), stride=stride)  # (E*F, 1, W)
    W = y.shape[-1]
    return y.reshape(n_episodes, -1, W).transpose(1, 2).reshape(n_episodes * W, *A.shape[1:])


def iter_chunks(
    data: Dataset,
    chunk_steps: int = 4096,
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
) -> Iterator[tuple[Chunk, int]]:
    """Slabs of at most ``chunk_steps`` steps, each a block of (episodes x consecutive steps).

    Yields ``(chunk, n_episodes)``: the chunk flattened over (episode, time) and how many
    episodes it holds (for :func:`weak_form`).
    """
    E, T = data.n_episodes, data.n_steps
    per = max(1, chunk_steps // T)
    if per > 1 or T <= chunk_steps:
        spans = [(slice(e, min(e + per, E)), slice(0, T)) for e in range(0, E, per)]
    else:
        spans = [(slice(e, e + 1), slice(t, min(t + chunk_steps, T))) for e in range(E) for t in range(0, T, chunk_steps)]

    def cut(arr: np.ndarray, ep: slice, ts: slice, shift: int = 0) -> torch.Tensor:
        x = arr[ep, ts.start + shift : ts.stop + shift]
        return torch.as_tensor(x.reshape(-1, *x.shape[2:]), dtype=dtype, device=device)

    for ep, ts in spans:
        quat, angvel, vel = cut(data.quat, ep, ts), cut(data.angvel, ep, ts), cut(data.vel, ep, ts)
        w_body = matrix_apply_transpose(quat_to_matrix(quat), angvel)
        w_next = matrix_apply_transpose(quat_to_matrix(cut(data.quat, ep, ts, 1)), cut(data.angvel, ep, ts, 1))
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
            push_point=cut(data.push_point, ep, ts),
        )
        yield chunk, len(range(*ep.indices(E)))
