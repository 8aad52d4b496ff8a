"""``cable_friction``: dry friction along each cable that sticks and slips (a box constraint).

A cable running through a guide, a pulley or a geared motor resists changes of its length.  As
MuJoCo's tendon ``frictionloss`` (a soft constraint, like its contacts), the friction is not a
function of the velocity alone: while the cable *sticks* it takes whatever force holds its length
still (up to a small compliance), and it *slips* once that force would exceed a bound.  Written
as the force ``r_j`` that resists lengthening cable ``j`` (pulling both ends together when
positive), with ``L̈_j`` the cable's length acceleration (the ends' accelerations along the cable,
no centripetal term) and ``L̇_j`` its rate:

    r_j = clip(m_j L̈_j + d_j L̇_j, -F_j, F_j)

per cable: the slip force ``F_j`` (N), and while it sticks a virtual mass ``m_j`` (kg) and damper
``d_j`` (N s/m) on its length -- a stiff, stable stand-in for "no motion" (MuJoCo's soft
constraint gives exactly this with ``m = 1/R``, ``d = b/R``: its regulariser ``R`` and reference
damping ``b``).  That the clip of the *actual* acceleration is the whole law is the constraint's
optimality condition: a cable slips (force at ``±F``) exactly when the stick law would ask for
more than ``F`` in the same direction.

Identification (stage ``joint``, linear per iteration): given which cables stick at every
recorded instant, the force is linear in the parameters -- ``F_j sign`` where it slips,
``m_j L̈_j + d_j L̇_j`` where it sticks, with ``L̈`` and ``L̇`` from the recorded states -- so the
columns enter the paper's regression with K, c, M, I.  Which cables stick follows from the
parameters themselves (``|m L̈ + d L̇| < F``), so the fit iterates: the first pass calls a cable
stuck while ``|L̈ + b L̇| < θ``, with ``b`` read off the data (:meth:`CableFriction.starts`: a
sticking cable's rate decays as ``e^{-bt}``, a sharp peak of ``-L̈ / L̇``) and four widths ``θ``
tried on a part of the data; every later pass classifies with the previous pass's parameters,
until they stop moving (:meth:`CableFriction.reclassify`): the fit's classification strategy,
:mod:`identified.fit.classification`, which the class declares (``fit_strategy``).  Cables the data never show sticking
(or slipping) have their stick law (their slip force and stick damping) held, and the fit's
metrics say which.  On clean data of a MuJoCo plant the law is exact, and so are the parameters
(measured: F, m and b to 1e-6 on the paper icosahedron with frictionloss 1-5 N).

Engine (stage ``needs_base_acceleration``): the cable's length acceleration depends on the
friction of every cable (they share rods), so the twin solves the box-constrained problem
``(A + diag(1/m)) r = L̈0 + (d/m) L̇`` on the sticking cables, ``r = ±F`` on the slipping ones,
with ``A = J M⁻¹ Jᵀ`` the cables' inverse effective mass from the identified M and I and ``L̈0``
the length acceleration under every other force, by a fixed number of active-set passes
(:meth:`CableFriction.wrench`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from identified.effects.base import Effect, ParamBlock
from identified.rotation import matrix_apply, matrix_apply_transpose

__all__ = ["CableFriction"]

#: active-set passes of the twin's box solve (each one a batched dense solve over the cables);
#: measured on the paper icosahedron with frictionloss 5: exact (1e-6 N) after 8 in every step
PASSES = 10


class CableFriction(Effect):
    name = "cable_friction"
    description = "dry friction along each cable that sticks (virtual mass and damper) and slips at F"
    blocks = (
        ParamBlock("force", "spring", unit="N"),
        ParamBlock("stick_mass", "spring", unit="kg"),
        ParamBlock("stick_damping", "spring", unit="N s/m"),
    )
    needs_base_acceleration = True  # the twin solves for the force given every other force
    fit_strategy = "classification"  # its columns depend on a classification made from its own values
    fit_cost = 15.0  # several passes of the fit (measured ~15x a drag fit on the robot)

    def __init__(self, n_rods: int, n_springs: int, values: Any = None, stderr: Any = None,
                 options: dict[str, Any] | None = None) -> None:
        super().__init__(n_rods, n_springs, values, stderr, options)
        # what the data showed under the last classification (:meth:`observe`): nothing yet
        self._never_stuck = np.zeros(self.n_springs, dtype=bool)
        self._never_slipped = np.zeros(self.n_springs, dtype=bool)
        self._qmax = np.zeros(self.n_springs)
        self._held = np.zeros(self.n_params, dtype=bool)

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> CableFriction:
        return cls(topology.n_rods, topology.n_springs)

    # ------------------------------------------------------------------ kinematics
    @staticmethod
    def _length_rows(ctx: Any) -> torch.Tensor:
        """``P`` (..., S, 2, 6): the cable length rate per unit twist ``(v, ω_world)`` of the rod
        at each end, ``L̇ = Σ_e P_e · twist(rod(e))``; zero at fixed anchors."""
        unit = ctx.geometry.unit.unsqueeze(-2)  # (..., S, 1, 3)
        lever = ctx.ends.lever
        sign = torch.tensor([-1.0, 1.0], dtype=unit.dtype, device=unit.device).view(2, 1)
        on = ctx.graph.on_rod.to(unit.dtype).unsqueeze(-1)
        u = unit.expand_as(lever)
        return torch.cat((u, torch.linalg.cross(lever, u)), -1) * sign * on

    @staticmethod
    def _length_acceleration(ctx: Any, P: torch.Tensor, lin: torch.Tensor, ang_body: torch.Tensor) -> torch.Tensor:
        """``J qacc`` per cable (..., S) from rod accelerations (..., R, 3) world / rod frame."""
        alpha = matrix_apply(ctx.rot, ang_body)
        idx = ctx.graph.endpoint_rods  # (S, 2), anchors -> 0 (their P is zero)
        twist = torch.cat((lin, alpha), -1)[..., idx, :]  # (..., S, 2, 6)
        return (P * twist).sum((-1, -2))

    def _split(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        th = self.theta(like).view(self.n_springs, 3)
        return th[:, 0], th[:, 1], th[:, 2]

    # ------------------------------------------------------------------ the fit's columns
    def end_features(self, state: Any, ctx: Any) -> torch.Tensor:
        """Per unit of (F, m, d): the force on each cable end, (..., S, 2, 3, 3), from the recorded
        accelerations and the current classification (stick / slip and the slip direction)."""
        if ctx.recorded_lin_acc is None:
            raise ValueError("cable_friction's columns need the recorded accelerations (a fit context)")
        P = self._length_rows(ctx)
        acc = self._length_acceleration(ctx, P, ctx.recorded_lin_acc, ctx.recorded_ang_acc_body)
        rate = ctx.geometry.rate
        stick, direction = self.classify(acc, rate)
        zero = torch.zeros_like(rate)
        per = torch.stack((torch.where(stick, zero, direction), torch.where(stick, acc, zero),
                           torch.where(stick, rate, zero)), -1)  # (..., S, 3) resisting force per unit
        t = per.unsqueeze(-1) * ctx.geometry.unit.unsqueeze(-2)  # (..., S, 3, 3)
        return torch.stack((t, -t), dim=-3)

    def classify(self, acc: torch.Tensor, rate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Which cables stick (..., S) bool, and the direction of the slip force (±1).

        With fitted values: the constraint's own condition ``|m L̈ + d L̇| < F``; at a start of the
        fit's search (options ``start_rate`` b, ``start_band`` θ, :func:`identified.fit.classification.starts`): ``|L̈ + b L̇| < θ``; else (an
        unfitted candidate) a length rate below 1 mm/s, slipping against it."""
        if self.values is None and "start_rate" in self.options:  # a start of the fit's search
            z = acc + float(self.options["start_rate"]) * rate
            return z.abs() < float(self.options["start_band"]), torch.sign(z)
        if self.values is None:  # an unfitted candidate (diagnose's scores): stuck below 1 mm/s
            return rate.abs() < 1e-3, torch.sign(rate)
        F, m, d = self._split(acc)
        q = m * acc + d * rate
        return q.abs() < F.clamp_min(0.0), torch.sign(q)

    def length_motion(self, ctx: Any, lin_acc: torch.Tensor, ang_acc_body: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each cable's length acceleration ``L̈`` (..., S) under the rod accelerations ``lin_acc``
        (..., R, 3) world and ``ang_acc_body`` (..., R, 3) rod frame, and its length rate ``L̇``
        (..., S): what :meth:`classify` reads."""
        acc = self._length_acceleration(ctx, self._length_rows(ctx), lin_acc, ang_acc_body)
        return acc, ctx.geometry.rate

    def stick_force(self, acc: torch.Tensor, rate: torch.Tensor) -> torch.Tensor:
        """The stick law's force ``|m L̈ + d L̇|`` (..., S) with the fitted values."""
        _, m, d = self._split(acc)
        return (m * acc + d * rate).abs()

    def observe(self, stuck: np.ndarray, rows: int, qmax: np.ndarray, min_rows: int = 100) -> None:
        """Record what the data showed of each cable under the current classification: ``stuck``
        (S,) instants seen sticking out of ``rows``, ``qmax`` (S,) the largest stick force seen.
        A cable seen sticking fewer than ``min_rows`` times has a stick law the data cannot tell:
        its ``m``, ``d`` are held at 0 (:meth:`pinned`), and the twin lets it slip at ``F`` -- or,
        with ``F`` = 0, carry no friction at all (:mod:`identified.fit.classification`)."""
        self._never_stuck = np.asarray(stuck) < min_rows
        self._never_slipped = rows - np.asarray(stuck) < min_rows
        self._qmax = np.asarray(qmax, dtype=float)

    def release(self) -> None:
        """Forget the parameters :meth:`hold` held (a new start of the search)."""
        self._held = np.zeros(self.n_params, dtype=bool)

    def hold(self, names: list[str], topology: Any) -> bool:
        """Hold (at :meth:`pinned_values`) the parameters of this effect among ``names`` -- those
        a pass found unidentifiable; whether any was."""
        mine = self.param_names(topology.rod_names, topology.spring_names)
        idx = [mine.index(n) for n in names if n in mine]
        if not idx:
            return False
        self._held = self._held.copy()
        self._held[idx] = True
        return True

    def pinned(self) -> np.ndarray:
        """(P,) bool: parameters the data cannot tell, held in the fit (:meth:`pinned_values`).

        A cable never seen sticking: its stick law (``m``, ``d`` held at 0).  A cable never seen
        slipping: its slip force (held at the largest stick force seen, a lower bound) and its
        stick damping ``d`` (held at 0: while it sticks, ``d`` and the spring's own damping ``c``
        act alike, and ``c`` takes both)."""
        stick, slip = self._never_stuck, self._never_slipped
        return np.stack([slip, stick, stick | slip], 1).reshape(-1) | self._held

    def pinned_values(self) -> np.ndarray:
        """(P,) the values of the held parameters (:meth:`pinned`)."""
        F = self._qmax
        return np.stack([F, np.zeros_like(F), np.zeros_like(F)], 1).reshape(-1)

    def inert(self) -> bool:
        """Whether the last classification saw no cable stick (nothing for more passes to settle)."""
        return bool(np.all(self._never_stuck))

    def partly_unseen(self) -> bool:
        """Whether the last classification saw some cables stick and others not (too few rows to
        tell their stick law): the data the classification was made on are too few for it."""
        never = self._never_stuck
        return bool(np.any(never) and not np.all(never))

    def unseen(self) -> dict[str, list[int]]:
        """Cables the data never showed sticking or slipping (for the fit's report)."""
        return {"never_stuck": np.flatnonzero(self._never_stuck).tolist(),
                "never_slipped": np.flatnonzero(self._never_slipped).tolist()}

    def reclassify(self, previous: np.ndarray | None) -> bool:
        """Whether another pass of the fit is needed: the parameters moved since ``previous`` by
        more than 1e-9 of each block's largest value (F, m, d; a cable with no friction, F = 0,
        does not keep the passes going on rounding)."""
        if previous is None or self.values is None:
            return True
        now, before = self.values.reshape(-1, 3), previous.reshape(-1, 3)
        scale = np.maximum(np.abs(now).max(0), 1e-12)
        return bool(np.any(np.abs(now - before).max(0) > 1e-9 * scale))

    # ------------------------------------------------------------------ the twin
    def wrench(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Force and WORLD torque on each rod: the box-constrained friction of every cable."""
        from identified.engine.accelerations import rod_wrench

        t = self.cable_forces(state, ctx).unsqueeze(-1) * ctx.geometry.unit
        return rod_wrench(ctx.graph, torch.stack((t, -t), dim=-2), ctx.ends.lever)

    def cable_forces(self, state: Any, ctx: Any) -> torch.Tensor:
        """The friction force resisting each cable's lengthening, (..., S), given the accelerations
        under every other force (``ctx.base_lin_acc``, ``ctx.base_ang_acc_body``)."""
        F, m, d = self._split(state.pos)
        m = m.clamp_min(1e-9)
        P = self._length_rows(ctx)  # (..., S, 2, 6)
        p = ctx.params
        idx = ctx.graph.endpoint_rods
        # Y_e = M⁻¹ P_e of the end's rod: lin / M, ang through the world inertia R I⁻¹ Rᵀ
        rot = ctx.rot[..., idx, :, :]  # (..., S, 2, 3, 3)
        lin = P[..., :3] / p.mass[..., idx].unsqueeze(-1)
        ang = matrix_apply(rot, matrix_apply_transpose(rot, P[..., 3:]) / p.inertia[..., idx, :])
        Y = torch.cat((lin, ang), -1)
        # A_jk = sum over the ends e of j and f of k on one rod of P_je . Y_kf: the ends gathered per
        # rod, (..., S, R x 6), and one batched product
        on = self._end_rods(ctx.graph, p.mass.shape[-1], P)  # (S, 2, R, 1)
        J = (P.unsqueeze(-2) * on).sum(-3).flatten(-2)
        A = J @ (Y.unsqueeze(-2) * on).sum(-3).flatten(-2).transpose(-1, -2)  # (..., S, S)
        acc0 = self._length_acceleration(ctx, P, ctx.base_lin_acc, ctx.base_ang_acc_body)
        rate = ctx.geometry.rate
        Q = A + torch.diag_embed(1.0 / m.expand_as(rate))
        demand = acc0 + (d / m) * rate  # what sticking needs: Q r = demand
        if torch.compiler.is_compiling():  # compiled: a fixed count (no data-dependent branch, one graph)
            return _box_solve(Q, A, demand, acc0, rate, F, m, d, PASSES)
        # eager: the instants still moving, only -- an instant whose active set did not change in a
        # pass gets the same solve in every later one (the batched solves are independent per instant)
        shape = rate.shape
        S = shape[-1]
        flat = lambda x: x.expand(shape).reshape(-1, S)
        Q, A = Q.expand(*shape, S).reshape(-1, S, S), A.expand(*shape, S).reshape(-1, S, S)
        demand, acc0, rate, F, m, d = (flat(x) for x in (demand, acc0, rate, F, m, d))
        out = torch.empty_like(rate)
        todo = torch.arange(rate.shape[0], device=rate.device)
        slip = torch.zeros_like(rate, dtype=torch.bool)
        sign = torch.zeros_like(rate)
        for _ in range(PASSES):
            r, slip, sign, moved = _box_pass(Q, A, demand, acc0, rate, F, m, d, slip, sign)
            done = ~moved
            out[todo[done]] = torch.where(slip[done], F[done] * sign[done], r[done].clamp(-F[done], F[done]))
            if bool(done.all()):
                return out.reshape(shape)
            keep = moved.nonzero().squeeze(-1)
            todo = todo[keep]
            Q, A, demand, acc0, rate, F, m, d, slip, sign = (x[keep] for x in (Q, A, demand, acc0, rate, F, m, d,
                                                                              slip, sign))
            last = r[keep]
        out[todo] = torch.where(slip, F * sign, last.clamp(-F, F))
        return out.reshape(shape)

    def _end_rods(self, graph: Any, n_rods: int, like: torch.Tensor) -> torch.Tensor:
        """(S, 2, R, 1): 1 where end e of cable j sits on rod r (0 at a fixed anchor)."""
        key = ("ends", n_rods, like.dtype, like.device)
        if key not in self._cache:
            rods = graph.endpoint_rods.to(like.device)
            hit = (rods.unsqueeze(-1) == torch.arange(n_rods, device=like.device)) & graph.on_rod.unsqueeze(-1)
            self._cache[key] = hit.to(like.dtype).unsqueeze(-1)
        return self._cache[key]


def _box_pass(Q: torch.Tensor, A: torch.Tensor, demand: torch.Tensor, acc0: torch.Tensor, rate: torch.Tensor,
              F: torch.Tensor, m: torch.Tensor, d: torch.Tensor, slip: torch.Tensor, sign: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One active-set pass of the box solve (:meth:`CableFriction.cable_forces`): the sticking
    cables' forces with the slipping ones at ``±F``, then the new active set.  Returns the forces,
    ``slip``, ``sign`` and whether each instant's active set changed, (...) bool."""
    eye = torch.eye(Q.shape[-1], dtype=Q.dtype, device=Q.device)
    free = (~slip).to(Q.dtype)
    fixed = torch.where(slip, F * sign, torch.zeros_like(rate))
    rhs = (demand - (A @ fixed.unsqueeze(-1)).squeeze(-1)) * free
    Qf = Q * free.unsqueeze(-1) * free.unsqueeze(-2) + eye * (1.0 - free).unsqueeze(-1)
    r = torch.linalg.solve(Qf, rhs.unsqueeze(-1)).squeeze(-1) * free + fixed
    q = m * (acc0 - (A @ r.unsqueeze(-1)).squeeze(-1)) + d * rate  # the stick law at this r
    # a sticking cable that asks for more than F slips, in the direction it pulled; a slipping
    # one sticks again once the stick law at its bound asks for less (the box's KKT
    # conditions); a slipping cable keeps its direction (re-reading it from q cycles)
    clamp = ~slip & (r.abs() > F)
    release = slip & (sign * q < F)
    sign = torch.where(clamp, torch.sign(r), sign)
    slip = (slip | clamp) & ~release
    return r, slip, sign, (clamp | release).any(-1)


def _box_solve(Q: torch.Tensor, A: torch.Tensor, demand: torch.Tensor, acc0: torch.Tensor, rate: torch.Tensor,
               F: torch.Tensor, m: torch.Tensor, d: torch.Tensor, passes: int) -> torch.Tensor:
    """``passes`` active-set passes over every instant (the compiled twin: one graph)."""
    slip = torch.zeros_like(rate, dtype=torch.bool)
    sign = torch.zeros_like(rate)
    for _ in range(passes):
        r, slip, sign, _ = _box_pass(Q, A, demand, acc0, rate, F, m, d, slip, sign)
    return torch.where(slip, F * sign, r.clamp(-F, F))
