"""The one-step pass of the diagnosis: the model's residual wrench at every recorded instant, where
it lies (by rod, axis, region of state, and on the rows of the model's own effects), and how much of
it each candidate effect would remove.

One pass over the data in windows (:func:`_windows`): each window's residual wrench
(:func:`identified.evaluate.residual_wrench`) is stored (:class:`_Record`) and added to the normal
equations of the candidates' scores (:class:`_Scores`); the summaries are taken at the end.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from identified.dataset import Dataset
from identified.effects import Effect
from identified.evaluate import actuator_forces, push_points, residual_wrench
from identified.fit.derivatives import weak_form, weak_rows, weak_stride
from identified.fit.features import RodColumns, equation_rows
from identified.fit.identify import dilate_rows
from identified.fit.layout import ParameterLayout
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel
from identified.rotation import matrix_apply
from identified.samples import iter_chunks
from identified.twin import effects_from_model, engine_from_model

from .stats import explained_sum_of_squares, least_squares

__all__ = ["FAST_QUANTILE", "FOLDS", "held_out_score", "one_step"]

FAST_QUANTILE = 0.9
#: the candidates' sums are kept per half of the data, for the held-out scores ...
FOLDS = 2
#: ... the halves made of blocks of this many seconds, alternating
FOLD_BLOCK_S = 1.0
_TIME_POINTS = 600
_SCATTER_POINTS = 3000
_SAMPLE_INSTANTS = 400


def one_step(model: IdentifiedModel, data: Dataset, candidates: list[Effect], region_effects: dict[str, Effect],
             chunk_steps: int, weak_window: int | None = None, contact_margin: int | None = None) -> dict[str, Any]:
    """The one-step residual of ``model`` on ``data`` (the keys of ``diagnose``'s ``one_step``,
    ``regions``, ``candidates``, ``best_feature``, and the raw residual ``res`` (E, T', R, 6) with
    its instants ``times`` for the statistics).  ``weak_window``: the candidates are scored on the
    weak form of the rows (windows of that many steps; whole episodes are analysed at once);
    ``contact_margin`` (steps): the rows of the rods the model's own regional effects act on (ground
    contact's rods on the ground), and those within that many steps of them, are left out of the
    candidates' scores (``None``: every row is scored).

    ``region_effects``: per region name (an effect class's ``region``), the effect whose
    :meth:`~identified.effects.Effect.rows_affected` defines it (the model's own when it has one).
    """
    topo = model.topology
    scheme = model.metrics.get("scheme") or ("central" if model.integrator == "rk4" else "forward")
    first = 1 if scheme == "central" else 0
    eng = engine_from_model(model)
    half = torch.as_tensor(_half_lengths(model), dtype=torch.float64)
    rec = _Record(data.n_episodes, data.n_steps - first, topo.n_rods, topo.n_springs, list(region_effects))
    scores = _Scores(model, data, candidates, rec, eng.params.gravity, weak_window)
    if scores.weak:  # the windows of the weak form lie within an episode: analysed whole
        chunk_steps = max(chunk_steps, data.n_steps)
    own = {e.name for e in effects_from_model(model)}
    forces = actuator_forces(model, data)  # over whole episodes: a filter carries across the windows below

    for win, eps, t_first in _windows(data, chunk_steps, first):
        ch, n_ep = next(iter_chunks(win, 10**12, scheme))
        n_t = ch.pos.shape[0] // len(eps)
        tendon_force = None if forces is None else torch.as_tensor(
            forces[eps, t_first:t_first + n_t].reshape(-1, forces.shape[-1]), dtype=ch.pos.dtype)
        rw = residual_wrench(eng, ch, push_points(win, ch, n_ep, scheme), tendon_force)
        state = _state(ch)
        ctx = rw.terms.ctx
        rot = ctx.rot
        region_rows = {k: e.rows_affected(state, ctx) for k, e in region_effects.items()}
        if contact_margin is not None:  # the scores leave the model's regional effects' rows out
            hit = torch.zeros(ch.pos.shape[:2], dtype=torch.bool)
            for k, e in region_effects.items():
                if e.name in own:
                    hit |= region_rows[k]
            hit = dilate_rows(hit, n_ep, contact_margin) if contact_margin > 0 else hit
            ch.row_weight = (~hit).to(ch.pos.dtype) * (1.0 if ch.row_weight is None else ch.row_weight)
        # the residual's rows: force, and torque / half-length in the world (both N)
        y = torch.cat((rw.force, matrix_apply(rot, rw.torque_body) / half[:, None]), -1)  # (N, R, 6)
        if ch.row_weight is not None:  # the central scheme leaves out rows across a push switch
            y = y * ch.row_weight[..., None]
        ts = np.arange(t_first, t_first + n_t) - first
        rec.store(eps, ts, rw, ch, region_rows,
                  {k: e.contact_point(state, ctx) for k, e in region_effects.items() if hasattr(e, "contact_point")})
        ctx = ctx._replace(base_lin_acc=rw.terms.lin_acc, base_ang_acc_body=rw.terms.ang_acc_body,
                           recorded_lin_acc=ch.acc, recorded_ang_acc_body=ch.alpha_body)
        scores.add(ch, state, ctx, rot, half, y, eps, ts)

    out = rec.summary(topo, half)
    out["regions"] = rec.regions(topo, region_effects)
    out["effect_rows"] = rec.effect_rows({k: e for k, e in region_effects.items() if e.name in own})
    out.update(scores.results(rec))
    out["time_series"] = rec.time_series(topo, data.dt, first)
    out.update({"res": rec.res, "times": np.arange(first, data.n_steps), "scheme": scheme})
    return out


# ---------------------------------------------------------------------- the residual, stored
class _Record:
    """The residual wrench and the state's regions at every analysed instant (E, T', R, .)."""

    def __init__(self, E: int, Tn: int, R: int, S: int, regions: list[str]) -> None:
        self.res = np.full((E, Tn, R, 6), np.nan)  # force world N, torque rod frame N m
        self.ref = np.zeros((E, Tn, R, 6))  # the recorded inertial wrench, for the relative RMS
        self.masks = {k: np.zeros((E, Tn, R), dtype=bool) for k in (*regions, "pushed")}
        #: per region whose effect has a contact point: the residual torque about it (world, N m)
        self.about: dict[str, np.ndarray] = {}
        self.short = np.zeros((E, Tn, S), dtype=bool)
        self.speed = np.zeros((E, Tn, R))

    def store(self, eps: np.ndarray, ts: np.ndarray, rw: Any, ch: Any, region_rows: dict[str, torch.Tensor],
              points: dict[str, torch.Tensor] | None = None) -> None:
        E_, n_t = len(eps), len(ts)
        R, S = self.res.shape[2], self.short.shape[2]
        blk = (eps[:, None], ts[None, :])
        self.res[blk] = torch.cat((rw.force, rw.torque_body), -1).reshape(E_, n_t, R, 6).numpy()
        self.ref[blk] = torch.cat((rw.inertial_force, rw.inertial_torque_body), -1).reshape(E_, n_t, R, 6).numpy()
        self.short[blk] = (rw.terms.ctx.geometry.length < ch.rest).reshape(E_, n_t, S).numpy()
        self.masks["pushed"][blk] = (ch.push_force.norm(dim=-1) > 0).reshape(E_, n_t, R).numpy()
        for k, rows in region_rows.items():
            self.masks[k][blk] = rows.reshape(E_, n_t, R).numpy()
        torque = matrix_apply(rw.terms.ctx.rot, rw.torque_body)
        for k, point in (points or {}).items():
            if k not in self.about:
                self.about[k] = np.full(self.res.shape[:3] + (3,), np.nan)
            self.about[k][blk] = (torque - torch.linalg.cross(point, rw.force)).reshape(E_, n_t, R, 3).numpy()
        self.speed[blk] = ch.vel.norm(dim=-1).reshape(E_, n_t, R).numpy()

    @property
    def valid(self) -> np.ndarray:
        """(E, T') the instants analysed."""
        return ~np.isnan(self.res[..., 0, 0])

    def summary(self, topo: Any, half: torch.Tensor) -> dict[str, Any]:
        """RMS of the residual per world axis (force) and rod-frame axis (torque), relative to the
        recorded wrench, per rod, and the worst rod."""
        valid = self.valid
        r, rf_ = self.res[valid], self.ref[valid]  # (n, R, 6)
        force_rms, torque_rms = _rms(r[..., :3], (0, 1)), _rms(r[..., 3:], (0, 1))
        rel = {"force": _ratio(np.sqrt((force_rms ** 2).mean()), _rms(rf_[..., :3], (0, 1, 2))),
               "torque": _ratio(np.sqrt((torque_rms ** 2).mean()), _rms(rf_[..., 3:], (0, 1, 2)))}
        per = _rms(r, 0)  # (R, 6)
        per_rod = [{"rod": name, "force_rms": per[i, :3].tolist(), "torque_rms": per[i, 3:].tolist(),
                    "force_rms_norm": float(np.sqrt((per[i, :3] ** 2).sum())),
                    "torque_rms_norm": float(np.sqrt((per[i, 3:] ** 2).sum()))}
                   for i, name in enumerate(topo.rod_names)]
        worst = int(np.argmax([x["force_rms_norm"] + x["torque_rms_norm"] / half[i].item()
                               for i, x in enumerate(per_rod)]))
        return {"force_rms": force_rms.tolist(), "torque_rms": torque_rms.tolist(), "relative": rel,
                "per_rod": per_rod, "worst_rod": topo.rod_names[worst], "rows": int(valid.sum())}

    def regions(self, topo: Any, region_effects: dict[str, Effect]) -> dict[str, Any]:
        """The residual's norm in each region of state against the rest (rod-instants; spring ends
        for the slack springs): ``fraction`` of the rod-instants in it, RMS in and out, their ratio."""
        res, valid = self.res, self.valid
        fnorm = np.sqrt((res[..., :3] ** 2).sum(-1))
        tnorm = np.sqrt((res[..., 3:] ** 2).sum(-1))
        vr = np.broadcast_to(valid[..., None], fnorm.shape)
        S = self.short.shape[2]
        fast = self.speed >= np.quantile(self.speed[valid], FAST_QUANTILE)
        cables = np.asarray(topo.pull_only, dtype=bool)
        springs = np.flatnonzero(cables) if cables.any() else np.arange(S)
        js, es = np.nonzero(topo.endpoint_rods[springs] >= 0)
        end_rod, end_spring = topo.endpoint_rods[springs][js, es], springs[js]
        masks: dict[str, Any] = {k: (self.masks[k], fnorm, tnorm, vr) for k in region_effects}
        masks.update({
            "slack": (self.short[..., end_spring], fnorm[..., end_rod], tnorm[..., end_rod], vr[..., end_rod]),
            "fast": (fast, fnorm, tnorm, vr),
            "pushed": (self.masks["pushed"], fnorm, tnorm, vr),
        })
        descr = {k: (f"the rods whose equations hold the {e.name} force, as its fit classifies them "
                     f"(rod-instants)") for k, e in region_effects.items()}
        descr.update({
            "slack": ("a cable shorter than its rest length, i.e. slack (the rods at its ends, per cable end)"
                      if cables.any() else "a spring shorter than its rest length: slack if it were a cable "
                      "(the rods at its ends, per spring end)"),
            "fast": f"rod speed in the top {100 * (1 - FAST_QUANTILE):g} % of rod-instants",
            "pushed": "a push acts on the rod (rod-instants)"})
        out: dict[str, Any] = {}
        for k, (m, fv, tv, ok) in masks.items():
            inside, outside = m & ok, ~m & ok
            f_in, f_out = _rms_or_none(fv[inside]), _rms_or_none(fv[outside])
            t_in, t_out = _rms_or_none(tv[inside]), _rms_or_none(tv[outside])
            out[k] = {"description": descr[k], "available": True,
                      "fraction": float(inside.sum() / max(ok.sum(), 1)),
                      "force_rms_in": f_in, "force_rms_out": f_out, "torque_rms_in": t_in, "torque_rms_out": t_out,
                      "force_ratio": _ratio(f_in, f_out), "torque_ratio": _ratio(t_in, t_out)}
        return out

    def effect_rows(self, own: dict[str, Effect]) -> list[dict[str, Any]]:
        """For each of the model's own effects that acts in a region: the residual on its rows and
        on the other rows, relative to the recorded wrench there (force: ``|M (a - a_model)|`` RMS
        over ``|M (a - g)|`` RMS; torque likewise), over all episodes and per episode."""
        out = []
        valid = self.valid[..., None]
        for region, eff in own.items():
            inside = self.masks[region] & valid
            outside = ~self.masks[region] & valid
            entry: dict[str, Any] = {"effect": eff.name, "region": region,
                                     "fraction": float(inside.sum() / max((inside | outside).sum(), 1))}
            for side, m in (("inside", inside), ("outside", outside)):
                entry[side] = _relative(self.res[m], self.ref[m])
                entry[f"{side}_per_episode"] = [_relative(self.res[e][m[e]], self.ref[e][m[e]])
                                                for e in range(self.res.shape[0])]
            if region in self.about:  # what stays of the torque once the residual force's moment is out
                a = inside & ~np.isnan(self.about[region][..., 0])
                entry["inside"]["torque_about_contact_point"] = _ratio(_rms(self.about[region][a], None),
                                                                       _rms(self.ref[a][:, 3:], None))
            out.append(entry)
        return out

    def time_series(self, topo: Any, dt: float, first: int) -> dict[str, Any]:
        """The residual's force and torque norms against time, episode 0, per rod, subsampled."""
        Tn = self.res.shape[1]
        fnorm = np.sqrt((self.res[0, :, :, :3] ** 2).sum(-1))
        tnorm = np.sqrt((self.res[0, :, :, 3:] ** 2).sum(-1))
        ti = np.unique(np.linspace(0, Tn - 1, min(Tn, _TIME_POINTS)).round().astype(int))
        return {"t": ((ti + first) * dt).tolist(), "rods": list(topo.rod_names),
                "force": fnorm[ti].T.tolist(), "torque": tnorm[ti].T.tolist()}


# ---------------------------------------------------------------------- candidate scores
class _Accumulator:
    """Normal equations and moment sums of one candidate's columns ``X`` against the residual rows
    ``y`` and the base model's equation columns ``B``, added rod by rod (each rod's rows touch only
    its own columns: the sums stay small), per half of the data (:data:`FOLDS`)."""

    def __init__(self, eff: Effect, names: list[str], n_base: int) -> None:
        self.eff, self.names, self.n_base = eff, names, n_base
        self.P = 0
        self.nonfinite = self.entries = 0
        self.sample: list[np.ndarray] = []

    def allocate(self, blocks: list[tuple[torch.Tensor, np.ndarray]]) -> None:
        """Size the sums by the columns the features give (a global effect may have parameters
        without a feature column, e.g. the friction bound of ground contact)."""
        if self.P:
            return
        kind = self.eff.kind
        P = self.P = self.eff.n_params if kind != "global" else max(len(xi) for _, xi in blocks)
        self.XX, self.Xy = np.zeros((FOLDS, P, P)), np.zeros((FOLDS, P))
        self.BX = np.zeros((FOLDS, self.n_base, P))
        self.sx, self.sxx = np.zeros(P), np.zeros(P)

    def add(self, f: int, X: np.ndarray, xi: np.ndarray, y: np.ndarray, B: np.ndarray, bi: np.ndarray) -> None:
        """One rod's rows of half ``f``: ``X`` (n, w) the candidate's columns ``xi``, ``B`` (n, nb) the base's ``bi``."""
        self.XX[f][np.ix_(xi, xi)] += X.T @ X
        self.Xy[f][xi] += X.T @ y
        self.BX[f][np.ix_(bi, xi)] += B.T @ X
        self.sx[xi] += X.sum(0)
        self.sxx[xi] += (X * X).sum(0)


@dataclass
class _Moments:
    """Sums over the residual rows: their sum, sum of squares per half of the data, and count."""

    sy: float = 0.0
    syy: np.ndarray = field(default_factory=lambda: np.zeros(FOLDS))
    n: int = 0


class _Scores:
    """The candidates' scores: least squares of the residual rows on the model's own equation
    columns (total mass held) with and without each candidate's columns, from normal equations
    summed window by window -- on the rows as they are, or (``weak``) on their weak form, each
    episode's rows summed over windows of ``weak`` steps with the fit's bump
    (:func:`identified.fit.derivatives.weak_form`).  The sums are kept per half of the data for the
    held-out scores: blocks of :data:`FOLD_BLOCK_S` (at most half an episode) alternate between the
    halves, shifted by one from an episode to the next (a row belongs to the block of its instant,
    a weak-form window to that of its middle)."""

    def __init__(self, model: IdentifiedModel, data: Dataset, candidates: list[Effect], rec: _Record,
                 gravity: torch.Tensor, weak: int | None = None) -> None:
        topo = model.topology
        self.topo, self.R = topo, topo.n_rods
        # the base model's columns (its joint effects' too), refitted beside each candidate
        self.joint = [e for e in effects_from_model(model) if e.stage == "joint"]
        self.layout = ParameterLayout.for_topology(topo, "multiple", self.joint)
        self.rcols = RodColumns.build(topo, self.layout)
        nb = self.nb = self.layout.n_full
        self.base_idx = [np.flatnonzero(self.rcols.full[i] >= 0) for i in range(self.R)]  # local columns of rod i
        self.implicit_dt = data.dt if model.integrator == "implicit" else None
        self.gravity = gravity
        self.weak = weak if weak and weak > 1 else None
        self.GBB, self.bB = np.zeros((FOLDS, nb, nb)), np.zeros((FOLDS, nb))
        self.accs = [_Accumulator(c, c.param_names(topo.rod_names, topo.spring_names), nb) for c in candidates]
        self.m = _Moments()
        self.sample_rows: list[np.ndarray] = []
        E, Tn = rec.res.shape[:2]
        if self.weak:
            Tn = weak_rows(Tn, self.weak)  # the windows per episode
        self.Tn = Tn
        # the halves: blocks of FOLD_BLOCK_S seconds (at most half an episode), alternating in time
        # and from one episode to the next -- each half sees every episode and every kind of motion
        self.block = max(1, min(round(FOLD_BLOCK_S / data.dt), -(-rec.res.shape[1] // 2)))
        self.stride = max(1, E * Tn // _SAMPLE_INSTANTS)

    def add(self, ch: Any, state: Any, ctx: Any, rot: torch.Tensor, half: torch.Tensor, y: torch.Tensor,
            eps: np.ndarray, ts: np.ndarray) -> None:
        """One window's rows ``y`` (N, R, 6): the base columns, each candidate's columns, the
        moments and the sampled instants for the scatter plot."""
        R = self.R
        with torch.no_grad():
            Bt = _base_rows(equation_rows(self.topo, self.rcols, ch, self.gravity, self.implicit_dt, self.joint),
                            rot, half)
            cand_X = [self._candidate_columns(acc, state, ctx, half, ch.row_weight) for acc in self.accs]
            row_t = ts  # each row's place in its episode (the weak form: its window's)
            if self.weak:  # every row summed over windows of each episode's steps (whole episodes here)
                n_ep, w = len(eps), self.weak
                row_t = np.arange(weak_rows(len(ts), w))
                ts = ts[0] + weak_stride(w) * row_t + w // 2  # the windows' middles
                y, Bt = weak_form(y, n_ep, w), weak_form(Bt, n_ep, w)
                cand_X = [[(weak_form(X, n_ep, w), xi) for X, xi in blocks] for blocks in cand_X]
        fold = ((eps[:, None] + ts[None, :] // self.block) % FOLDS).reshape(-1)
        rows_of = [np.flatnonzero(np.repeat(fold == f, 6)) for f in range(FOLDS)]  # a rod's rows: 6 per instant
        yv = y.reshape(-1).numpy()
        self.m.sy += float(yv.sum())
        self.m.n += yv.size
        yr = y.numpy()
        for f in range(FOLDS):
            yf = yr[fold == f]
            self.m.syy[f] += float((yf * yf).sum())
        # instants kept for the scatter plot: global flat index (e * Tn + t) on the stride
        flat = (eps[:, None] * self.Tn + row_t[None, :]).reshape(-1)
        keep = np.flatnonzero(flat % self.stride == 0)
        self.sample_rows.append(yv[(keep[:, None] * (R * 6) + np.arange(R * 6)).reshape(-1)])
        for i in range(R):
            yi = yr[:, i].reshape(-1)
            bi = self.base_idx[i]
            Bi = Bt[:, i][..., torch.as_tensor(bi)].reshape(-1, len(bi)).numpy()
            fi = self.rcols.full[i, bi]
            Xs = [(X.reshape(-1, len(xi)).numpy(), xi) for X, xi in (blocks[i] for blocks in cand_X)]
            for f, rows in enumerate(rows_of):
                if not len(rows):
                    continue
                Bf, yf = Bi[rows], yi[rows]
                self.GBB[f][np.ix_(fi, fi)] += Bf.T @ Bf
                self.bB[f][fi] += Bf.T @ yf
                for acc, (X, xi) in zip(self.accs, Xs):
                    acc.add(f, X[rows], xi, yf, Bf, fi)
        for acc, blocks in zip(self.accs, cand_X):  # the sampled instants' rows, dense
            Xs = np.zeros((len(keep), R, 6, acc.P))
            for i, (X, xi) in enumerate(blocks):
                Xs[:, i][..., xi] = X[torch.as_tensor(keep)].numpy()
            acc.sample.append(Xs.reshape(-1, acc.P))

    def _candidate_columns(self, acc: _Accumulator, state: Any, ctx: Any, half: torch.Tensor,
                           row_weight: torch.Tensor | None) -> list[tuple[torch.Tensor, np.ndarray]]:
        blocks = _candidate_blocks(acc.eff, state, ctx, self.topo, half)
        acc.allocate(blocks)
        # a model far from physical (negative inertia) can make a feature non-finite: count, zero
        acc.nonfinite += sum(int((~torch.isfinite(X)).sum()) for X, _ in blocks)
        acc.entries += sum(X.numel() for X, _ in blocks)
        blocks = [(torch.nan_to_num(X, nan=0.0, posinf=0.0, neginf=0.0), xi) for X, xi in blocks]
        if row_weight is not None:
            blocks = [(X * row_weight[:, i, None, None], xi) for i, (X, xi) in enumerate(blocks)]
        return blocks

    def results(self, rec: _Record) -> dict[str, Any]:
        """``candidates`` (scores, correlations), ``best_feature``, ``scatter``, ``base_refit``."""
        m = self.m
        sy, syy, n_rows = m.sy, float(m.syy.sum()), m.n
        cands, best = [], None
        my, vy = sy / max(n_rows, 1), syy / max(n_rows, 1) - (sy / max(n_rows, 1)) ** 2
        Z = _mass_total_held(self.nb, np.array([self.layout.m(i) for i in range(self.R)]))
        GBB_f, bB_f = Z.T @ self.GBB @ Z, self.bB @ Z  # per half, in the total-mass-held directions
        GBB, bB = GBB_f.sum(0), bB_f.sum(0)
        rss_base = max(syy - explained_sum_of_squares(GBB, bB), 0.0) if self.accs else None
        for acc in self.accs:
            entry, corr = self._score(acc, Z, GBB, bB, rss_base, my, vy)
            entry.update(self._held_out(acc, Z, GBB_f, bB_f, GBB, bB))
            cands.append(entry)
            P = acc.P
            j = int(np.argmax(np.abs(corr))) if P else 0
            if P and (best is None or abs(corr[j]) > abs(best[0])):
                best = (float(corr[j]), acc, j, acc.names[:P][j])
        scatter, best_feature = {}, None
        if best is not None and np.isfinite(best[0]):
            corr, acc, j, name = best
            x = np.concatenate([s[:, j] for s in acc.sample])
            nz = np.flatnonzero(x != 0)
            pick = nz[np.unique(np.linspace(0, len(nz) - 1, min(len(nz), _SCATTER_POINTS)).round().astype(int))] \
                if len(nz) else nz
            sample_y = np.concatenate(self.sample_rows)
            scatter = {"name": name, "corr": corr, "x": x[pick].tolist(), "y": sample_y[pick].tolist()}
            best_feature = {"candidate": acc.eff.name, "feature": name, "corr": corr}
        return {"candidates": cands, "best_feature": best_feature, "scatter": scatter,
                "base_refit": None if rss_base is None or syy <= 0 else float(np.clip(1 - rss_base / syy, 0, 1))}

    def _held_out(self, acc: _Accumulator, Z: np.ndarray, GBB_f: np.ndarray, bB_f: np.ndarray, GBB: np.ndarray,
                  bB: np.ndarray) -> dict[str, Any]:
        """The candidate's score on each half of the data with its coefficients fitted on the
        other half (:func:`held_out_score`; ``GBB_f``, ``bB_f`` the base's sums per half, ``GBB``,
        ``bB`` over both); ``score_held_out`` is the smaller of the two (``None`` where a half
        holds no residual)."""
        per: list[float | None] = []
        if acc.P:
            BX = np.einsum("ij,fjk->fik", Z.T, acc.BX)
            sums = [(GBB_f[f], bB_f[f], BX[f], acc.XX[f], acc.Xy[f], float(self.m.syy[f])) for f in range(FOLDS)]
            whole = (GBB, bB, BX.sum(0))
            per = [held_out_score(sums[FOLDS - 1 - test], sums[test], whole) for test in range(FOLDS)]
        held = None if not per or any(v is None for v in per) else float(min(per))
        if acc.nonfinite > 0.01 * max(acc.entries, 1):
            held, per = None, []
        return {"score_held_out": held, "score_held_out_halves": [finite_or_none(v) for v in per]}

    def _score(self, acc: _Accumulator, Z: np.ndarray, GBB: np.ndarray, bB: np.ndarray, rss_base: float | None,
               my: float, vy: float) -> tuple[dict[str, Any], np.ndarray]:
        """One candidate's score (``1 - RSS(base + candidate) / RSS(base)``), the share its columns
        alone explain, and its columns' correlations with the residual rows."""
        syy, n_rows, P = float(self.m.syy.sum()), self.m.n, acc.P
        BX = Z.T @ acc.BX.sum(0)
        XX, Xy = acc.XX.sum(0), acc.Xy.sum(0)
        score = alone = unexplained = None
        if syy > 0:
            alone = float(np.clip(explained_sum_of_squares(XX, Xy) / syy, 0.0, 1.0))
            G = np.block([[GBB, BX], [BX.T, XX]])
            rss = max(syy - explained_sum_of_squares(G, np.concatenate((bB, Xy))), 0.0)
            if rss_base > 0:
                unexplained = float(np.clip(rss / rss_base, 0.0, 1.0))
                score = 1.0 - unexplained
        note = None
        if acc.nonfinite > 0.01 * max(acc.entries, 1):
            note = (f"features not finite on {acc.nonfinite / acc.entries:.0%} of the entries under this model's "
                    f"parameters (a negative inertia?): not scored")
            score = unexplained = alone = None
        mx, vx = acc.sx / n_rows, acc.sxx / n_rows - (acc.sx / n_rows) ** 2
        cov = Xy / n_rows - mx * my
        with np.errstate(all="ignore"):
            corr = np.where((vx > 0) & (vy > 0), cov / np.sqrt(np.clip(vx, 1e-300, None) * max(vy, 1e-300)), 0.0)
        j = int(np.argmax(np.abs(corr))) if P else 0
        names = acc.names[:P]
        top = np.argsort(-np.abs(corr))[:3]
        return ({"name": acc.eff.name, "score": score, "unexplained": unexplained, "score_alone": alone,
                 "n_params": int(P), "description": acc.eff.description,
                 "nonfinite_features": int(acc.nonfinite), "note": note,
                 "max_abs_corr": finite_or_none(abs(corr[j])) if P else None,
                 "best_feature": names[j] if P else None,
                 "top_features": [{"feature": names[i], "corr": finite_or_none(corr[i])} for i in top]}, corr)


def held_out_score(fit: tuple, test: tuple, base: tuple) -> float | None:
    """A candidate's score on the ``test`` rows with its coefficients fitted on the ``fit`` rows.

    ``fit`` and ``test`` are the sums ``(B'B, B'y, B'X, X'X, X'y, y'y)`` of their rows (``B`` the
    model's own columns, ``X`` the candidate's, ``y`` the residual); ``base`` is ``(B'B, B'y, B'X)``
    over all the rows.  The model's own columns are taken out of ``X`` and ``y`` with their fit on
    all the rows (Frisch-Waugh: ``X~ = X - B P``, ``y~ = y - B q``, ``P = (B'B)⁺ B'X``, ``q = (B'B)⁺
    B'y``), as the in-sample score lets them move; the candidate's coefficients ``θ`` are the least
    squares of ``y~`` on ``X~`` over the fitting rows, and the score is the share of the test rows'
    ``|y~|²`` they remove, ``1 - |y~ - X~ θ|² / |y~|²``.  An effect the data do not hold has a ``θ``
    fitted to the other half's noise, which removes nothing there (less than nothing, about ``-P /
    rows``).  (Refitting the model's columns on half the rows instead leaves them and a candidate
    poorly told apart on a short recording: a drag and the cables' dampings both pull against
    velocity.)"""
    GBB, bB, BX = base
    P, q = least_squares(GBB, BX), least_squares(GBB, bB)

    def tilde(s: tuple) -> tuple[np.ndarray, np.ndarray, float]:
        G, b, BXs, XX, Xy, yy = s
        XXt = XX - BXs.T @ P - P.T @ BXs + P.T @ G @ P
        Xyt = Xy - P.T @ b - BXs.T @ q + P.T @ G @ q
        return XXt, Xyt, float(yy - 2.0 * q @ b + q @ G @ q)

    XX, Xy, _ = tilde(fit)
    tXX, tXy, tyy = tilde(test)
    if not tyy > 0:
        return None
    theta = least_squares(XX, Xy)
    rest = tyy - 2.0 * theta @ tXy + theta @ tXX @ theta  # |y~ - X~ θ|²
    return float(1.0 - max(rest, 0.0) / tyy)


def _candidate_blocks(eff: Effect, state: Any, ctx: Any, topo: Any,
                      half: torch.Tensor) -> list[tuple[torch.Tensor, np.ndarray]]:
    """Per rod: its rows (N, 6, w) of the candidate's columns (force and torque / half-length,
    world) and which of the candidate's parameters they belong to (w,)."""
    R = state.pos.shape[-2]
    if eff.kind == "spring":
        f = eff.end_features(state, ctx)  # (N, S, 2, 3) or (N, S, 2, W, 3)
        if f.dim() == 4:
            f = f.unsqueeze(-2)
        W = f.shape[-2]
        tau = torch.cross(ctx.ends.lever.unsqueeze(-2).expand_as(f), f, dim=-1)
        out = []
        for i in range(R):
            js, es = np.nonzero(topo.endpoint_rods == i)
            u, inv = np.unique(js, return_inverse=True)
            cols = torch.cat((f[:, js, es], tau[:, js, es] / half[i]), -1).flatten(1, 2)  # (N, k W, 6)
            slots = torch.as_tensor((inv[:, None] * W + np.arange(W)).reshape(-1))
            X = torch.zeros(f.shape[0], len(u) * W, 6, dtype=f.dtype).index_add_(1, slots, cols)
            out.append((X.transpose(1, 2), (u[:, None] * W + np.arange(W)).reshape(-1)))
        return out
    force, torque = eff.features(state, ctx)  # (N, R, W, 3) rod / (N, R, P, 3) global
    cols = torch.cat((force, torque / half[:, None, None]), -1).transpose(-1, -2)  # (N, R, 6, W)
    W = cols.shape[-1]
    if eff.kind == "global":
        return [(cols[:, i], np.arange(W)) for i in range(R)]
    return [(cols[:, i], i * W + np.arange(W)) for i in range(R)]


def _base_rows(A: torch.Tensor, rot: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """Compact equation rows (N, R, 6, L) of :func:`~identified.fit.features.equation_rows` in the
    residual's rows: rotation rows (rod frame there) turned to the world and divided by the
    half-length."""
    tb = A[:, :, 3:].transpose(-1, -2)  # (N, R, L, 3)
    tw = matrix_apply(rot.unsqueeze(-3), tb).transpose(-1, -2) / half[:, None, None]
    return torch.cat((A[:, :, :3], tw), 2)


def _mass_total_held(n_full: int, m_idx: np.ndarray) -> np.ndarray:
    """``Z`` (n_full, n_full - 1): parameter changes with the total mass held (the last rod's mass
    change is minus the others'), which fixes the scale: otherwise the model's own parameters
    would explain any residual (``A θ = y``)."""
    keep = [k for k in range(n_full) if k != m_idx[-1]]
    Z = np.eye(n_full)[:, keep]
    Z[m_idx[-1], [keep.index(k) for k in m_idx[:-1]]] = -1.0
    return Z


# ---------------------------------------------------------------------- helpers
def _windows(data: Dataset, chunk_steps: int, first: int):
    """Sub-datasets of whole episodes (or time windows of one) of about ``chunk_steps`` steps, with
    the episode indices and the first recorded step whose equations they give."""
    E, T = data.n_episodes, data.n_steps
    per = max(1, chunk_steps // T)
    if per > 1 or T <= chunk_steps:
        spans = [(np.arange(e, min(e + per, E)), 0, T) for e in range(0, E, per)]
    else:
        spans = [(np.array([e]), t, min(t + chunk_steps, T)) for e in range(E) for t in range(0, T, chunk_steps)]
    for eps, t0, t1 in spans:
        a = max(t0 - first, 0)
        yield data.span(eps, a, t1), eps, a + first


def _state(ch: Any) -> Any:
    from identified.engine.integration import RodState

    return RodState(ch.pos, ch.quat, ch.vel, ch.angvel)


def _half_lengths(model: IdentifiedModel) -> np.ndarray:
    return np.array([max(r.length / 2.0, 1e-6) for r in model.topology.rods])


def _rms(a: np.ndarray, ax: Any = 0) -> np.ndarray:
    return np.sqrt(np.mean(a * a, axis=ax))


def _relative(res: np.ndarray, ref: np.ndarray) -> dict[str, float | None]:
    """RMS of the residual's force (torque) norm over RMS of the recorded wrench's, rows (n, 6)."""
    if not len(res):
        return {"force": None, "torque": None, "rows": 0}
    return {"force": _ratio(_rms(res[:, :3], None), _rms(ref[:, :3], None)),
            "torque": _ratio(_rms(res[:, 3:], None), _rms(ref[:, 3:], None)), "rows": len(res)}


def _ratio(a: Any, b: Any) -> float | None:
    a, b = finite_or_none(a), finite_or_none(b)
    if a is None or b is None or b <= 0:
        return None
    return a / b


def _rms_or_none(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x * x))) if x.size else None
