"""Rod poses from markers: a rigid fit of each rod's visible markers to its sites in the rod frame.

A rod's markers at sites ``o_k`` (rod frame) are seen at ``p_k = c + R o_k + noise``.  With three
or more markers not on one line the fit is the weighted Kabsch solution (Kabsch 1976; Umeyama
1991): ``R`` from the SVD of the weighted cross-covariance, ``c`` the weighted mean residual.
When all of a rod's sites lie on one line (end caps on the rod's axis) a rotation about that line
moves no marker: the rod's *axial spin is not observable* from its markers, and only the line's
direction ``a`` and the position ``c`` are fitted, from ``p_k = c + s_k a`` (``s_k`` the site's
coordinate along the line) by linear least squares.  :class:`RodGeometry` says which case a rod is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identified.topology import Topology

__all__ = ["RodGeometry", "fit_axis", "fit_rigid", "rod_geometries"]

#: sites closer than this (m) to the line through the rod's sites count as on the line
COLLINEAR_TOL = 1e-6


@dataclass(frozen=True)
class RodGeometry:
    """How a rod's marker sites sit in its frame.

    ``sites`` (names), ``offsets`` (n, 3) rod frame; ``collinear``: all on one line, whose
    direction ``axis`` (unit, rod frame) and foot ``origin`` (rod frame, the point of the line
    nearest the frame origin) are given; ``along`` (n,) each site's coordinate on the line.
    """

    name: str
    sites: tuple[str, ...]
    offsets: np.ndarray
    collinear: bool
    axis: np.ndarray
    origin: np.ndarray
    along: np.ndarray

    @property
    def axial_spin_observable(self) -> bool:
        """False when the markers cannot see a rotation about the rod's axis."""
        return not self.collinear


def rod_geometries(topology: Topology, sites: tuple[str, ...] | None = None) -> list[RodGeometry]:
    """Each rod's marker geometry, over the rod's sites that are in ``sites`` (default: all)."""
    out = []
    for r in topology.rods:
        keep = [k for k, s in enumerate(r.sites) if sites is None or s in sites]
        off = np.asarray(r.site_offsets, dtype=float)[keep]
        names = tuple(r.sites[k] for k in keep)
        if len(keep) >= 2:
            mean = off.mean(axis=0)
            _, _sv, vt = np.linalg.svd(off - mean)
            axis = vt[0]
            along = (off - mean) @ axis
            resid = off - mean - along[:, None] * axis
            collinear = bool(np.all(np.linalg.norm(resid, axis=-1) < COLLINEAR_TOL))
            origin = mean - (mean @ axis) * axis
            along = off @ axis
        else:
            axis, origin, along, collinear = np.array([0.0, 0.0, 1.0]), np.zeros(3), np.zeros(len(keep)), True
        out.append(RodGeometry(r.name, names, off, collinear, axis, origin, along))
    return out


def fit_axis(points: np.ndarray, along: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Line through markers: ``points`` (F, n, 3) with NaN for missing, ``along`` (n,) the sites'
    coordinates on the line, ``weights`` (n,).  Returns the world point at coordinate 0 and the unit
    direction, (F, 3) each, NaN where fewer than 2 markers are visible."""
    vis = ~np.isnan(points[..., 0])
    w = np.where(vis, weights[None, :], 0.0)
    P = np.nan_to_num(points)
    sw = w.sum(-1)
    s_mean = (w * along).sum(-1) / np.maximum(sw, 1e-300)
    p_mean = (w[..., None] * P).sum(-2) / np.maximum(sw, 1e-300)[:, None]
    ds = along[None, :] - s_mean[:, None]
    sxx = (w * ds * ds).sum(-1)
    slope = (w[..., None] * ds[..., None] * (P - p_mean[:, None, :])).sum(-2) / np.maximum(sxx, 1e-300)[:, None]
    norm = np.linalg.norm(slope, axis=-1)
    direction = slope / np.maximum(norm, 1e-300)[:, None]
    # p = c + s a with |a| = 1: the point at coordinate 0, using the fitted scale |slope| ~ 1
    point = p_mean - s_mean[:, None] * direction
    bad = (vis.sum(-1) < 2) | (sxx <= 0)
    point[bad] = np.nan
    direction[bad] = np.nan
    return point, direction


def fit_rigid(points: np.ndarray, offsets: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch fit of ``p_k = c + R o_k``: ``points`` (F, n, 3) NaN for missing, ``offsets``
    (n, 3).  Returns ``c`` (F, 3) and ``R`` (F, 3, 3); NaN where the visible markers do not fix a
    rotation (fewer than 3, or on one line)."""
    F, _n = points.shape[:2]
    vis = ~np.isnan(points[..., 0])
    w = np.where(vis, weights[None, :], 0.0)
    P = np.nan_to_num(points)
    sw = np.maximum(w.sum(-1), 1e-300)
    pm = (w[..., None] * P).sum(-2) / sw[:, None]
    om = (w[..., None] * offsets[None]).sum(-2) / sw[:, None]
    H = np.einsum("fk,fki,fkj->fij", w, offsets[None] - om[:, None], P - pm[:, None])
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", Vt, U)))
    D = np.zeros((F, 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("fji,fjk,flk->fil", Vt, D, U)
    c = pm - np.einsum("fij,fj->fi", R, om)
    bad = (vis.sum(-1) < 3) | (S[:, 1] <= 1e-12 * np.maximum(S[:, 0], 1e-300))
    c[bad] = np.nan
    R[bad] = np.nan
    return c, R
