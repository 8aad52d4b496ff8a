"""Statistics of the one-step residual: whiteness (Ljung-Box), correlations with the inputs, and
the sum of squares a least-squares fit explains."""

from __future__ import annotations

from typing import Any

import numpy as np

from identified.dataset import Dataset
from identified.jsonsafe import finite_or_none

__all__ = ["ALPHA", "DOFS", "LJUNG_BOX_LAGS", "corr_matrix", "explained_sum_of_squares",
           "input_correlation", "least_squares", "ljung_box", "whiteness"]

#: the six residual components per rod: world force axes, rod-frame torque axes
DOFS = ("fx", "fy", "fz", "tx", "ty", "tz")
ALPHA = 0.01  # Ljung-Box level (Bonferroni over the rod/dof series)
LJUNG_BOX_LAGS = 20


def ljung_box(x: np.ndarray, lags: int) -> tuple[float, int]:
    """Ljung-Box ``Q = n (n + 2) Σ_k ρ_k² / (n - k)`` of the series ``x`` (..., n) over the last axis,
    summed over the leading axes (independent series, e.g. episodes); returns ``(Q, dof)``."""
    x = np.asarray(x, dtype=float)
    x = x.reshape(-1, x.shape[-1])
    n = x.shape[-1]
    lags = int(min(lags, n - 1))
    xc = x - x.mean(-1, keepdims=True)
    den = (xc * xc).sum(-1)
    ok = den > 0
    if lags < 1 or not ok.any():
        return float("nan"), 0
    xc, den = xc[ok], den[ok]
    q = np.zeros(len(xc))
    for k in range(1, lags + 1):
        rho = (xc[:, :-k] * xc[:, k:]).sum(-1) / den
        q += rho * rho / (n - k)
    return float((n * (n + 2) * q).sum()), lags * len(xc)


