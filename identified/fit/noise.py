"""Errors in variables: the regression rows of the data with fresh sensor noise added.

On noisy data every regressor of :mod:`identified.fit.features` is computed from noisy states, so
least squares is biased (errors in variables: ``E[AᵀA] = A₀ᵀA₀ + C`` with ``C`` the covariance of
the rows' noise; Fuller 1987, *Measurement Error Models*, sec. 2.2).  ``C`` depends on the states
and on every nonlinear feature, but the dataset records the sensor noise (``Dataset.noise``:
std of pos, vel, quat, angvel), so it is measured rather than derived: the rows are computed once
more from the states with *fresh* noise of the recorded size, and ``ΔA = A(x + n') - A(x)`` has,
to first order, the distribution of ``A(x) - A(x₀)`` (Monte-Carlo corrected scores, Novick and
Stefanski 2002, JASA 97: 472).  ``C`` sums over every window of the data, so one copy measures it
well: on 20 x 2000 steps the spread of the fitted parameters over copies is below 1 % of their
standard errors.  More copies come in antithetic pairs ``±n'``, which cancel the odd-order terms
of ``ΔAᵀΔA``.  :mod:`identified.fit.regression` uses ``C`` in its errors-in-variables estimator.

States reconstructed from noisy markers (:mod:`identified.fit.markers`) have noise that the
splines and the rigid fits shape, not the white noise of a state sensor: such a dataset carries its
``replicas``, the same reconstruction from its markers with fresh marker noise added, and those
take the copies' place here.

Quaternion noise is a rotation vector of the recorded std per axis, composed on the left and
renormalised (:mod:`tensegrity_gym.collect` records it that way); for isotropic noise the frame
of composition does not matter.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace

import numpy as np
import torch

from identified.dataset import Dataset
from identified.rotation import quat_exp, quat_multiply

__all__ = ["Rows", "has_noise", "perturbed", "with_noise_replicates"]

#: a function ``(dataset, primary) -> iterable of (rows, n_clusters)``: the regression rows of a
#: dataset in chunks, each chunk made of ``n_clusters`` equal, independent runs (episodes)
Rows = Callable[[Dataset, bool], Iterable[tuple[torch.Tensor, int]]]


def has_noise(data: Dataset) -> bool:
    """Whether the dataset records sensor noise (any std > 0) or carries noisy replicas."""
    return bool(np.any(np.asarray(data.noise) > 0)) or bool(data.replicas)


def perturbed(data: Dataset, draws: dict[str, np.ndarray], sign: float) -> Dataset:
    """``data`` with ``sign`` times the standard-normal ``draws`` scaled by the recorded noise."""
    sp, sv, sq, sw = (float(x) for x in data.noise)
    rot = torch.as_tensor(sign * sq * draws["quat"])
    quat = quat_multiply(quat_exp(rot), torch.as_tensor(data.quat)).numpy()
    return replace(
        data,
        pos=data.pos + sign * sp * draws["pos"],
        vel=data.vel + sign * sv * draws["vel"],
        angvel=data.angvel + sign * sw * draws["angvel"],
        quat=quat / np.linalg.norm(quat, axis=-1, keepdims=True),
    )


def _draws(data: Dataset, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {"pos": rng.standard_normal(data.pos.shape), "vel": rng.standard_normal(data.vel.shape),
            "quat": rng.standard_normal(data.quat.shape[:-1] + (3,)),
            "angvel": rng.standard_normal(data.angvel.shape)}


def with_noise_replicates(
    rows_of: Rows,
    data: Dataset,
    copies: int = 1,
    seed: int = 0,
    block_steps: int = 1 << 16,
) -> Iterator[tuple[torch.Tensor, int, list[torch.Tensor]]]:
    """``(rows, n_clusters, replicates)`` per chunk: the data's rows and, aligned with them, the rows
    of ``copies`` noisy copies (the second of each pair antithetic to the first).  No replicates
    when ``copies`` is 0 or the dataset records no noise.  Works through groups of episodes of
    about ``block_steps`` steps, so that only one group's copies are in memory.
    """
    if copies <= 0 or not has_noise(data):
        for A, n in rows_of(data, True):
            yield A, n, []
        return
    rng = np.random.default_rng([seed, 0x5EED])
    per = max(1, block_steps // max(data.n_steps, 1))
    for e0 in range(0, data.n_episodes, per):
        part = data.select(episodes=slice(e0, min(e0 + per, data.n_episodes)))
        if part.replicas:  # measured again from noisier sensors (states from markers)
            noisy = list(part.replicas[:copies])
        else:
            draws = [_draws(part, rng) for _ in range((copies + 1) // 2)]
            noisy = [perturbed(part, draws[k // 2], 1.0 if k % 2 == 0 else -1.0) for k in range(copies)]
        streams = [iter(rows_of(c, False)) for c in noisy]
        for A, n in rows_of(part, True):
            yield A, n, [next(s)[0] for s in streams]
