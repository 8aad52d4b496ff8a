"""Diagnosis of an identified model on recorded data: where it is wrong, and which effect explains it.

:func:`diagnose` is the library side of ``tensegrity diagnose``; :func:`write_report` draws its
figures and writes a report in words.  Everything is measured on the data given (use data the
model was not fitted on).

**Free-run error** (``error_before``, ``error_after``; the ``metric`` key says it in words): the
model is started from every episode's recorded initial state and driven by the recorded rest
lengths and pushes for ``horizon_s`` seconds; the error is the distance between each rod's
predicted and recorded centre of mass (m), averaged over rods, over the steps ``1..H`` and over the
episodes.  ``error_after`` is the model as it is, ``error_before`` the same model with its added
effects removed (``model.effects = []``).  ``None``: the free run diverged.

**One-step residual** (the acceleration residual, as a wrench): at every recorded instant, the
recorded acceleration (:func:`identified.samples.iter_chunks`: the forward difference of
the velocities, or the central one for an RK4 model) minus the model's, times the model's mass
(inertia), ``M (a - a_model)`` in newtons and ``I (α_b - α_b,model)`` in N m, i.e. the wrench the
model misses.  For the Euler integrator this is exactly ``M (a - g) - F`` and
``R (I α_b + ω_b × I ω_b) - τ``.  Forces are reported per world axis, torques per rod-frame axis
(z is the rod's axis).

**Candidates**: every effect of the library (:data:`identified.effects.EFFECTS`) the model does not
have.  The rows ``y`` are the residual force (3 rows) and the residual torque divided by the rod's
half-length (3 rows; world frame, so both are in newtons) of every rod at every instant; a
candidate's columns ``X`` are the same rows of its force and torque per unit of each of its
parameters (:meth:`identified.effects.Effect.features`).  Its *score* is the fraction of the
residual that adding it to the model would remove: least squares of ``y`` on the model's own
equation columns ``B`` (:func:`identified.fit.features.equation_rows`: K, c, M, I, h and the model's
joint effects, with the total mass held, which fixes the scale) together with ``X``, against ``B``
alone, ``score = 1 - RSS(B, X) / RSS(B)`` (``unexplained = 1 - score``): the base parameters may
move, because a fit without the effect has bent them to mimic it.  1 = the candidate explains the
residual completely, 0 = not at all; an unrelated candidate with ``P`` parameters scores about
``P / rows`` on white residuals.  ``score_alone`` is the fraction of ``y'y`` that ``X`` alone
explains.  ``ground_contact`` needs the MJCF's ground plane and capsules (``mjcf=``, else
``model.source_model`` when it is a file); without them it is listed under ``skipped``.

**Explained** (``explained``, with the reason in ``explained_by``): the residual is at rounding
level (its RMS below ``1e-6`` times the RMS of the recorded inertial wrench, for both force and
torque), or it is white (no rod/dof series rejects the Ljung-Box test at 1 % after a Bonferroni
correction over the series), or the model's added effects cut the free-run error at least 5×
(``error_after <= 0.2 error_before``).

Also: the residual by region of state (rod ends near the ground, slack cables -- springs shorter
than their rest length when no cable is declared --, the fastest 10 % of rod-instants, rods under a
push) against the rest; k-step errors;
Ljung-Box statistics per rod and dof; the residual's correlation with the inputs (rest lengths,
pushes) and with every candidate feature.  The result is a JSON-able dict (``None`` for anything
undefined, never NaN).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from identified.dataset import Dataset, DatasetError, atomic_write
from identified.effects import EFFECTS, GeometryError, make_effect, read_contact_geometry
from identified.engine.accelerations import inertial_wrench
from identified.engine.integration import RodState
from identified.fit.features import RodColumns, equation_rows
from identified.fit.layout import ParameterLayout
from identified.jsonsafe import json_safe
from identified.model import IdentifiedModel
from identified.predict import quat_distance, rollout
from identified.rotation import matrix_apply
from identified.samples import iter_chunks
from identified.twin import effects_from_model, engine_from_model

__all__ = ["DOFS", "K_STEPS", "diagnose", "ljung_box", "write_report"]

#: the six residual components per rod: world force axes, rod-frame torque axes
DOFS = ("fx", "fy", "fz", "tx", "ty", "tz")
#: k-step prediction errors are reported for these k
K_STEPS = (1, 10, 100)
ROUNDING_LEVEL = 1e-6  # residual RMS relative to the recorded wrench RMS
EXPLAINED_GAIN = 0.2  # error_after <= this x error_before
ALPHA = 0.01  # Ljung-Box level (Bonferroni over the rod/dof series)
LJUNG_BOX_LAGS = 20
NEAR_GROUND_M = 0.02  # a rod end is near the ground when its capsule is within this of the plane
FAST_QUANTILE = 0.9
_CURVE_POINTS = 200
_TIME_POINTS = 600
_SCATTER_POINTS = 3000
_KSTEP_STARTS = 256
_SAMPLE_INSTANTS = 400


# ---------------------------------------------------------------------- public API
def diagnose(
    model: IdentifiedModel,
    data: Dataset,
    horizon_s: float = 1.0,
    max_steps: int = 50_000,
    mjcf: str | os.PathLike | None = None,
    chunk_steps: int = 2048,
) -> dict[str, Any]:
    """Residual analysis of ``model`` on ``data`` (see the module docstring for every rule).

    ``horizon_s``: free-run horizon, s (the data must hold at least that much per episode);
    ``max_steps``: at most this many recorded steps are analysed (whole episodes first);
    ``mjcf``: path or text of the plant's MJCF, for the ground geometry (default: the model's
    ``source_model`` when it is a readable file).  Raises ``DatasetError`` when the data do not
    belong to the model, ``ValueError`` when they are too short for the horizon.

    Keys: ``error_before``, ``error_after`` (m), ``metric``, ``horizon_s``, ``added``,
    ``explained``, ``explained_by`` (``"rounding"``, ``"white"``, ``"improved"``),
    ``explained_rule``; ``candidates`` (best first: ``name``, ``score``, ``unexplained``,
    ``score_alone``, ``n_params``, ``max_abs_corr``, ``best_feature``, ``top_features``, ``note``),
    ``score_rule``, ``skipped`` (``name``, ``reason``), ``base_refit_explains``; ``data``;
    ``one_step`` (``force_rms`` N and ``torque_rms`` N m per axis, ``relative``, ``per_rod``,
    ``worst_rod``); ``k_step`` (``after``/``before``: ``{"1", "10", "100"}`` with ``pos`` m and
    ``quat``); ``free_run`` (``time_s``, ``before``, ``after`` curves, subsampled); ``regions``
    (``near_ground``, ``slack``, ``fast``, ``pushed``: RMS residual in and out); ``whiteness``
    (Ljung-Box per rod and dof, ``white``, ``min_p``); ``input_correlation`` (``rest_length``,
    ``push_force``); ``best_feature``; ``plot_data`` (what :func:`write_report` draws).

    Runs on one thread: its work is many small steps, which a team of threads only slows down
    (badly so on a loaded machine).
    """
    with threadpool_limits(1):
        return _diagnose(model, data, horizon_s, max_steps, mjcf, chunk_steps)


def _diagnose(model: IdentifiedModel, data: Dataset, horizon_s: float, max_steps: int,
              mjcf: str | os.PathLike | None, chunk_steps: int) -> dict[str, Any]:
    topo = model.topology
    if data.rod_names != topo.rod_names or data.tendon_names != topo.spring_names:
        missing = sorted(set(topo.rod_names + topo.spring_names) - set(data.rod_names + data.tendon_names))
        raise DatasetError("the dataset's rods/tendons do not match the identified model's"
                           + (f" (the data lack {', '.join(missing[:4])})" if missing else ""))
    if not (np.isfinite(horizon_s) and horizon_s > 0):
        raise ValueError(f"horizon must be a positive number of seconds, got {horizon_s}")
    H = round(horizon_s / data.dt)
    if H < 1 or H > data.n_steps:
        raise ValueError(f"the data hold {data.n_steps * data.dt:g} s per episode, shorter than the "
                         f"{horizon_s:g} s horizon")
    sub = _subset(data, int(max_steps), H)
    added = [str(e.get("name")) for e in model.effects]
    base = replace(model, effects=[])
    src = _mjcf_source(model, mjcf)
    geometry = _ground_geometry(model, src)

    # free run, before and after the added effects
    fr_after = _free_run(model, sub, H)
    fr_before = _free_run(base, sub, H) if added else fr_after
    k_after = _k_step(model, sub)
    k_before = _k_step(base, sub) if added else k_after

    # candidates: the library's effects the model does not have
    candidates, skipped = [], []
    for name in EFFECTS:
        if name in added:
            continue
        try:
            eff = make_effect(name, topo, src)
        except (GeometryError, ValueError, OSError) as exc:
            reason = str(exc) if src is not None else "no MJCF geometry (pass the plant's MJCF)"
            skipped.append({"name": name, "reason": reason})
            continue
        candidates.append(eff)
    skipped.append({"name": "actuator_lag", "reason": "not available: the dataset records the actual rest lengths"})

    one = _one_step(model, sub, candidates, geometry, chunk_steps)
    res = one["res"]  # (E, T', R, 6)
    lb = _whiteness(res, topo.rod_names)
    rel = one["relative"]
    rounding = all(v is not None and v < ROUNDING_LEVEL for v in rel.values())
    eb, ea = fr_before["error"], fr_after["error"]
    improved = bool(added) and ((eb is None and ea is not None)
                                or (eb is not None and ea is not None and eb > 0 and ea <= EXPLAINED_GAIN * eb))
    reasons = [r for r, ok in (("rounding", rounding), ("white", lb["white"]), ("improved", improved)) if ok]

    cand = sorted(one["candidates"], key=lambda c: -(c["score"] if c["score"] is not None else -1))
    result: dict[str, Any] = {
        "metric": (f"free-run position error: distance between predicted and recorded rod centres of mass, m, "
                   f"mean over rods, steps 1..{H} ({H * sub.dt:g} s) and {sub.n_episodes} episodes, from each "
                   f"episode's recorded initial state under the recorded rest lengths and pushes"),
        "horizon_s": H * sub.dt,
        "horizon_steps": H,
        "error_before": eb,
        "error_after": ea,
        "added": added,
        "explained": bool(reasons),
        "explained_by": reasons,
        "explained_rule": (f"explained when the one-step residual is at rounding level (RMS < {ROUNDING_LEVEL:g} x "
                           f"the recorded wrench RMS, force and torque), or white (Ljung-Box, {LJUNG_BOX_LAGS} lags, "
                           f"no rod/dof series rejects at {ALPHA:g} after Bonferroni), or the added effects cut the "
                           f"free-run error at least {1 / EXPLAINED_GAIN:g}x"),
        "candidates": cand,
        "score_rule": ("fraction of the one-step residual (rows: force and torque / rod half-length, world frame, "
                       "every rod and instant) that adding the candidate would remove: 1 - RSS(model columns + "
                       "candidate columns) / RSS(model columns), least squares with the model's own K, c, M, I, h "
                       "(total mass held) free to move; score_alone: the fraction the candidate's columns alone "
                       "explain"),
        "skipped": skipped,
        "base_refit_explains": one["base_refit"],
        "data": {"episodes": sub.n_episodes, "steps_per_episode": sub.n_steps, "dt": sub.dt,
                 "instants": int(one["rows"]), "scheme": one["scheme"], "integrator": model.integrator,
                 "episodes_given": data.n_episodes, "steps_given": data.n_steps},
        "one_step": {
            "definition": ("M (a_recorded - a_model) N per world axis, I (alpha_b,recorded - alpha_b,model) N m "
                           "per rod-frame axis (z = rod axis)"),
            "force_rms": one["force_rms"],
            "torque_rms": one["torque_rms"],
            "relative": rel,
            "per_rod": one["per_rod"],
            "worst_rod": one["worst_rod"],
        },
        "k_step": {"after": k_after, "before": k_before if added else None},
        "free_run": {"before": fr_before["curve"], "after": fr_after["curve"], "time_s": fr_after["time"]},
        "regions": one["regions"],
        "whiteness": lb,
        "input_correlation": _input_correlation(res, one["times"], sub),
        "best_feature": one["best_feature"],
        "plot_data": {"residual_time": one["time_series"], "feature": one["scatter"]},
    }
    return json_safe(result)


def write_report(result: dict[str, Any], out_dir: str | os.PathLike) -> list[str]:
    """Write the figures (PNG) and ``report.md`` of a :func:`diagnose` result into ``out_dir``.

    Figures: the residual against time (first episode, per rod), the residual against its
    best-correlated candidate feature, the free-run error before and after the added effects.
    Every file is written atomically (temporary file, then rename).  Returns the paths written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = os.path.abspath(os.fspath(out_dir))
    os.makedirs(out, exist_ok=True)
    paths: list[str] = []

    def save(fig, name: str) -> str:
        p = os.path.join(out, name)
        atomic_write(p, lambda fh: fig.savefig(fh, format="png", dpi=100), binary=True)
        plt.close(fig)
        paths.append(p)
        return name

    figs = {}
    ts = (result.get("plot_data") or {}).get("residual_time") or {}
    if ts.get("t"):
        fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True, constrained_layout=True)
        for rod, f, t in zip(ts["rods"], ts["force"], ts["torque"]):
            axes[0].plot(ts["t"], _nan(f), lw=0.8, label=rod)
            axes[1].plot(ts["t"], _nan(t), lw=0.8, label=rod)
        axes[0].set_ylabel("|force residual| (N)")
        axes[1].set_ylabel("|torque residual| (N m)")
        axes[1].set_xlabel("time (s), episode 0")
        axes[0].legend(fontsize=7, ncol=3)
        for ax in axes:
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
        fig.suptitle("one-step residual against time")
        figs["time"] = save(fig, "residual_time.png")
    sc = (result.get("plot_data") or {}).get("feature") or {}
    if sc.get("x"):
        fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
        ax.scatter(_nan(sc["x"]), _nan(sc["y"]), s=3, alpha=0.4)
        ax.set_xlabel(f"feature {sc['name']} (N or N per unit parameter)")
        ax.set_ylabel("residual row (N; torque / half-length)")
        corr = sc.get("corr")
        ax.set_title(f"residual against its best-correlated feature (r = {corr:.3f})" if corr is not None
                     else "residual against its best-correlated feature")
        ax.grid(True, alpha=0.3)
        figs["feature"] = save(fig, "residual_feature.png")
    fr = result.get("free_run") or {}
    if fr.get("time_s"):
        fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
        if result.get("added"):
            ax.semilogy(fr["time_s"], np.maximum(_nan(fr["before"]), 1e-18), label="before (no added effects)")
        ax.semilogy(fr["time_s"], np.maximum(_nan(fr["after"]), 1e-18),
                    label=f"after ({', '.join(result['added'])})" if result.get("added") else "model")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("position error (m)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        ax.set_title("free-run error, mean over rods and episodes")
        figs["free_run"] = save(fig, "free_run_error.png")

    text = _report_text(result, figs)
    p = os.path.join(out, "report.md")
    atomic_write(p, lambda fh: fh.write(text))
    paths.append(p)
    return paths


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


# ---------------------------------------------------------------------- data and rollouts
def _subset(data: Dataset, max_steps: int, H: int) -> Dataset:
    E, T = data.n_episodes, data.n_steps
    if E * T <= max_steps:
        return data
    T_use = min(T, max(H, max_steps))
    E_use = max(1, min(E, max_steps // T_use))
    return data.select(episodes=slice(0, E_use), steps=T_use)


def _mjcf_source(model: IdentifiedModel, mjcf: str | os.PathLike | None) -> str | None:
    if mjcf is not None:
        return os.fspath(mjcf)
    src = model.source_model
    if src and not str(src).startswith("preset:") and os.path.isfile(src):
        return str(src)
    return None


def _ground_geometry(model: IdentifiedModel, src: str | None) -> dict[str, Any] | None:
    for e in model.effects:
        opt = e.get("options") or {}
        if e.get("name") == "ground_contact" and {"radius", "segment", "normal", "ground_height"} <= set(opt):
            return opt
    if src is None:
        return None
    try:
        return read_contact_geometry(src, model.topology.rod_names)
    except (ValueError, OSError):
        return None


def _free_run(model: IdentifiedModel, data: Dataset, H: int) -> dict[str, Any]:
    """Per-step position error (mean over episodes and rods) of the free run, its mean over 1..H."""
    with np.errstate(all="ignore"):
        states = rollout(model, data, H)
        err = np.linalg.norm(states.pos.numpy() - data.pos[:, : H + 1], axis=-1).mean(axis=(0, 2))
    finite = bool(np.all(np.isfinite(err)))
    idx = np.unique(np.linspace(0, H, min(H + 1, _CURVE_POINTS)).round().astype(int))
    return {"error": float(err[1:].mean()) if finite else None,
            "curve": [float(v) if np.isfinite(v) else None for v in err[idx]],
            "time": (idx * data.dt).tolist()}


def _k_step(model: IdentifiedModel, data: Dataset) -> dict[str, Any]:
    """Position and quaternion error after k free steps from recorded states, for k in K_STEPS."""
    eng = engine_from_model(model)
    E, T = data.n_episodes, data.n_steps
    out: dict[str, Any] = {}
    for k in K_STEPS:
        if k > T:
            out[str(k)] = None
            continue
        pairs = [(e, t) for e in range(E) for t in range(T - k + 1)]
        pick = np.unique(np.linspace(0, len(pairs) - 1, min(len(pairs), _KSTEP_STARTS)).round().astype(int))
        ep = np.array([pairs[i][0] for i in pick])
        t0 = np.array([pairs[i][1] for i in pick])
        span = t0[:, None] + np.arange(k)
        s0 = eng.state(data.pos[ep, t0], data.quat[ep, t0], data.vel[ep, t0], data.angvel[ep, t0])
        with torch.no_grad(), np.errstate(all="ignore"):
            st = eng.rollout(s0, data.rest_length[ep[:, None], span], data.push_force[ep[:, None], span],
                             data.push_point[ep[:, None], span])
            pe = np.linalg.norm(st.pos[:, -1].numpy() - data.pos[ep, t0 + k], axis=-1)
            qe = quat_distance(st.quat[:, -1].numpy(), data.quat[ep, t0 + k])
        out[str(k)] = {"pos": _finite(pe.mean()), "quat": _finite(qe.mean()), "starts": len(pick)}
    return out


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
        win = replace(data, pos=data.pos[eps, a: t1 + 1], quat=data.quat[eps, a: t1 + 1],
                      vel=data.vel[eps, a: t1 + 1], angvel=data.angvel[eps, a: t1 + 1],
                      command=data.command[eps, a:t1], rest_length=data.rest_length[eps, a:t1],
                      push_force=data.push_force[eps, a:t1], push_point=data.push_point[eps, a:t1])
        yield win, eps, a + first


# ---------------------------------------------------------------------- the one-step pass
class _Accumulator:
    """Normal equations and moment sums of one candidate's columns ``X`` against the residual rows
    ``y`` and the base model's equation columns ``B``, added rod by rod (each rod's rows touch only
    its own columns: the sums stay small)."""

    def __init__(self, eff: Any, names: list[str], n_base: int) -> None:
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
        self.XX, self.Xy, self.BX = np.zeros((P, P)), np.zeros(P), np.zeros((self.n_base, P))
        self.sx, self.sxx = np.zeros(P), np.zeros(P)

    def add(self, X: np.ndarray, xi: np.ndarray, y: np.ndarray, B: np.ndarray, bi: np.ndarray) -> None:
        """One rod's rows: ``X`` (n, w) the candidate's columns ``xi``, ``B`` (n, nb) the base's ``bi``."""
        self.XX[np.ix_(xi, xi)] += X.T @ X
        self.Xy[xi] += X.T @ y
        self.BX[np.ix_(bi, xi)] += B.T @ X
        self.sx[xi] += X.sum(0)
        self.sxx[xi] += (X * X).sum(0)


def _explained(G: np.ndarray, b: np.ndarray) -> float:
    """``b' G⁺ b``: the sum of squares a least-squares fit on the columns behind ``G = X'X``,
    ``b = X'y`` explains (columns equilibrated; directions below 1e-12 of the largest dropped)."""
    d = np.sqrt(np.clip(np.diag(G), 0.0, None))
    live = d > 0
    if not live.any():
        return 0.0
    Gn = G[np.ix_(live, live)] / np.outer(d[live], d[live])
    bn = b[live] / d[live]
    w, V = np.linalg.eigh(Gn)
    keep = w > w.max() * 1e-12
    z = V[:, keep].T @ bn
    return float(np.sum(z * z / w[keep]))


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


def _half_lengths(model: IdentifiedModel) -> np.ndarray:
    return np.array([max(r.length / 2.0, 1e-6) for r in model.topology.rods])


def _one_step(model: IdentifiedModel, data: Dataset, candidates: list, geometry: dict | None,
              chunk_steps: int) -> dict[str, Any]:
    topo = model.topology
    R, S = topo.n_rods, topo.n_springs
    scheme = model.metrics.get("scheme") or ("central" if model.integrator == "rk4" else "forward")
    first = 1 if scheme == "central" else 0
    eng = engine_from_model(model)
    p = eng.params
    half = torch.as_tensor(_half_lengths(model), dtype=torch.float64)
    E, T = data.n_episodes, data.n_steps
    Tn = T - first
    res = np.full((E, Tn, R, 6), np.nan)
    ref = np.zeros((E, Tn, R, 6))  # the recorded inertial wrench, for the relative RMS
    regions = {k: np.zeros((E, Tn, R), dtype=bool) for k in ("near_ground", "pushed")}
    short_all = np.zeros((E, Tn, S), dtype=bool)
    speed = np.zeros((E, Tn, R))
    # the base model's columns (its joint effects' too), refitted beside each candidate
    joint = [e for e in effects_from_model(model) if e.stage == "joint"]
    layout = ParameterLayout.for_topology(topo, "multiple", joint)
    rcols = RodColumns.build(topo, layout)
    nb = layout.n_full
    base_idx = [np.flatnonzero(rcols.full[i] >= 0) for i in range(R)]  # local columns used by rod i
    implicit_dt = data.dt if model.integrator == "implicit" else None
    GBB, bB = np.zeros((nb, nb)), np.zeros(nb)
    accs = [_Accumulator(c, c.param_names(topo.rod_names, topo.spring_names), nb) for c in candidates]
    sy = syy = 0.0
    n_rows = 0
    sample_rows: list[np.ndarray] = []
    total = E * Tn
    stride = max(1, total // _SAMPLE_INSTANTS)

    for win, eps, t_first in _windows(data, chunk_steps, first):
        ch, _ = next(iter_chunks(win, 10**12, scheme))
        n_t = ch.pos.shape[0] // len(eps)
        state = RodState(ch.pos, ch.quat, ch.vel, ch.angvel)
        point = (torch.as_tensor(win.push_point[:, :n_t].reshape(-1, R, 3), dtype=torch.float64)
                 if scheme == "forward" else None)
        with torch.no_grad():
            terms = eng.dynamics(state, ch.rest, ch.push_force, point)
            rot = terms.ctx.rot
            rf = p.mass[:, None] * (ch.acc - terms.lin_acc)
            rtb = p.inertia * (ch.alpha_body - terms.ang_acc_body)
            if scheme == "central":  # the engine saw the push at the COM: its torque is the recorded one
                rtb = rtb - p.control_scale * ch.push_torque_body
            ref_f, ref_t = inertial_wrench(p.mass, p.inertia, p.gravity, ch.acc, ch.alpha_body, ch.angvel_body)
            y = torch.cat((rf, matrix_apply(rot, rtb) / half[:, None]), -1)  # (N, R, 6) world, N
            ctx = terms.ctx._replace(base_lin_acc=terms.lin_acc, base_ang_acc_body=terms.ang_acc_body,
                                     recorded_lin_acc=ch.acc, recorded_ang_acc_body=ch.alpha_body)
            # regions
            short = terms.ctx.geometry.length < ch.rest  # (N, S)
            near = _near_ground(state, rot, geometry) if geometry is not None else None
            Bt = _base_rows(equation_rows(topo, rcols, ch, p.gravity, implicit_dt, joint), rot, half)
            if ch.row_weight is not None:  # the central scheme leaves out rows across a push switch
                y = y * ch.row_weight[..., None]
            cand_X = []
            for acc in accs:
                blocks = _candidate_blocks(acc.eff, state, ctx, topo, half)
                acc.allocate(blocks)
                # a model far from physical (negative inertia) can make a feature non-finite: count, zero
                acc.nonfinite += sum(int((~torch.isfinite(X)).sum()) for X, _ in blocks)
                acc.entries += sum(X.numel() for X, _ in blocks)
                blocks = [(torch.nan_to_num(X, nan=0.0, posinf=0.0, neginf=0.0), xi) for X, xi in blocks]
                if ch.row_weight is not None:
                    blocks = [(X * ch.row_weight[:, i, None, None], xi) for i, (X, xi) in enumerate(blocks)]
                cand_X.append(blocks)
        ts = np.arange(t_first, t_first + n_t) - first
        blk = (eps[:, None], ts[None, :])
        res[blk] = torch.cat((rf, rtb), -1).reshape(len(eps), n_t, R, 6).numpy()
        ref[blk] = torch.cat((ref_f, ref_t), -1).reshape(len(eps), n_t, R, 6).numpy()
        short_all[blk] = short.reshape(len(eps), n_t, S).numpy()
        regions["pushed"][blk] = (ch.push_force.norm(dim=-1) > 0).reshape(len(eps), n_t, R).numpy()
        if near is not None:
            regions["near_ground"][blk] = near.reshape(len(eps), n_t, R).numpy()
        speed[blk] = ch.vel.norm(dim=-1).reshape(len(eps), n_t, R).numpy()
        yv = y.reshape(-1).numpy()
        sy += float(yv.sum())
        syy += float(yv @ yv)
        n_rows += yv.size
        # instants kept for the scatter plot: global flat index (e * Tn + t) on the stride
        flat = (eps[:, None] * Tn + ts[None, :]).reshape(-1)
        keep = np.flatnonzero(flat % stride == 0)
        rows_keep = (keep[:, None] * (R * 6) + np.arange(R * 6)).reshape(-1)
        sample_rows.append(yv[rows_keep])
        yr = y.numpy()
        for i in range(R):
            yi = yr[:, i].reshape(-1)
            bi = base_idx[i]
            Bi = Bt[:, i][..., torch.as_tensor(bi)].reshape(-1, len(bi)).numpy()
            fi = rcols.full[i, bi]
            GBB[np.ix_(fi, fi)] += Bi.T @ Bi
            bB[fi] += Bi.T @ yi
            for acc, blocks in zip(accs, cand_X):
                X, xi = blocks[i]
                acc.add(X.reshape(-1, len(xi)).numpy(), xi, yi, Bi, fi)
        for acc, blocks in zip(accs, cand_X):  # the sampled instants' rows, dense, for the scatter plot
            Xs = np.zeros((len(keep), R, 6, acc.P))
            for i, (X, xi) in enumerate(blocks):
                Xs[:, i][..., xi] = X[torch.as_tensor(keep)].numpy()
            acc.sample.append(Xs.reshape(-1, acc.P))

    valid = ~np.isnan(res[..., 0, 0])  # (E, Tn)
    r, rf_ = res[valid], ref[valid]  # (n, R, 6)
    rms = lambda a, ax=0: np.sqrt(np.mean(a * a, axis=ax))
    force_rms, torque_rms = rms(r[..., :3], (0, 1)), rms(r[..., 3:], (0, 1))
    rel = {"force": _ratio(np.sqrt((force_rms ** 2).mean()), rms(rf_[..., :3], (0, 1, 2))),
           "torque": _ratio(np.sqrt((torque_rms ** 2).mean()), rms(rf_[..., 3:], (0, 1, 2)))}
    per = rms(r, 0)  # (R, 6)
    per_rod = [{"rod": name, "force_rms": per[i, :3].tolist(), "torque_rms": per[i, 3:].tolist(),
                "force_rms_norm": float(np.sqrt((per[i, :3] ** 2).sum())),
                "torque_rms_norm": float(np.sqrt((per[i, 3:] ** 2).sum()))}
               for i, name in enumerate(topo.rod_names)]
    worst = int(np.argmax([x["force_rms_norm"] + x["torque_rms_norm"] / half[i].item()
                           for i, x in enumerate(per_rod)]))

    # regions: residual norm in each region against the rest (rod-instants; spring ends for the springs)
    fnorm = np.sqrt((res[..., :3] ** 2).sum(-1))
    tnorm = np.sqrt((res[..., 3:] ** 2).sum(-1))
    vr = np.broadcast_to(valid[..., None], fnorm.shape)
    fast = speed >= np.quantile(speed[valid], FAST_QUANTILE)
    cables = np.asarray(topo.pull_only, dtype=bool)
    springs = np.flatnonzero(cables) if cables.any() else np.arange(S)
    js, es = np.nonzero(topo.endpoint_rods[springs] >= 0)
    end_rod, end_spring = topo.endpoint_rods[springs][js, es], springs[js]
    masks = {
        "near_ground": None if geometry is None else (regions["near_ground"], fnorm, tnorm, vr),
        "slack": (short_all[..., end_spring], fnorm[..., end_rod], tnorm[..., end_rod], vr[..., end_rod]),
        "fast": (fast, fnorm, tnorm, vr),
        "pushed": (regions["pushed"], fnorm, tnorm, vr),
    }
    descr = {"near_ground": f"a rod's capsule end within {NEAR_GROUND_M:g} m of the ground plane (rod-instants)",
             "slack": ("a cable shorter than its rest length, i.e. slack (the rods at its ends, per cable end)"
                       if cables.any() else "a spring shorter than its rest length: slack if it were a cable "
                       "(the rods at its ends, per spring end)"),
             "fast": f"rod speed in the top {100 * (1 - FAST_QUANTILE):g} % of rod-instants",
             "pushed": "a push acts on the rod (rod-instants)"}
    reg_out: dict[str, Any] = {}
    for k, spec in masks.items():
        if spec is None:
            reg_out[k] = {"description": descr[k], "available": False,
                          "reason": "no ground geometry (a ground_contact effect or the plant's MJCF)"}
            continue
        m, fv, tv, ok = spec
        inside, outside = m & ok, ~m & ok
        f_in, f_out = _rms_or_none(fv[inside]), _rms_or_none(fv[outside])
        t_in, t_out = _rms_or_none(tv[inside]), _rms_or_none(tv[outside])
        reg_out[k] = {"description": descr[k], "available": True,
                      "fraction": float(inside.sum() / max(ok.sum(), 1)),
                      "force_rms_in": f_in, "force_rms_out": f_out, "torque_rms_in": t_in, "torque_rms_out": t_out,
                      "force_ratio": _ratio(f_in, f_out), "torque_ratio": _ratio(t_in, t_out)}

    # candidates: score and feature correlations
    sample_y = np.concatenate(sample_rows)
    cands, best = [], None
    my, vy = sy / max(n_rows, 1), syy / max(n_rows, 1) - (sy / max(n_rows, 1)) ** 2
    Z = _mass_total_held(nb, np.array([layout.m(i) for i in range(R)]))
    GBB, bB = Z.T @ GBB @ Z, Z.T @ bB
    rss_base = max(syy - _explained(GBB, bB), 0.0) if accs else None
    for acc in accs:
        P = acc.P
        BX = Z.T @ acc.BX
        score = alone = unexplained = None
        if syy > 0:
            alone = float(np.clip(_explained(acc.XX, acc.Xy) / syy, 0.0, 1.0))
            G = np.block([[GBB, BX], [BX.T, acc.XX]])
            rss = max(syy - _explained(G, np.concatenate((bB, acc.Xy))), 0.0)
            if rss_base > 0:
                unexplained = float(np.clip(rss / rss_base, 0.0, 1.0))
                score = 1.0 - unexplained
        note = None
        if acc.nonfinite > 0.01 * max(acc.entries, 1):
            note = (f"features not finite on {acc.nonfinite / acc.entries:.0%} of the entries under this model's "
                    f"parameters (a negative inertia?): not scored")
            score = unexplained = alone = None
        mx, vx = acc.sx / n_rows, acc.sxx / n_rows - (acc.sx / n_rows) ** 2
        cov = acc.Xy / n_rows - mx * my
        with np.errstate(all="ignore"):
            corr = np.where((vx > 0) & (vy > 0), cov / np.sqrt(np.clip(vx, 1e-300, None) * max(vy, 1e-300)), 0.0)
        j = int(np.argmax(np.abs(corr))) if P else 0
        names = acc.names[:P]
        top = np.argsort(-np.abs(corr))[:3]
        cands.append({"name": acc.eff.name, "score": score, "unexplained": unexplained, "score_alone": alone,
                      "n_params": int(P), "description": acc.eff.description,
                      "nonfinite_features": int(acc.nonfinite), "note": note,
                      "max_abs_corr": _finite(abs(corr[j])) if P else None,
                      "best_feature": names[j] if P else None,
                      "top_features": [{"feature": names[i], "corr": _finite(corr[i])} for i in top]})
        if P and (best is None or abs(corr[j]) > abs(best[0])):
            best = (float(corr[j]), acc, j, names[j])

    scatter, best_feature = {}, None
    if best is not None and np.isfinite(best[0]):
        corr, acc, j, name = best
        x = np.concatenate([s[:, j] for s in acc.sample])
        nz = np.flatnonzero(x != 0)
        pick = nz[np.unique(np.linspace(0, len(nz) - 1, min(len(nz), _SCATTER_POINTS)).round().astype(int))] \
            if len(nz) else nz
        scatter = {"name": name, "corr": corr, "x": x[pick].tolist(), "y": sample_y[pick].tolist()}
        best_feature = {"candidate": acc.eff.name, "feature": name, "corr": corr}

    # residual against time (episode 0, per rod), subsampled
    ti = np.unique(np.linspace(0, Tn - 1, min(Tn, _TIME_POINTS)).round().astype(int))
    time_series = {"t": ((ti + first) * data.dt).tolist(), "rods": list(topo.rod_names),
                   "force": fnorm[0, ti].T.tolist(), "torque": tnorm[0, ti].T.tolist()}
    return {"res": res, "times": np.arange(first, T), "scheme": scheme, "rows": int(valid.sum()),
            "force_rms": force_rms.tolist(), "torque_rms": torque_rms.tolist(), "relative": rel,
            "per_rod": per_rod, "worst_rod": topo.rod_names[worst], "regions": reg_out,
            "candidates": cands, "best_feature": best_feature, "scatter": scatter, "time_series": time_series,
            "base_refit": None if rss_base is None or syy <= 0 else float(np.clip(1 - rss_base / syy, 0, 1))}


def _near_ground(state: RodState, rot: torch.Tensor, geo: dict[str, Any]) -> torch.Tensor:
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=float), dtype=state.pos.dtype)
    radius, seg, n, h = t(geo["radius"]), t(geo["segment"]), t(geo["normal"]), float(geo["ground_height"])
    centre = state.pos.unsqueeze(-2) + matrix_apply(rot.unsqueeze(-3), seg)  # (N, R, 2, 3)
    gap = (centre * n).sum(-1) - h - radius.unsqueeze(-1)
    return (gap < NEAR_GROUND_M).any(-1)


def _candidate_blocks(eff: Any, state: RodState, ctx: Any, topo: Any,
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


# ---------------------------------------------------------------------- statistics
def _whiteness(res: np.ndarray, rod_names: tuple[str, ...]) -> dict[str, Any]:
    """Ljung-Box per rod and dof, the episodes' Q summed (dof summed)."""
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
            row.append({"dof": DOFS[k], "Q": _finite(q), "df": dof, "p": pv})
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


def _input_correlation(res: np.ndarray, times: np.ndarray, data: Dataset) -> dict[str, Any]:
    """Largest |Pearson correlation| of the residual series (per rod and dof) with each input."""
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
        c = _corr_matrix(y[:, i * 6: (i + 1) * 6], push[:, :, i].reshape(-1, 3))
        if c is None:
            continue
        a, b = np.unravel_index(int(np.nanargmax(np.abs(c))), c.shape)
        if best is None or abs(c[a, b]) > abs(best["corr"]):
            best = {"corr": float(c[a, b]), "rod": data.rod_names[i], "dof": DOFS[a], "input": f"push_force.{'xyz'[b]}"}
    out["push_force"] = best or {"corr": None, "reason": "no pushes on any rod"}
    return out


def _corr_matrix(y: np.ndarray, x: np.ndarray) -> np.ndarray | None:
    """Pearson correlations (y columns x x columns); 0 where a column is constant (to rounding)."""
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
    c = _corr_matrix(y, x)
    if c is None:
        return {"corr": None, "reason": "the input does not vary"}
    a, b = np.unravel_index(int(np.argmax(np.abs(c))), c.shape)
    return {"corr": float(c[a, b]), "rod": rod_names[a // 6], "dof": DOFS[a % 6], "input": names[b]}


# ---------------------------------------------------------------------- report
def _report_text(r: dict[str, Any], figs: dict[str, str]) -> str:
    f = lambda v, spec=".3g": "n/a" if v is None else format(v, spec)
    L = ["# Diagnosis of the identified model", ""]
    verdict = "explained" if r["explained"] else "NOT explained"
    why = {"rounding": "the one-step residual is at rounding level", "white": "the residual is white (Ljung-Box)",
           "improved": "the added effects cut the free-run error at least 5x"}
    L.append(f"**Verdict: the residual is {verdict}**"
             + (f" ({'; '.join(why[x] for x in r['explained_by'])})." if r["explained_by"] else
                ": it is structured and the model's effects do not account for it."))
    L.append("")
    L.append(f"Rule: {r['explained_rule']}.")
    L.append("")
    d = r["data"]
    L.append(f"Data: {d['episodes']} episodes x {d['steps_per_episode']} steps (dt {d['dt']:g} s), "
             f"{d['instants']} instants analysed; accelerations by the {d['scheme']} difference; "
             f"integrator {d['integrator']}.")
    L += ["", "## Free-run error", "", f"Metric: {r['metric']}.", ""]
    added = ", ".join(r["added"]) or "none"
    L.append(f"- before (no added effects): **{f(r['error_before'])} m**")
    L.append(f"- after (added: {added}): **{f(r['error_after'])} m**")
    if r["error_before"] and r["error_after"] is not None and r["added"]:
        L.append(f"- ratio after / before: {r['error_after'] / r['error_before']:.3g}")
    if "free_run" in figs:
        L += ["", f"![free-run error]({figs['free_run']})"]
    L += ["", "k-step position error (m) of the model as it is, from recorded states:", ""]
    L.append("| k | position error (m) | quaternion error |")
    L.append("|---|---|---|")
    for k, v in r["k_step"]["after"].items():
        L.append(f"| {k} | {f(v and v['pos'])} | {f(v and v['quat'])} |")
    os_ = r["one_step"]
    L += ["", "## One-step residual", "", f"Definition: {os_['definition']}.", "",
          (f"RMS over all rods: force {', '.join(f(x) for x in os_['force_rms'])} N (x, y, z), "
          f"torque {', '.join(f(x) for x in os_['torque_rms'])} N m (rod frame x, y, z); relative to the recorded "
          f"wrench: force {f(os_['relative']['force'])}, torque {f(os_['relative']['torque'])}."), "",
          "| rod | force RMS x, y, z (N) | torque RMS x, y, z (N m) |", "|---|---|---|"]
    for p in os_["per_rod"]:
        L.append(f"| {p['rod']} | {', '.join(f(x) for x in p['force_rms'])} | {', '.join(f(x) for x in p['torque_rms'])} |")
    L += ["", f"Worst rod: {os_['worst_rod']}."]
    if "time" in figs:
        L += ["", f"![residual against time]({figs['time']})"]
    L += ["", "## Where: by region of state", "",
          "| region | share | force RMS in / out (N) | torque RMS in / out (N m) |", "|---|---|---|---|"]
    for k, v in r["regions"].items():
        if not v.get("available"):
            L.append(f"| {v['description']} | n/a | {v.get('reason', '')} | |")
            continue
        L.append(f"| {v['description']} | {v['fraction']:.1%} | {f(v['force_rms_in'])} / {f(v['force_rms_out'])} | "
                 f"{f(v['torque_rms_in'])} / {f(v['torque_rms_out'])} |")
    w = r["whiteness"]
    L += ["", "## Statistics", "",
          (f"Whiteness: {w['test']}: {'white' if w['white'] else 'not white'}; smallest p-value {f(w['min_p'])}, "
          f"{f(w['fraction_rejected'], '.0%') if w['fraction_rejected'] is not None else 'n/a'} of the rod/dof series "
          f"reject at 1 %, median Q / dof {f(w['median_Q_per_dof'])} (1 for white noise).")]
    ic = r["input_correlation"]
    for k, v in ic.items():
        if v.get("corr") is None:
            L.append(f"- correlation with {k}: n/a ({v.get('reason', '')})")
        else:
            L.append(f"- largest correlation with {k}: {v['corr']:+.3f} (rod {v['rod']} {v['dof']} with {v['input']})")
    L += ["", "## Candidate effects", "", f"Score: {r['score_rule']}.", "",
          "| effect | score | unexplained | alone | parameters | best feature (corr) |", "|---|---|---|---|---|---|"]
    for c in r["candidates"]:
        bf = f"{c['best_feature']} ({f(c['max_abs_corr'])})" if c["best_feature"] else "n/a"
        if c.get("note"):
            bf += f"; {c['note']}"
        L.append(f"| {c['name']} | {f(c['score'], '.4f')} | {f(c['unexplained'])} | {f(c['score_alone'])} | "
                 f"{c['n_params']} | {bf} |")
    for s in r["skipped"]:
        L.append(f"| {s['name']} | skipped | | | | {s['reason']} |")
    if r["candidates"]:
        top = r["candidates"][0]
        L += ["", (f"The best candidate is **{top['name']}**: adding it would remove "
                  f"{f(top['score'], '.1%') if top['score'] is not None else 'n/a'} of the residual.")]
    if "feature" in figs:
        L += ["", f"![residual against its best-correlated feature]({figs['feature']})"]
    return "\n".join(L) + "\n"


# ---------------------------------------------------------------------- helpers
def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _ratio(a: Any, b: Any) -> float | None:
    a, b = _finite(a), _finite(b)
    if a is None or b is None or b <= 0:
        return None
    return a / b


def _rms_or_none(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x * x))) if x.size else None


def _nan(v: list) -> np.ndarray:
    return np.array([np.nan if x is None else x for x in v], dtype=float)
