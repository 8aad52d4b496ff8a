"""``pyramid_contact``: the ground as a soft constraint with a pyramidal friction cone.

Geometry as :mod:`identified.effects.ground_contact` (read from the MJCF, never its physics
parameters): every rod's collision capsule and the ground plane.  Each end sphere of a capsule
touches when it penetrates the plane, depth ``d = r - (n·c - h) > 0``; its contact point lies on
the capsule's surface, half the depth into the plane, ``p = c - (r - d/2) n``, so friction there
also spins the rod about its own axis.  The contact frame is ``n`` and two tangents: ``t1`` along
the rod's shadow on the ground, ``t2 = n × t1``.

Force law (a convex soft contact, Todorov 2014; MuJoCo's own form).  The contact's wrench is
spread over the ten edges of a friction pyramid, ``J_e = J_n ± μ_k J_k`` for the five friction
directions ``k`` -- sliding along ``t1`` and ``t2`` (coefficient ``μ``), spinning about ``n``
(``μ_t``, m) and rolling about ``t1`` and ``t2`` (``μ_r``, m) -- each a one-sided force ``f_e >= 0``
along its edge, so the normal force is shared by all of them and ``|f_k| <= μ_k f_n`` holds by
construction.  Each edge is a unilateral soft constraint with the reference acceleration

    a_ref,e = -β (J_e v) + κ d(d) d,        d(d) = impedance at depth d                (1)

and the regulariser ``R = 2 μ² (1 + μ²) / M · (1 - d(d)) / d(d)`` (one per contact, from the
rod's identified mass ``M``); the forces are those of the convex problem

    min over a:  ½ (a - a0)ᵀ 𝕄 (a - a0) + Σ_e ½ R⁻¹ max(0, a_ref,e - J_e a)²           (2)

(``a`` the rod's linear and angular acceleration, ``𝕄`` its mass matrix from the identified M and
inertia, ``a0`` its acceleration under every other force); the wrench is ``𝕄 (a - a0)``.  The
impedance rises from ``d_0`` at the surface to ``d_w`` at the depth ``w`` along a smooth step
(two parabolas meeting half way).  Parameters: ``β`` (1/s), ``κ`` (1/s²), ``d_0``, ``d_w``,
``w`` (m), ``μ``, ``μ_t`` (m), ``μ_r`` (m).  Non-linear in them: fitted by Gauss-Newton
(``scipy.optimize.least_squares``) on the residual wrench of the rods in contact
(:meth:`PyramidContact.fit_residual`).

Solved per rod by Newton's method on (2) (a 6x6 system per iteration, a backtracking line search),
batched over every rod and instant.  Two contacts on one rod are solved together.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from identified.effects.base import ParamBlock
from identified.effects.ground_contact import CapsuleOnPlane, cluster_covariance
from identified.engine.accelerations import inertia_matrix
from identified.engine.smallmat import unvec, vec

__all__ = ["PyramidContact"]

#: Newton iterations of the per-rod problem (2) and the line search's step sizes
NEWTON_ITERATIONS = 8
STEPS = (1.0, 0.5, 0.25, 0.1, 0.03)
#: where the fit starts (the law's order of magnitude for a hard floor), then its transforms:
#: logarithms of the positive parameters, logits of the impedances
START = {"beta": 50.0, "kappa": 2000.0, "imp_min": 0.8, "imp_max": 0.9, "imp_width": 2e-3, "mu": 0.5,
         "mu_torsion": 0.01, "mu_rolling": 0.001}
NAMES = tuple(START)
#: the impedance widths (m) the fit starts from, the best fit kept
WIDTHS = (3e-4, 2e-3, 1e-2)
#: at most this many rod-instants in contact enter the non-linear fit (a seeded subsample)
FIT_ROWS = 1500


def impedance(depth: torch.Tensor, d0: Any, dw: Any, width: Any) -> torch.Tensor:
    """The impedance at penetration ``depth`` (m): ``d0`` at the surface to ``dw`` at ``width``, a
    smooth step of two parabolas (``2x²`` up to ``x = ½``, ``1 - 2(1-x)²`` after)."""
    x = (depth / width).clamp(0.0, 1.0)
    y = torch.where(x <= 0.5, 2 * x * x, 1 - 2 * (1 - x) ** 2)
    return d0 + y * (dw - d0)


def _trail(x: torch.Tensor, k: int) -> torch.Tensor:
    """A parameter, a scalar or one per env (N,), with ``k`` trailing axes to broadcast over the
    rods' axis and those after it."""
    return x if x.dim() == 0 else x.reshape(x.shape + (1,) * k)


