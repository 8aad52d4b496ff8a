"""The weak form of the equations, for noisy data.

On noisy data a forward difference amplifies velocity noise by ``1/dt`` and correlates it with the
regressors (``v[t]`` appears in both).  The *weak form* (test-function or integral form, as in
weak SINDy) sums every equation over a window with a smooth bump ``phi``: because the equations
are linear in the parameters, ``sum_t phi_t A_t theta = 0`` is still exact on clean data, while
``sum_t phi_t (v[t+1] - v[t]) / dt = -sum_t (phi_t - phi_{t-1}) v[t] / dt`` turns the
differentiated noise into a small boundary term, uncorrelated with the (symmetrically weighted)
regressors.  Pushes, which switch on and off, are summed exactly like the accelerations they
cause.

The accelerations themselves come from :mod:`identified.samples`.
"""

from __future__ import annotations

import torch

__all__ = ["default_window", "weak_form", "weak_rows", "weak_stride"]


def default_window(dt: float) -> int:
    """Weak-form window (odd number of samples) spanning about 0.3 s.

    Longer windows damp the differentiated velocity noise (as ``window**-1.5``) and lose only
    information above ``~1/window`` in frequency; the equations stay exact whatever the window.
    """
    n = max(7, round(0.3 / dt))
    return n + 1 - n % 2


def weak_stride(window: int) -> int:
    """Steps between the starts of consecutive weak-form windows of ``window`` steps (a quarter
    window; 1 for ``window`` <= 1: the rows as they are)."""
    return max(1, int(window) // 4) if window > 1 else 1


def weak_rows(steps: int, window: int) -> int:
    """The rows :func:`weak_form` makes of an episode of ``steps`` steps: its windows (``window`` >
    1, windows starting every :func:`weak_stride`), else its steps."""
    return (int(steps) - int(window)) // weak_stride(window) + 1 if window > 1 else int(steps)


def weak_form(A: torch.Tensor, n_episodes: int, window: int, stride: int | None = None) -> torch.Tensor:
    """Sum equation rows ``A`` (N = n_episodes x T, ...) over windows with a Hann bump.

    Windows never cross an episode boundary.  Returns (n_episodes x n_windows, ...).
    """
    N = A.shape[0]
    T = N // n_episodes
    if T < window:
        raise ValueError(f"episodes of {T} steps are shorter than the weak-form window ({window} steps)")
    stride = stride or weak_stride(window)
    phi = torch.hann_window(window + 2, periodic=False, dtype=A.dtype, device=A.device)[1:-1]
    phi = phi / phi.sum()
    W = (T - window) // stride + 1
    # the windows start every `stride` samples: cut each episode into blocks of `stride` samples,
    # and a window is the sum over the `nb` blocks it spans of each block against its piece of the
    # bump -- one matrix-vector product per piece, over the rows as they lie (no transposed copy)
    nb = -(-window // stride)
    bump = torch.zeros(nb * stride, dtype=A.dtype, device=A.device)
    bump[:window] = phi
    x = A.reshape(n_episodes, T, -1)
    need = (W - 1 + nb) * stride
    if need > T:  # the last window's block runs past the episode: zeros where the bump is zero
        x = torch.cat([x, x.new_zeros(n_episodes, need - T, x.shape[-1])], 1)
    blocks = x[:, :need].reshape(n_episodes, W - 1 + nb, stride, -1)
    y = torch.matmul(bump[:stride], blocks[:, :W])
    for j in range(1, nb):
        y = y + torch.matmul(bump[j * stride:(j + 1) * stride], blocks[:, j:j + W])
    return y.reshape(n_episodes * W, *A.shape[1:])
