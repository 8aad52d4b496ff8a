"""Koopman+Int: the paper's physics-aware Koopman operator followed by the integration module.

Basis (paper, Sec. "Physics and System Topology Aware Identification" and appendix B):
``Φ(X) = [1, r, Δp̂_1, Δp̂_2, Δv̂_1, Δv̂_2, φ_i]`` with ``φ_i = a^{α_i} b^{β_i}`` for every pair of
scalars ``a, b`` among the components of ``r``, ``Δp̂_k``, ``Δv̂_k`` and every ``α_i + β_i ≤ Q``
(``Q = 2``).  Appendix B shows that the linear and angular accelerations of a rod are linear in
exactly these terms (``a`` in the ``Δp̂, Δv̂``, ``α`` in the products ``r_i (Δp̂)_j``, ``r_i (Δv̂)_j``),
so the operator is a linear regression ``[a, α] = Φ(X) W`` to the accelerations, which the
integration module then integrates (Koopman+Int).

* ``aggregate=True``: ``Δp̂_1`` is the sum over the springs on the rod's "+" end, ``Δp̂_2`` over
  its "-" end (the simple system has one spring per end; with uniform parameters the sum is exact),
  and one ``W`` is shared by every rod (uniform icosahedron).
* ``aggregate=False``: one slot per attached spring, one ``W`` per rod (appendix C: "six linear
  regressors for six rods", non-uniform parameters).

The regression is ridge-regularised least squares; the ridge is chosen on the validation set
(one-step acceleration error), never on the test set.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import scipy.linalg
import torch

from identified.baselines.features import EndSlots, acceleration_targets, end_features, integrate
from identified.dataset import Dataset
from identified.engine.forces import SpringGraph
from identified.engine.integration import RodState
from identified.topology import Topology

__all__ = ["KoopmanInt", "monomial_pairs"]

RIDGES = (0.0, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2, 1.0)


def monomial_pairs(n: int, degree: int = 2) -> list[tuple[tuple[int, int], ...]]:
    """The paper's terms ``a^α b^β`` (α + β ≤ Q, degree ≥ 2) over ``n`` scalars, each as a tuple of
    (variable, power), without repeats.  Q = 2 gives every ``z_a²`` and ``z_a z_b``."""
    terms: set[tuple[tuple[int, int], ...]] = set()
    for a in range(n):
        for p in range(2, degree + 1):
            terms.add(((a, p),))
    for a, b in itertools.combinations(range(n), 2):
        for pa in range(1, degree):
            for pb in range(1, degree - pa + 1):
                terms.add(((a, pa), (b, pb)))
    return sorted(terms)


class KoopmanInt:
    """Koopman operator to accelerations, then semi-implicit Euler (``step`` is a step model)."""

    def __init__(self, topology: Topology, dt: float, degree: int = 2, aggregate: bool = True,
                 dtype: torch.dtype = torch.float64) -> None:
        self.topology, self.dt, self.degree, self.aggregate, self.dtype = topology, float(dt), degree, aggregate, dtype
        self.graph = SpringGraph.from_topology(topology, dtype=dtype)
        self.slots = EndSlots.from_topology(topology)
        n = 15 if aggregate else 3 + 6 * self.slots.index.shape[1]
        self.n_scalars = n
        terms = monomial_pairs(n, degree)
        self._pairs_a = torch.tensor([t[0][0] for t in terms])
        self._pow_a = torch.tensor([t[0][1] for t in terms], dtype=dtype)
        self._pairs_b = torch.tensor([t[1][0] if len(t) > 1 else 0 for t in terms])
        self._pow_b = torch.tensor([t[1][1] if len(t) > 1 else 0 for t in terms], dtype=dtype)
        self.n_features = 1 + n + len(terms)
        self.coef_: torch.Tensor | None = None  # (F, 6) shared, or (R, F, 6) per rod
        self.ridge_: list[float] | None = None  # per output (a_x, a_y, a_z, α_x, α_y, α_z)
        self.validation_: dict[float, list[float]] = {}
        self.validation_mse_: list[float] | None = None
        self.fit_seconds_: float | None = None
        self.chunk: int | None = None  # pairs per streamed block (None: ~20M basis numbers)

    # ------------------------------------------------------------------ basis
    def scalars(self, state: RodState, rest: torch.Tensor) -> torch.Tensor:
        """The components of ``r``, ``Δp̂``, ``Δv̂`` per rod: (..., R, n)."""
        r, dp, dv = end_features(self.graph, self.slots, state, rest)
        if self.aggregate:
            plus = self.slots.plus.to(dp.device).unsqueeze(-1).to(dp.dtype)
            valid = self.slots.valid.to(dp.device).unsqueeze(-1).to(dp.dtype)
            minus = valid - plus
            parts = [r, (dp * plus).sum(-2), (dp * minus).sum(-2), (dv * plus).sum(-2), (dv * minus).sum(-2)]
            return torch.cat(parts, dim=-1)
        return torch.cat([r, dp.flatten(-2), dv.flatten(-2)], dim=-1)

    def basis(self, state: RodState, rest: torch.Tensor) -> torch.Tensor:
        """``Φ(X)`` per rod: (..., R, F)."""
        z = self.scalars(state, rest)
        prod = z[..., self._pairs_a] ** self._pow_a * z[..., self._pairs_b] ** self._pow_b
        return torch.cat([torch.ones_like(z[..., :1]), z, prod], dim=-1)

    # ------------------------------------------------------------------ data
    def _pairs(self, data: Dataset, chunk: int | None = None):
        """Yield (Φ (N, R, F), targets (N, R, 6)) over the data's (S_t, S_{t+1}) pairs, in chunks of
        about ``chunk`` pairs (default: a basis block of ~20M numbers, 160 MB, whatever F is)."""
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype)
        if chunk is None:
            chunk = max(256, int(2e7 // (self.topology.n_rods * self.n_features)))
        per = max(1, chunk // max(data.n_steps, 1))
        for e0 in range(0, data.n_episodes, per):
            sl = slice(e0, e0 + per)
            flat = lambda a, k, sl=sl: t(a[sl, k].reshape(-1, *a.shape[2:]))
            s0 = RodState(*(flat(getattr(data, n), slice(0, -1)) for n in ("pos", "quat", "vel", "angvel")))
            s1 = RodState(*(flat(getattr(data, n), slice(1, None)) for n in ("pos", "quat", "vel", "angvel")))
            rest = flat(data.rest_length, slice(None))
            a, alpha = acceleration_targets(s0, s1, data.dt)
            yield self.basis(s0, rest), torch.cat([a, alpha], dim=-1)

    # ------------------------------------------------------------------ fit
    def fit(self, train: Dataset, val: Dataset) -> KoopmanInt:
        """Ridge regression to the accelerations; the ridge picked on ``val`` (one-step error).

        The rows are reduced by a streaming QR of ``[Φ | targets]`` (the basis is nearly collinear,
        ``|r|² = const`` among others, so normal equations would square its condition number and
        lose the exact fit that appendix B promises on the simple system)."""
        t0 = time.perf_counter()
        F = self.n_features
        R = self.topology.n_rods
        groups = 1 if self.aggregate else R
        tri: list[np.ndarray | None] = [None] * groups
        sq = np.zeros((groups, F))
        # rows are buffered per group and folded into the triangular factor once a block of
        # `fold` rows has gathered: memory stays O(fold x F) whatever the data size, and each QR
        # is tall enough (20x its width at least) that carrying the (F + 6)-row factor along costs
        # little (per rod at 1378 features: 6 buffers of 27,700 rows, 1.8 GB)
        fold = max(20 * (F + 6), int(6e7 // ((F + 6) * groups)))
        buf: list[list[np.ndarray]] = [[] for _ in range(groups)]
        nbuf = [0] * groups

        def reduce(g: int) -> None:
            stack = np.vstack(([tri[g]] if tri[g] is not None else []) + buf[g])
            tri[g] = scipy.linalg.qr(stack, mode="r", check_finite=False, overwrite_a=True)[0][: F + 6]
            buf[g], nbuf[g] = [], 0

        for phi, y in self._pairs(train, self.chunk):
            rows = torch.cat([phi, y], dim=-1).numpy()  # (N, R, F + 6)
            del phi, y
            for g in range(groups):
                m = rows.reshape(-1, F + 6) if self.aggregate else np.ascontiguousarray(rows[:, g])
                sq[g] += np.sum(m[:, :F] ** 2, axis=0)
                buf[g].append(m)
                nbuf[g] += m.shape[0]
                if nbuf[g] >= fold:
                    reduce(g)
            del rows
        for g in range(groups):
            if buf[g]:
                reduce(g)
        # each of the six outputs is its own regression: its ridge is chosen on its own
        # validation error (one shared ridge would let a badly extrapolating α spoil an exact a);
        # one streamed pass over the validation data scores every ridge
        svds = [self._svd(tri[g], np.sqrt(sq[g]), F) for g in range(groups)]
        coefs = {}
        for lam in RIDGES:
            coef = np.stack([self._coef(svd, lam) for svd in svds])
            coefs[lam] = torch.as_tensor(coef[0] if self.aggregate else coef)
        err = {lam: np.zeros(6) for lam in RIDGES}
        count = 0
        with np.errstate(over="ignore", invalid="ignore"):
            for phi, y in self._pairs(val, self.chunk):
                for lam, coef in coefs.items():
                    pred = self._apply(coef, phi)
                    err[lam] += ((pred - y) ** 2).reshape(-1, 6).sum(0).numpy()
                count += y.numel() // 6
        best_err = np.full(6, np.inf)
        best_lam = np.zeros(6)
        coef_best = None
        for lam in RIDGES:
            mse = np.where(np.isfinite(err[lam]), err[lam] / max(count, 1), np.inf)
            self.validation_[lam] = mse.tolist()
            better = mse < best_err
            coef = coefs[lam].numpy()
            if coef_best is None:
                coef_best = coef.copy()
            coef_best[..., better] = coef[..., better]
            best_err = np.where(better, mse, best_err)
            best_lam = np.where(better, lam, best_lam)
        self.ridge_ = best_lam.tolist()
        self.coef_ = torch.as_tensor(coef_best, dtype=self.dtype)
        self.validation_mse_ = best_err.tolist()
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    @staticmethod
    def _svd(tri: np.ndarray, d: np.ndarray, F: int) -> tuple[np.ndarray, ...]:
        """SVD of the column-scaled triangular factor ``R_Φ / d`` and the rotated targets ``z``:
        every ridge then costs one product (filter factors ``s / (s² + λ)``)."""
        d = np.where(d > 0, d, 1.0)
        k = min(tri.shape[0], F)
        Rs = tri[:k, :F] / d[None, :]
        z = tri[:k, F:]
        U, sv, Vt = scipy.linalg.svd(Rs, full_matrices=False, check_finite=False, lapack_driver="gesdd")
        return U, sv, Vt, z, d

    @staticmethod
    def _coef(svd: tuple[np.ndarray, ...], lam: float, rcond: float = 1e-12) -> np.ndarray:
        """Ridge (``lam`` on the unit-norm column scale) or, for 0, minimum-norm least squares with
        singular values below ``rcond`` of the largest dropped (the basis is rank deficient, e.g.
        ``|r|² = const``)."""
        U, sv, Vt, z, d = svd
        if lam > 0:
            f = sv / (sv ** 2 + lam)
        else:
            keep = sv > rcond * (sv[0] if sv.size else 0.0)
            f = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
        w = Vt.T @ (f[:, None] * (U.T @ z))
        return w / d[:, None]

    def _apply(self, coef: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        if coef.ndim == 2:
            return phi @ coef
        return torch.einsum("...rf,rfy->...ry", phi, coef)

    # ------------------------------------------------------------------ predict
    def step(self, state: RodState, rest: torch.Tensor, push_force=None, push_point=None) -> RodState:
        """One step: Koopman accelerations, then the integration module.  Pushes are not modelled
        (the operator is derived "in scenarios without external forces", appendix B)."""
        if self.coef_ is None:
            raise RuntimeError("fit the Koopman operator first")
        acc = self._apply(self.coef_, self.basis(state, rest))
        return integrate(state, acc[..., :3], acc[..., 3:], self.dt)