def whiteness(res: np.ndarray, rod_names: tuple[str, ...]) -> dict[str, Any]:
    """Ljung-Box per rod and dof of the residual ``res`` (E, T, R, 6; NaN rows left out), the
    episodes' Q summed (dof summed); white when no series rejects at :data:`ALPHA` after a
    Bonferroni correction over the series."""
    from scipy.special import (
        chdtrc,  # the chi-square survival function (scipy.stats.chi2.sf), light to import
    )

    _E, _Tn, R, _ = res.shape
    valid = ~np.isnan(res[0, :, 0, 0])
    x = res[:, valid]  # (E, n, R, 6)
    n = x.shape[1]
    lags = int(min(LJUNG_BOX_LAGS, max(1, n // 5)))
    table, pvals = [], []
    for i in range(R):
        row = []
        for k in range(6):
            q, dof = ljung_box(x[:, :, i, k], lags) if n > 2 else (float("nan"), 0)
            pv = float(chdtrc(dof, q)) if dof > 0 and np.isfinite(q) else None
            row.append({"dof": DOFS[k], "Q": finite_or_none(q), "df": dof, "p": pv})
            if pv is not None:
                pvals.append(pv)
        table.append(row)
    m = len(pvals)
    white = bool(m > 0 and min(pvals) > ALPHA / m)
    qd = [c["Q"] / c["df"] for row in table for c in row if c["Q"] is not None and c["df"]]
    return {"test": f"Ljung-Box, {lags} lags, per episode, Q and dof summed over episodes", "lags": lags,
            "white": white, "min_p": min(pvals) if pvals else None,
            "fraction_rejected": (sum(pv < ALPHA for pv in pvals) / m) if m else None,
            "median_Q_per_dof": float(np.median(qd)) if qd else None,
            "per_rod": [{"rod": rod_names[i], "series": row} for i, row in enumerate(table)]}


def input_correlation(res: np.ndarray, times: np.ndarray, data: Dataset) -> dict[str, Any]:
    """Largest |Pearson correlation| of the residual series (per rod and dof) with each input:
    the rest lengths, and the pushes on the same rod."""
    _E, _Tn, R, _ = res.shape
    valid = ~np.isnan(res[0, :, 0, 0])
    t = times[valid]
    y = res[:, valid].reshape(-1, R * 6)
    out: dict[str, Any] = {}
    rest = data.rest_length[:, t].reshape(-1, data.n_tendons)
    out["rest_length"] = _max_corr(y, rest, [f"rest_length[{n}]" for n in data.tendon_names], data.rod_names)
    push = data.push_force[:, t]  # (E, n, R, 3)
    best = None
    for i in range(R):
        c = corr_matrix(y[:, i * 6: (i + 1) * 6], push[:, :, i].reshape(-1, 3))
        if c is None:
            continue
        a, b = np.unravel_index(int(np.nanargmax(np.abs(c))), c.shape)
        if best is None or abs(c[a, b]) > abs(best["corr"]):
            best = {"corr": float(c[a, b]), "rod": data.rod_names[i], "dof": DOFS[a], "input": f"push_force.{'xyz'[b]}"}
    out["push_force"] = best or {"corr": None, "reason": "no pushes on any rod"}
    return out


def corr_matrix(y: np.ndarray, x: np.ndarray) -> np.ndarray | None:
    """Pearson correlations (y columns x x columns); 0 where a column is constant (to rounding);
    ``None`` when no column of ``x`` or of ``y`` varies."""
    varies = lambda a: np.ptp(a, axis=0) > 1e-12 * np.maximum(np.abs(a).max(axis=0), 1e-300)
    xv, yv = varies(x), varies(y)
    if not xv.any() or not yv.any():
        return None
    yc, xc = (y - y.mean(0)) * yv, (x - x.mean(0)) * xv
    sy, sx = np.sqrt((yc * yc).sum(0)), np.sqrt((xc * xc).sum(0))
    with np.errstate(all="ignore"):
        c = (yc.T @ xc) / np.outer(sy, sx)
    c[~np.isfinite(c)] = 0.0
    return c


def _max_corr(y: np.ndarray, x: np.ndarray, names: list[str], rod_names: tuple[str, ...]) -> dict[str, Any]:
    c = corr_matrix(y, x)
    if c is None:
        return {"corr": None, "reason": "the input does not vary"}
    a, b = np.unravel_index(int(np.argmax(np.abs(c))), c.shape)
    return {"corr": float(c[a, b]), "rod": rod_names[a // 6], "dof": DOFS[a % 6], "input": names[b]}


def explained_sum_of_squares(G: np.ndarray, b: np.ndarray) -> float:
    """``b' G⁺ b``: the sum of squares a least-squares fit on the columns behind ``G = X'X``,
    ``b = X'y`` explains (columns equilibrated; directions below 1e-12 of the largest dropped)."""
    return float(b @ least_squares(G, b))


def least_squares(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``G⁺ b``: the least-squares coefficients on the columns behind ``G = X'X``, ``b = X'y``
    (``b`` a vector, or a matrix ``X'Y`` of several right-hand sides; columns equilibrated,
    directions below 1e-12 of the largest dropped: the minimum-norm solution in the equilibrated
    columns; a column that is all zero gets 0)."""
    theta = np.zeros(b.shape)
    d = np.sqrt(np.clip(np.diag(G), 0.0, None))
    live = d > 0
    if not live.any():
        return theta
    dl = d[live].reshape((-1,) + (1,) * (b.ndim - 1))
    Gn = G[np.ix_(live, live)] / np.outer(d[live], d[live])
    w, V = np.linalg.eigh(Gn)
    keep = w > w.max() * 1e-12
    wk = w[keep].reshape((-1,) + (1,) * (b.ndim - 1))
    theta[live] = (V[:, keep] @ ((V[:, keep].T @ (b[live] / dl)) / wk)) / dl
    return theta

