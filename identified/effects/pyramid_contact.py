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

Solved per rod by Newton's method on (2) (a 6x6 system per iteration, a line search), in the rod's
contact frame and in component form (:meth:`PyramidContact._law`: every rod and instant elementwise,
the constant entries of the contact rows dropped, a rod's two contacts and twenty edges stacked on
short leading axes so that one operation serves all of them), which the twin's compiled step fuses;
the engine's tensor form and the fit run the same function.  Two contacts on one rod are solved together.
With :attr:`PyramidContact.smoothing` > 0 the same problem is solved with each contact's weight and
each edge's ``max(0, ·)`` smoothed over a width (a smooth wrench, for a marker fit's Jacobians).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from identified.effects.base import ParamBlock
from identified.effects.ground_contact import CapsuleOnPlane, cluster_covariance, shadow_frame
from identified.engine.accelerations import inertia_matrix
from identified.engine.smallmat import Mat, Vec, mat, mtv, mv, unvec, vadd, vcross, vdot, vec, vsub

__all__ = ["PyramidContact"]

#: Newton iterations of the per-rod problem (2) and the line search's step sizes. Measured on the
#: 6,184 rod-contacts of a 20 s plant collection (float64, against 30 iterations): 6 reach rounding
#: (8.7e-15 of the force at worst), 5 leave 6e-4 on one contact in 3,000; fewer step sizes need more
NEWTON_ITERATIONS = 6
#: the same for the smoothed law (``PyramidContact.smoothing``), whose edges bend over a width:
#: measured on the same run against 40 iterations, 6 leave 1.2e-3 of the force at 1 mm of width, 10
#: leave 2e-11, 12 and more rounding (1e-17), at widths of 1e-5 to 1e-3 m
SMOOTHED_ITERATIONS = 12
STEPS = (1.0, 0.5, 0.25, 0.1, 0.03)
#: where the fit starts (the law's order of magnitude for a hard floor), then its transforms:
#: logarithms of the positive parameters, logits of the impedances
START = {"beta": 50.0, "kappa": 2000.0, "imp_min": 0.8, "imp_max": 0.9, "imp_width": 2e-3, "mu": 0.5,
         "mu_torsion": 0.01, "mu_rolling": 0.001}
NAMES = tuple(START)
#: the relative step of the fit's forward-difference Jacobian (in the transformed parameters)
DIFF_STEP = 1e-5
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


def smoothstep(x: torch.Tensor) -> torch.Tensor:
    """``3x² - 2x³`` on [0, 1], 0 below and 1 above: a step with a continuous slope."""
    x = x.clamp(0.0, 1.0)
    return x * x * (3 - 2 * x)