def _spd_solve(H: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``H⁻¹ b`` for symmetric positive definite ``H`` (..., n, n), ``b`` (..., n): Cholesky written
    out over the (small) size, elementwise over the batch, so that a compiled step fuses it."""
    n = H.shape[-1]
    L: list[list[torch.Tensor]] = [[None] * n for _ in range(n)]  # type: ignore[list-item]
    for j in range(n):
        d = H[..., j, j] - sum((L[j][k] * L[j][k] for k in range(j)), torch.zeros_like(H[..., j, j]))
        L[j][j] = torch.sqrt(d)
        inv = 1.0 / L[j][j]
        for i in range(j + 1, n):
            L[i][j] = (H[..., i, j] - sum((L[i][k] * L[j][k] for k in range(j)), torch.zeros_like(d))) * inv
    y: list[torch.Tensor] = []
    for i in range(n):  # L y = b
        y.append((b[..., i] - sum((L[i][k] * y[k] for k in range(i)), torch.zeros_like(b[..., i]))) / L[i][i])
    x: list[torch.Tensor] = [None] * n  # type: ignore[list-item]
    for i in reversed(range(n)):  # Lᵀ x = y
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), torch.zeros_like(y[i]))) / L[i][i]
    return torch.stack(x, -1)


class PyramidContact(CapsuleOnPlane):
    name = "pyramid_contact"
    description = ("rod capsules on a ground plane: a soft unilateral constraint at the capsule's surface "
                   "with a pyramidal friction cone (sliding, torsional and rolling edges)")
    blocks = (
        ParamBlock("beta", "global", mass_scaled=False, unit="1/s"),
        ParamBlock("kappa", "global", mass_scaled=False, unit="1/s^2"),
        ParamBlock("imp_min", "global", mass_scaled=False),
        ParamBlock("imp_max", "global", mass_scaled=False),
        ParamBlock("imp_width", "global", mass_scaled=False, unit="m"),
        ParamBlock("mu", "global", mass_scaled=False),
        ParamBlock("mu_torsion", "global", mass_scaled=False, unit="m"),
        ParamBlock("mu_rolling", "global", mass_scaled=False, unit="m"),
    )
    fit_strategy = "residual"
    needs_base_acceleration = True
    region = "near_ground"
    #: named by the user (``--effects pyramid_contact``), not tried by the effect search: its law has
    #: no component form yet, so its twin steps through the engine's tensor form (tens of times
    #: slower to train on than ``ground_contact``'s compiled step)
    searched = False
    fit_cost = 10.0

    def contact_point(self, state: Any, ctx: Any) -> torch.Tensor:
        """Each rod's contact point, the lever from its frame origin (..., R, 3) world: on the
        capsule's surface below its end sphere in contact (the mean of both when both are; 0 when
        none is).  The diagnosis takes torques about it."""
        points, depth = self._points(state, ctx.rot)
        active = (depth > 0).to(state.pos.dtype)
        lever = points - state.pos.unsqueeze(-2)
        return (active.unsqueeze(-1) * lever).sum(-2) / active.sum(-1).clamp_min(1.0).unsqueeze(-1)

    def _points(self, state: Any, rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        radius, _, n, _, _, _ = self._geom(state.pos)
        centre, depth = self._end_spheres(state, rot)
        return centre - (radius.unsqueeze(-1) - depth / 2).unsqueeze(-1) * n, depth

    def _edges(self, state: Any, ctx: Any, th: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per rod: the edges' Jacobians ``J`` (..., R, 20, 6) in (linear, angular) world
        coordinates (two end spheres x ten edges), their reference accelerations (..., R, 20),
        inverse regularisers ``D`` (..., R, 20; 0 at an end not in contact), the mass matrix
        (..., R, 6, 6) and ``a0`` (..., R, 6)."""
        _, _, n, t1, _, _ = self._geom(state.pos)
        rot = ctx.rot
        points, depth = self._points(state, rot)
        p = ctx.params
        com = getattr(p, "com", None)
        origin_to_com = 0.0 if com is None else (rot @ com.unsqueeze(-1)).squeeze(-1)
        rho = points - (state.pos + origin_to_com).unsqueeze(-2)  # (..., R, 2, 3) from the centre of mass
        axis = rot[..., :, 2]
        along = axis - (axis * n).sum(-1, keepdim=True) * n
        norm = along.norm(dim=-1, keepdim=True)
        along = torch.where(norm > 1e-6, along / norm.clamp_min(1e-12), t1)
        across = torch.linalg.cross(n.expand_as(along), along)
        nn = n.expand_as(along)
        zero = torch.zeros_like(along)
        th = th if th.dim() == 1 else th.squeeze(-2)  # (P,) or per env (N, 1, P) -> (N, P)

        def lin(u: torch.Tensor) -> torch.Tensor:  # (..., R, 3) -> (..., R, 2, 6)
            u2 = u.unsqueeze(-2).expand_as(rho)
            return torch.cat((u2, torch.linalg.cross(rho, u2)), -1)

        def ang(u: torch.Tensor) -> torch.Tensor:
            return torch.cat((zero, u), -1).unsqueeze(-2).expand(rho.shape[:-1] + (6,))

        beta, kappa, d0, dw, width, mu, mu_t, mu_r = (th[..., k] for k in range(8))
        # the contact frame's six rows (force along n, t1, t2; torque about n, t1, t2), (..., R, 2, 6, 6);
        # edge (k, ±) is row 0 ± μ_k row k
        rows = torch.stack((lin(nn), lin(along), lin(across), ang(nn), ang(along), ang(across)), -2)
        mus = torch.stack(torch.broadcast_tensors(mu, mu, mu_t, mu_r, mu_r), -1)  # (5,) or (N, 5)
        mus = mus if mus.dim() == 1 else mus.reshape(mus.shape[:1] + (1, 1, 5))
        vg = torch.cat((state.vel, state.angvel), -1)  # (..., R, 6)
        imp = impedance(depth.clamp_min(0.0), _trail(d0, 2), _trail(dw, 2), _trail(width, 2))  # (..., R, 2)
        # the reference accelerations (1) of the six rows: a_ref,(k,±) = ref_0 ± μ_k ref_k
        ref = -_trail(beta, 3) * (rows @ vg.unsqueeze(-2).unsqueeze(-1)).squeeze(-1)
        ref = torch.cat(((ref[..., 0] + _trail(kappa, 2) * imp * depth).unsqueeze(-1), ref[..., 1:]), -1)
        mass = p.mass
        mu2 = _trail(mu, 2) ** 2
        R = 2 * mu2 * (1 + mu2) / mass.unsqueeze(-1) * (1 - imp) / imp  # (..., R, 2)
        D = torch.where(depth > 0, 1.0 / R, torch.zeros_like(R))
        products = getattr(p, "inertia_products", None)
        if products is None:
            Ib = torch.diag_embed(p.inertia)
        else:
            Ib = unvec(inertia_matrix(vec(p.inertia), vec(products))).unflatten(-1, (3, 3))
        Iw = rot @ Ib @ rot.transpose(-1, -2)
        Mg = torch.zeros(Iw.shape[:-2] + (6, 6), dtype=Iw.dtype, device=Iw.device)
        Mg[..., :3, :3] = torch.eye(3, dtype=Iw.dtype, device=Iw.device) * mass.unsqueeze(-1).unsqueeze(-1)
        Mg[..., 3:, 3:] = Iw
        alpha0 = (rot @ ctx.base_ang_acc_body.unsqueeze(-1)).squeeze(-1)
        a0 = torch.cat((ctx.base_lin_acc, alpha0), -1)
        return {"rows": rows, "ref": ref, "mu": mus, "D": D, "M": Mg, "a0": a0}

    @staticmethod
    def _solve(e: dict[str, torch.Tensor]) -> torch.Tensor:
        """Newton's method on problem (2), batched: the contact's change of the rod's acceleration
        ``a - a0`` (..., R, 6).  Written on each contact's six frame rows (an edge is row 0 ± μ_k
        row k), so the Hessian ``𝕄 + Σ_e D J_eᵀ J_e`` is ``𝕄 + Bᵀ W B`` with ``W`` an arrowhead."""
        B, ref, mu, D, Mg, a0 = e["rows"], e["ref"], e["mu"], e["D"], e["M"], e["a0"]
        Dk = D.unsqueeze(-1)  # (..., R, 2, 1)

        def violations(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            r = ref - (B @ a.unsqueeze(-2).unsqueeze(-1)).squeeze(-1)  # (..., R, 2, 6)
            return r[..., :1] + mu * r[..., 1:], r[..., :1] - mu * r[..., 1:]  # (..., R, 2, 5) each

        def cost(a: torch.Tensor) -> torch.Tensor:
            da = a - a0
            vp, vm = violations(a)
            edges = (Dk * (vp.clamp_min(0.0) ** 2 + vm.clamp_min(0.0) ** 2)).sum((-1, -2))
            return 0.5 * (da * (Mg @ da.unsqueeze(-1)).squeeze(-1)).sum(-1) + 0.5 * edges

        a = a0
        for _ in range(NEWTON_ITERATIONS):
            vp, vm = violations(a)
            wp, wm = Dk * (vp > 0).to(D.dtype), Dk * (vm > 0).to(D.dtype)  # active edges
            fp, fm = wp * vp, wm * vm  # the edges' forces
            g6 = torch.cat(((fp + fm).sum(-1, keepdim=True), mu * (fp - fm)), -1)  # (..., R, 2, 6)
            grad = (Mg @ (a - a0).unsqueeze(-1)).squeeze(-1) - (B.transpose(-1, -2) @ g6.unsqueeze(-1)).squeeze(-1).sum(-2)
            w0 = (wp + wm).sum(-1)  # (..., R, 2)
            w0k = mu * (wp - wm)
            wkk = mu * mu * (wp + wm)
            b0, bk = B[..., 0, :], B[..., 1:, :]  # (..., R, 2, 6), (..., R, 2, 5, 6)
            cross = (w0k.unsqueeze(-1) * bk).sum(-2)  # Σ_k W_0k b_k
            outer = lambda x, y: x.unsqueeze(-1) * y.unsqueeze(-2)
            H6 = (w0.unsqueeze(-1).unsqueeze(-1) * outer(b0, b0) + outer(b0, cross) + outer(cross, b0)
                  + bk.transpose(-1, -2) @ (wkk.unsqueeze(-1) * bk))  # (..., R, 2, 6, 6)
            step = -_spd_solve(Mg + H6.sum(-3), grad)
            best, best_c = a, cost(a)
            for s in STEPS:
                cand = a + s * step
                c = cost(cand)
                better = c < best_c
                best = torch.where(better.unsqueeze(-1), cand, best)
                best_c = torch.where(better, c, best_c)
            a = best
        return a - a0

    def wrench(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """The law's force and WORLD torque about each rod's frame origin, (..., R, 3)."""
        return self._wrench(state, ctx, self.theta(state.pos))

    def _wrench(self, state: Any, ctx: Any, th: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        e = self._edges(state, ctx, th)
        gen = (e["M"] @ self._solve(e).unsqueeze(-1)).squeeze(-1)  # force, torque about the centre of mass
        force, torque = gen[..., :3], gen[..., 3:]
        com = getattr(ctx.params, "com", None)
        if com is not None:  # the engine takes torques about the rod frame's origin
            torque = torque + torch.linalg.cross((ctx.rot @ com.unsqueeze(-1)).squeeze(-1), force)
        return force, torque

    # ------------------------------------------------------------------ fit on the residual
    def fit_residual(self, state: Any, ctx: Any, force: torch.Tensor, torque: torch.Tensor,
                     groups: np.ndarray, rows: torch.Tensor) -> dict[str, Any]:
        """Gauss-Newton of the law on the residual wrench of the contact rows (a seeded subsample
        of at most :data:`FIT_ROWS` rod-instants), from the values it holds (a refit) or else from
        :data:`START` with each width of :data:`WIDTHS` (the best kept); standard errors
        cluster-robust over episodes (``groups``), from the Jacobian at the solution.  Sets
        ``values``/``stderr``; returns ``rows``, ``explained_variance`` (on every contact row)."""
        from scipy.optimize import least_squares

        _, depth = self._end_spheres(state, ctx.rot)
        sel = rows & (depth > 0).any(-1)
        idx = torch.nonzero(sel)  # (K, 2): instant, rod
        if len(idx) < 50:
            raise ValueError("too few contact rows to identify pyramid_contact")
        scale = self.torque_scale

        def pick(k: torch.Tensor) -> tuple[Any, Any, torch.Tensor]:
            t, r = k[:, 0], k[:, 1]
            st = type(state)(*(None if x is None else x[t] for x in state))
            cx = ctx._replace(rot=ctx.rot[t], angvel_body=None if ctx.angvel_body is None else ctx.angvel_body[t],
                              base_lin_acc=ctx.base_lin_acc[t], base_ang_acc_body=ctx.base_ang_acc_body[t])
            y = torch.cat((force[t, r], torque[t, r] / scale), -1)
            return st, cx, y

        def model(st: Any, cx: Any, k: torch.Tensor, th: torch.Tensor) -> torch.Tensor:
            f, tq = self._wrench(st, cx, th)
            r = k[:, 1]
            ar = torch.arange(len(r))
            return torch.cat((f[ar, r], tq[ar, r] / scale), -1)

        gen = np.random.default_rng(0)
        sub = idx if len(idx) <= FIT_ROWS else idx[torch.as_tensor(np.sort(gen.choice(len(idx), FIT_ROWS, replace=False)))]
        st, cx, y = pick(sub)
        dtype = state.pos.dtype

        def natural(x: np.ndarray) -> np.ndarray:
            v = np.exp(x)
            v[2:4] = 1 / (1 + np.exp(-x[2:4]))
            return v

        def residual(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return (model(st, cx, sub, torch.as_tensor(natural(x), dtype=dtype)) - y).reshape(-1).numpy()

        def transformed(v: np.ndarray) -> np.ndarray:
            x = np.log(v)
            x[2:4] = np.log(v[2:4] / (1 - v[2:4]))
            return x

        # a refit starts from the values it has; a first fit from START with each width of WIDTHS
        # (the fit has local minima in the impedance's width)
        starts = ([np.asarray(self.values, dtype=float)] if self.values is not None else
                  [np.array([START[k] if k != "imp_width" else w for k in NAMES]) for w in WIDTHS])
        sol = None
        for start in starts:
            x0 = transformed(start)
            s = least_squares(residual, x0, diff_step=1e-5, x_scale=1.0, max_nfev=200)
            if sol is None or s.cost < sol.cost:
                sol = s
        values = natural(sol.x)
        # the standard errors, natural units (the delta method through the transforms)
        g = np.repeat(groups[sub[:, 0].numpy()], 6)
        cov_x = cluster_covariance(sol.jac, sol.fun, g)
        dv = values.copy()
        dv[2:4] = values[2:4] * (1 - values[2:4])
        self.values = values
        self.stderr = np.sqrt(np.clip(np.diag(cov_x), 0, None)) * np.abs(dv)
        # explained variance on every contact row
        sse, sst = 0.0, 0.0
        for chunk in torch.split(idx, 20000):
            st_c, cx_c, y_c = pick(chunk)
            with torch.no_grad():
                r = model(st_c, cx_c, chunk, torch.as_tensor(values, dtype=dtype)) - y_c
            sse += float((r * r).sum())
            sst += float((y_c * y_c).sum())
        return {"rows": len(idx), "fit_rows": len(sub), "nfev": int(sol.nfev),
                "explained_variance": float(1 - sse / max(sst, 1e-300)),
                "profile": "Gauss-Newton from fixed starting values (no profile scan)"}