def soft_positive(v: torch.Tensor, width: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``h(v) = w log(1 + exp(v / w))``, a smooth ``max(0, v)`` over ``width`` ``w``, and its first and
    second derivatives."""
    z = v / width
    s = torch.sigmoid(z)
    return width * torch.logaddexp(z, torch.zeros_like(z)), s, s * (1 - s) / width


def _trail(x: torch.Tensor, k: int) -> torch.Tensor:
    """A parameter, a scalar or one per env (N,), with ``k`` trailing axes to broadcast over the
    rods' axis and those after it."""
    return x if x.dim() == 0 else x.reshape(x.shape + (1,) * k)


# ---------------------------------------------------------------------- sparse component algebra
# The contact's rows in the rod's contact frame are mostly the constants 0 and 1: entries are
# tensors or Python floats, and these helpers drop the products and sums with 0 and 1, so that the
# problem's algebra is written once, generally, and costs only its non-trivial terms.
Entry = Any  # a tensor (..., R) or a float


def _mul(a: Entry, b: Entry) -> Entry:
    if isinstance(a, float):
        return 0.0 if a == 0.0 else (b if a == 1.0 else (-b if a == -1.0 else a * b))
    if isinstance(b, float):
        return 0.0 if b == 0.0 else (a if b == 1.0 else (-a if b == -1.0 else a * b))
    return a * b


def _sum(*terms: Entry) -> Entry:
    out: Entry = 0.0
    for t in terms:
        if isinstance(t, float) and t == 0.0:
            continue
        out = t if isinstance(out, float) and out == 0.0 else out + t
    return out


def _dot(a: list, b: list) -> Entry:
    return _sum(*(_mul(x, y) for x, y in zip(a, b)))


def _matvec(M: list, x: list) -> list:
    return [_dot(row, x) for row in M]


def _lead(t: torch.Tensor) -> torch.Tensor:
    """The sum over a short leading axis as a chain of additions (elementwise: a compiled step
    fuses it with the work around it, where a reduction is a loop of its own)."""
    out = t[0]
    for k in range(1, t.shape[0]):
        out = out + t[k]
    return out


def _dense_algebra() -> bool:
    """Whether :meth:`PyramidContact._law` forms its 6x6 Hessian and solves it as (..., 6, 6)
    tensors (batched products and LAPACK: few operations, fast eagerly) or in components (elementwise,
    what a compiled step fuses): the latter inside ``torch.compile``."""
    return not torch.compiler.is_compiling()


def _dense(rows: list, shape: torch.Size, like: torch.Tensor) -> torch.Tensor:
    """A matrix given as rows of entries (tensors broadcastable to ``shape``, or floats) as one
    tensor (*shape, n, m)."""
    full = lambda e: (e if isinstance(e, torch.Tensor) else torch.tensor(e, dtype=like.dtype,
                                                                          device=like.device)).expand(shape)
    return torch.stack([torch.stack([full(e) for e in row], -1) for row in rows], -2)


def _spd_solve(H: list, b: list) -> list:
    """``H⁻¹ b`` for a symmetric positive definite ``H`` given as a list of rows of entries (its
    lower triangle is read), ``b`` a list: Cholesky written out over the (small) size, elementwise
    over the batch, so that a compiled step fuses it."""
    n = len(b)
    L: list[list[Entry]] = [[0.0] * n for _ in range(n)]
    inv: list[Entry] = [0.0] * n
    for j in range(n):
        d = _sum(H[j][j], *(-(L[j][k] * L[j][k]) for k in range(j)))
        L[j][j] = torch.sqrt(d)
        inv[j] = 1.0 / L[j][j]
        for i in range(j + 1, n):
            L[i][j] = _mul(_sum(H[i][j], *(-_mul(L[i][k], L[j][k]) for k in range(j))), inv[j])
    y: list[Entry] = []
    for i in range(n):  # L y = b
        y.append(_mul(_sum(b[i], *(-_mul(L[i][k], y[k]) for k in range(i))), inv[i]))
    x: list[Entry] = [0.0] * n
    for i in reversed(range(n)):  # Lᵀ x = y
        x[i] = _mul(_sum(y[i], *(-_mul(L[k][i], x[k]) for k in range(i + 1, n))), inv[i])
    return x


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
    component_form = True
    #: tried by ``--effects auto`` on full rod states (on a 30 s robot collection it is the law the
    #: search adds, in place of ``ground_contact``); not on states reconstructed from markers, where
    #: its fit from the splines' accelerations is not measured
    searched = True
    searched_on_markers = False
    warm_starts = True  # the Gauss-Newton fit starts from the values it holds
    fit_cost = 10.0
    #: the law smoothed over this depth (m; 0: the exact law). Each contact turns on over
    #: ``[-ε/2, ε/2]`` of depth (:func:`smoothstep` of its weight) instead of at 0, and each edge's
    #: ``max(0, ·)`` in (2) is :func:`soft_positive` over ``κ ε`` (the spring's acceleration across the
    #: width): the wrench is then a smooth function of the state.  The exact law's wrench jumps
    #: where a contact makes or breaks and kinks where a friction edge switches, so the markers of a
    #: window are piecewise smooth in its initial state, with kinks microns apart (measured, 30 Hz
    #: windows of a robot on its ground); :meth:`identified.fit.output_error._Problem.with_smoothing`
    #: gives a marker fit's windows through it (``benchmarks/bench_state_steps.py``)
    smoothing = 0.0
    #: Newton iterations of the smoothed law (``None``: :data:`SMOOTHED_ITERATIONS`, its solve to
    #: rounding); for Jacobians :data:`NEWTON_ITERATIONS` do (1e-3 of the force at 1 mm)
    smoothed_iterations: int | None = None

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

    def wrench(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """The law's force and WORLD torque about each rod's frame origin, (..., R, 3): the
        component form (:meth:`wrench_components`) on the tensors' components."""
        return self._wrench(state, ctx, self.theta(state.pos))

    def _wrench(self, state: Any, ctx: Any, th: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        p = ctx.params
        opt = lambda x: None if x is None else vec(x)
        force, torque = self._law(th, vec(state.pos), vec(state.vel), vec(state.angvel), mat(ctx.rot),
                                  vec(ctx.base_lin_acc), vec(ctx.base_ang_acc_body), p.mass, vec(p.inertia),
                                  opt(getattr(p, "com", None)), opt(getattr(p, "inertia_products", None)))
        return unvec(force), unvec(torque)

    def wrench_components(self, pos: Vec, vel: Vec, angvel: Vec, rot: Mat, base_lin_acc: Vec,
                          base_ang_acc_body: Vec, mass: torch.Tensor, inertia: Vec, com: Vec | None = None,
                          products: Vec | None = None) -> tuple[Vec, Vec]:
        """The law's force and WORLD torque about each rod's frame origin in component form (every
        argument's components (..., R)), for the engine's fused step; :meth:`wrench` is the same."""
        return self._law(self.theta(pos[0]), pos, vel, angvel, rot, base_lin_acc, base_ang_acc_body, mass,
                         inertia, com, products)

    def _stacked(self, like: torch.Tensor, rods: torch.Tensor | None) -> tuple[torch.Tensor, tuple]:
        """The capsules' radii and their two segment ends' rod-frame components stacked on a leading
        axis of the two end spheres, (2, R) each (or (2, K) for the rod-instants ``rods``)."""
        key = ("ends", like.dtype, like.device)
        if key not in self._cache:
            radius, seg, _, _, _ = self._geom_components(like)
            self._cache[key] = (radius, tuple(torch.stack((seg[0][k], seg[1][k])) for k in range(3)))
        radius, ends = self._cache[key]
        if rods is not None:
            radius, ends = radius[rods], tuple(c[:, rods] for c in ends)
        return radius, ends

    def _steps(self, like: torch.Tensor) -> torch.Tensor:
        """The line search's step sizes, 0 and :data:`STEPS`, as a tensor (6,)."""
        key = ("steps", like.dtype, like.device)
        if key not in self._cache:
            self._cache[key] = torch.tensor((0.0, *STEPS), dtype=like.dtype, device=like.device)
        return self._cache[key]

    def _law(self, th: torch.Tensor, pos: Vec, vel: Vec, angvel: Vec, rot: Mat, base_lin_acc: Vec,
             base_ang_acc_body: Vec, mass: torch.Tensor, inertia: Vec, com: Vec | None,
             products: Vec | None, rods: torch.Tensor | None = None) -> tuple[Vec, Vec]:
        """Problem (2) per rod, written in the rod's contact frame ``U = (n, t1, t2)``: the
        unknown ``x`` is the contact's change of the rod's acceleration at its centre of mass,
        linear and angular, in ``U``'s components, so that the frame rows of a contact at ``ρ`` (from
        the centre of mass, in ``U``) are the unit vectors and ``ρ``'s components (``B`` below), and
        the mass matrix is ``diag(M, M, M, U J Uᵀ)``.  Newton's method from ``x = 0`` with the
        Hessian ``𝕄 + Σ Bᵀ W B`` (``W`` the arrowhead of a contact's active edges) and a line
        search over :data:`STEPS` on the exact cost.  ``rods`` (K,): every argument's components
        are (K,), row k one instant of rod ``rods[k]`` (the fit's rod-instants in contact).

        Layout: a rod's quantities are (*b) tensors (``b`` the components' shape); a contact's are
        stacked on a leading axis of the rod's two end spheres, (2, *b), and an edge's on two more,
        the sign of its friction term and the five friction directions, (2, 5, 2, *b), so that each
        line of the algebra below is one operation for all twenty edges of a rod."""
        th = th if th.dim() == 1 else th.squeeze(-2)  # (P,) or per env (N, 1, P) -> (N, P)
        beta, kappa, d0, dw, width, mu, mu_t, mu_r = (_trail(th[..., k], 1) for k in range(8))
        nb = pos[0].dim()
        ones = (1,) * nb
        # the five friction coefficients with the edges' signs, (2, 5, 1, ...) against (2, 5, 2, *b)
        mk = torch.stack(torch.broadcast_tensors(mu, mu, mu_t, mu_r, mu_r))
        mk = mk.reshape((5, 1) + (mk.shape[1:] if mk.dim() > 1 else ones))
        sm = torch.stack((mk, -mk))
        _, _, n, t1, height = self._geom_components(pos[0])
        radius, ends = self._stacked(pos[0], rods)
        ends = tuple(c.reshape((2,) + (1,) * (nb + 1 - c.dim()) + c.shape[1:]) for c in ends)  # (2, 1.., R)
        # the contact frame: n, the rod's shadow on the ground (t1 when it stands upright), across
        U = shadow_frame(rot, n, t1)
        P = [mtv(rot, u) for u in U]  # the frame's axes in the rod's frame
        # the mass matrix in U: M on the linear block, U J Uᵀ on the angular one
        Jb = None if products is None else inertia_matrix(inertia, products)
        JP = [tuple(i * x for i, x in zip(inertia, p)) if Jb is None else mv(Jb, p) for p in P]
        Jf = [[vdot(P[i], JP[j]) for j in range(3)] for i in range(3)]
        Mf: list[list[Entry]] = [[mass if i == j else 0.0 for j in range(3)] + [0.0] * 3 for i in range(3)]
        Mf += [[0.0] * 3 + Jf[i] for i in range(3)]
        # the acceleration under every other force at the centre of mass, in U
        w_b = mtv(rot, angvel)
        com_w = None if com is None else mv(rot, com)
        a0 = base_lin_acc if com is None else vadd(
            base_lin_acc, mv(rot, vadd(vcross(base_ang_acc_body, com), vcross(w_b, vcross(w_b, com)))))
        a0f = [_dot(list(a0), list(u)) for u in U] + [vdot(base_ang_acc_body, p) for p in P]
        spin = [vdot(angvel, u) for u in U]
        mu2 = mu * mu
        mass_over_r = mass / (2 * mu2 * (1 + mu2))  # the regulariser R = 2 μ² (1 + μ²) (1 - d) / (d M), inverted
        # the two contacts (end spheres), (2, *b): depth, the lever to the surface point, its rows B
        lever = mv(rot, ends)  # frame origin -> end-sphere centre
        depth = radius - (_dot(list(vadd(pos, lever)), list(n)) - height)
        lever = tuple(_sum(x, -_mul(c, radius - depth / 2)) for x, c in zip(lever, n))  # -> the surface point
        rho = lever if com_w is None else vsub(lever, com_w)
        rn, ra, rp = (_dot(list(rho), list(u)) for u in U)
        B = [[1.0, 0.0, 0.0, 0.0, rp, -ra], [0.0, 1.0, 0.0, -rp, 0.0, rn], [0.0, 0.0, 1.0, ra, -rn, 0.0],
             [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]
        # the reference accelerations (1) of the six rows, less the rows at a0: the row values at x = 0
        v_p = vadd(vel, vcross(angvel, lever))
        rate = [_dot(list(v_p), list(u)) for u in U] + spin
        imp = impedance(depth.clamp_min(0.0), d0, dw, width)
        g = [-beta * r - _dot(b, a0f) for r, b in zip(rate, B)]
        g[0] = g[0] + kappa * imp * depth
        eps = float(self.smoothing)
        if eps > 0:  # the contact turns on over [-ε/2, ε/2]; the edges' max(0, ·) over κ ε
            D = imp * mass_over_r / (1 - imp) * smoothstep(depth / eps + 0.5)
            soft = kappa * eps
        else:
            D = torch.where(depth > 0, imp * mass_over_r / (1 - imp), torch.zeros_like(depth))
        both = lambda e: e[0] + e[1] if isinstance(e, torch.Tensor) else 2 * e
        edge = lambda r: r[0] + sm * torch.stack(torch.broadcast_tensors(*r[1:], r[0])[:-1])
        s_col = self._steps(pos[0]).reshape((6, 1, 1, 1) + ones)

        dense = _dense_algebra()
        if dense:  # the contact rows and the mass matrix as (..., 6, 6) tensors
            Bd, Md = _dense(B, D.shape, D), _dense(Mf, D.shape[1:], D)
        x: list[Entry] = [0.0] * 6
        iterations = NEWTON_ITERATIONS if eps == 0 else (self.smoothed_iterations or SMOOTHED_ITERATIONS)
        for _ in range(iterations):
            Mx = _matvec(Mf, x)
            v = edge([_sum(gj, -_dot(b, x)) for gj, b in zip(g, B)])  # the edges' values (2, 5, 2, *b)
            if eps > 0:  # the smoothed edges: force D h h', weight (curvature) D (h'² + h h'')
                h, h1, h2 = soft_positive(v, soft)
                f, w = D * h * h1, D * (h1 * h1 + h * h2)
            else:
                w = D * (v > 0).to(D.dtype)  # the active edges' weights
                f = w * v  # and forces
            g6 = [_lead(f[0] + f[1]), *(mk * (f[0] - f[1])).unbind(0)]
            grad = [_sum(mx, -both(_sum(*(_mul(b[i], y) for b, y in zip(B, g6))))) for i, mx in enumerate(Mx)]
            w_both = w[0] + w[1]
            w0, w0k, wkk = _lead(w_both), (mk * (w[0] - w[1])).unbind(0), (mk * mk * w_both).unbind(0)
            if dense:  # H = 𝕄 + Σ Bᵀ W B, W the arrowhead of the active edges, by batched products
                W = torch.diag_embed(torch.stack((w0, *wkk), -1))
                W[..., 0, 1:] = W[..., 1:, 0] = torch.stack(w0k, -1)
                H = Md + (Bd.transpose(-1, -2) @ W @ Bd).sum(0)
                step = list(torch.linalg.solve(H, -torch.stack(torch.broadcast_tensors(*grad), -1)).unbind(-1))
            else:  # the same in components: H = 𝕄 + Σ_p B_p c_pᵀ, c_0 = W_00 B_0 + Σ_k W_0k B_k, c_k = W_0k B_0 + W_kk B_k
                c = [[_sum(_mul(w0, B[0][j]), *(_mul(wk, b[j]) for wk, b in zip(w0k, B[1:]))) for j in range(6)]]
                c += [[_sum(_mul(wk, B[0][j]), _mul(vk, b[j])) for j in range(6)] for wk, vk, b in zip(w0k, wkk, B[1:])]
                H = [[_sum(Mf[i][j], both(_sum(*(_mul(b[i], cp[j]) for b, cp in zip(B, c))))) for j in range(i + 1)]
                     for i in range(6)]
                step = [-s for s in _spd_solve(H, grad)]
            # the line search on the exact cost along the step, c0 + s c1 + s² c2 + the edges' terms,
            # at 0 and each s of STEPS at once (a leading axis of 6), the least kept (the first of equals)
            s6 = s_col[:, 0, 0, 0]
            quad = _sum(0.5 * _dot(x, Mx), _mul(s6, _dot(step, Mx)), _mul(0.5 * s6 * s6, _dot(step, _matvec(Mf, step))))
            short = v - s_col * edge([_dot(b, step) for b in B])  # (6, 2, 5, 2, *b)
            short = soft_positive(short, soft)[0] if eps > 0 else short.clamp_min(0.0)
            sq = short * short
            per_contact = D * _lead((sq[:, 0] + sq[:, 1]).transpose(0, 1))  # (6, 2, *b)
            cost = _sum(quad, 0.5 * (per_contact[:, 0] + per_contact[:, 1]))
            best_s, best_c = torch.zeros_like(cost[0]), cost[0]
            for k, s in enumerate(STEPS, start=1):
                better = cost[k] < best_c
                best_s = torch.where(better, s, best_s)
                best_c = torch.where(better, cost[k], best_c)
            x = [_sum(xi, best_s * si) for xi, si in zip(x, step)]
        # the wrench, M x, back in world components; torque about the frame origin
        fl = [mass * xi for xi in x[:3]]
        tl = [_dot(row, x[3:]) for row in Jf]
        force = tuple(_sum(*(_mul(f, u[k]) for f, u in zip(fl, U))) for k in range(3))
        torque = tuple(_sum(*(_mul(t, u[k]) for t, u in zip(tl, U))) for k in range(3))
        if com_w is not None:
            torque = vadd(torque, vcross(com_w, force))
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

        p = ctx.params
        opt = lambda x, r: None if x is None else vec(x[r])

        def pick(k: torch.Tensor) -> tuple[tuple, torch.Tensor]:
            """The law's arguments for the rod-instants ``k`` alone (each row one rod), and the target."""
            t, r = k[:, 0], k[:, 1]
            args = (vec(state.pos[t, r]), vec(state.vel[t, r]), vec(state.angvel[t, r]), mat(ctx.rot[t, r]),
                    vec(ctx.base_lin_acc[t, r]), vec(ctx.base_ang_acc_body[t, r]), p.mass[r], vec(p.inertia[r]),
                    opt(getattr(p, "com", None), r), opt(getattr(p, "inertia_products", None), r))
            return (args, r), torch.cat((force[t, r], torque[t, r] / scale), -1)

        def model(rows: tuple, th: torch.Tensor) -> torch.Tensor:
            args, r = rows
            f, tq = self._law(th, *args, rods=r)
            return torch.cat((unvec(f), unvec(tq) / scale), -1)

        gen = np.random.default_rng(0)
        sub = idx if len(idx) <= FIT_ROWS else idx[torch.as_tensor(np.sort(gen.choice(len(idx), FIT_ROWS, replace=False)))]
        rows_sub, y = pick(sub)
        dtype = state.pos.dtype

        def natural(x: np.ndarray) -> np.ndarray:
            v = np.exp(x)
            v[2:4] = 1 / (1 + np.exp(-x[2:4]))
            return v

        def residual(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return (model(rows_sub, torch.as_tensor(natural(x), dtype=dtype)) - y).reshape(-1).numpy()

        # the law's arguments repeated for 1 + P parameter vectors at once (the law takes one per env)
        n_th = len(NAMES) + 1
        wide = (tuple(tuple(c.expand(n_th, -1) for c in a) if isinstance(a, tuple) else
                      (a if a is None else a.expand(n_th, -1)) for a in rows_sub[0]), rows_sub[1])

        def jacobian(x: np.ndarray) -> np.ndarray:
            """Forward differences (scipy's steps for ``diff_step``), the law evaluated at ``x`` and its
            P steps in one call."""
            dx = (x + DIFF_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))) - x
            th = torch.as_tensor(np.stack([natural(x + d) for d in np.vstack((np.zeros_like(x), np.diag(dx)))]),
                                 dtype=dtype).unsqueeze(-2)
            with torch.no_grad():
                f = model(wide, th).reshape(n_th, -1).numpy()
            return ((f[1:] - f[0]) / dx[:, None]).T

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
            s = least_squares(residual, x0, jac=jacobian, x_scale=1.0, max_nfev=200)
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
            rows_c, y_c = pick(chunk)
            with torch.no_grad():
                r = model(rows_c, torch.as_tensor(values, dtype=dtype)) - y_c
            sse += float((r * r).sum())
            sst += float((y_c * y_c).sum())
        return {"rows": len(idx), "fit_rows": len(sub), "nfev": int(sol.nfev),
                "explained_variance": float(1 - sse / max(sst, 1e-300)),
                "profile": "Gauss-Newton from fixed starting values (no profile scan)"}
