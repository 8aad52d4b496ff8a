"""Checks that keep a fit honest: enough data for its error bars, physically possible parameters.

* :func:`check_enough_data` -- the residual degrees of freedom of a fit (equations minus free
  parameters; weak-form windows overlap, so their rows count for ``stride / window`` of a row).
  With none left the fit is refused with one line saying about how much more data it needs; with
  fewer than there are parameters its standard errors are marked *not estimable* (NaN, written
  as ``null``), never printed as ``± 1e-9`` on an exactly interpolated fit.
* :func:`constrain_inertias` -- a non-positive moment of inertia is held at a small positive
  floor and the fit is solved again (a constrained fit), with a warning that says so.
* :func:`physical_warnings` -- masses, inertias, stiffnesses positive, damping non-negative,
  each rod's inertia triangle inequality: every violation becomes one warning line, which the fit
  prints and stores under ``metrics["warnings"]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from identified.fit.derivatives import weak_stride
from identified.fit.noise import has_noise
from identified.fit.regression import IdentifiabilityError, Solution
from identified.model import com_and_tensor, inertia_tensor

__all__ = [
    "ADAM_TOLERANCE",
    "INERTIA_FLOOR",
    "MIN_DOF_PER_PARAMETER",
    "InsufficientDataError",
    "adam_convergence",
    "apply_checks",
    "check_enough_data",
    "constrain_inertias",
    "overlap_factor",
    "physical_warnings",
    "refresh_physics",
    "residual_dof",
    "widen_for_overlap",
]

#: residual degrees of freedom per free parameter below which standard errors are not estimable
MIN_DOF_PER_PARAMETER = 1.0
#: a moment of inertia that comes out non-positive is held at this fraction of its rod's largest one
INERTIA_FLOOR = 1e-3
AXES = ("x", "y", "z (axial)")


class InsufficientDataError(IdentifiabilityError):
    """Too few equations for the free parameters (no residual degrees of freedom)."""


def overlap_factor(weak_window: int) -> float:
    """How much overlapping weak-form windows inflate the variance of a sum of their rows.

    Windows of ``w`` steps advance by a quarter window (:func:`identified.fit.derivatives.weak_stride`)
    and weigh the steps with a Hann bump ``phi``: rows ``k`` windows apart share noise with
    correlation ``rho_k = sum phi(t) phi(t + k stride) / sum phi^2``, so a sum of rows has
    ``1 + 2 sum_k rho_k`` times the variance of independent ones (2.68 for the default window).
    """
    if weak_window <= 1:
        return 1.0
    w, stride = int(weak_window), weak_stride(int(weak_window))
    phi = np.hanning(w + 2)[1:-1]
    norm = float(phi @ phi)
    return 1.0 + 2.0 * sum(float(phi[: w - k] @ phi[k:]) / norm for k in range(stride, w, stride))


def residual_dof(rows: int, free: int, weak_window: int = 0) -> float:
    """Equations minus free parameters, the rows of overlapping weak-form windows counted as the
    independent rows they are worth (``rows / overlap_factor``)."""
    return rows / overlap_factor(weak_window) - free


def widen_for_overlap(sol: Solution, weak_window: int) -> Solution:
    """The iid covariance (fewer episodes than the cluster jackknife needs, too short to cut into
    enough blocks: :func:`identified.fit.identify.run_blocks`) treats overlapping
    weak-form rows as independent: scale it by :func:`overlap_factor` (measured on 3-episode noisy
    fits: z-scores against the truth with an RMS of 1.5-1.7 without, ~1 with)."""
    f = overlap_factor(weak_window)
    if sol.cov is not None and sol.covariance.startswith("iid") and f > 1:
        sol.cov = sol.cov * f
        sol.covariance = sol.covariance.replace("the overlap of weak-form windows is ignored",
                                                f"variance x {f:.3g} for the overlap of weak-form windows")
    return sol


def check_enough_data(sol: Solution, steps: int, weak_window: int = 0, solver: str = "lstsq") -> str | None:
    """Refuse a fit without residual degrees of freedom; say when its error bars are not estimable.

    ``steps``: the steps of data behind ``sol.rows``.  Raises :class:`InsufficientDataError`
    (one line: equations, parameters, about how many more steps) when the effective equations do
    not exceed the free parameters -- or, for a solver without error bars (``adam``), when they
    are fewer than twice the parameters.  Returns a warning line when the standard errors are not
    estimable (fewer residual degrees of freedom than parameters), else ``None``.
    """
    free = max(int(sol.free), 1)
    refuse_too_few_equations(sol.rows, free, steps, weak_window, error_bars=sol.cov is not None)
    dof = residual_dof(sol.rows, free, weak_window)
    effective = dof + free
    need = (1.0 + MIN_DOF_PER_PARAMETER) * free
    if sol.cov is not None and dof < MIN_DOF_PER_PARAMETER * free:
        return (f"standard errors not estimable: {dof:.0f} residual degrees of freedom for {free} "
                f"parameters (record at least {math.ceil(need / (effective / max(steps, 1)))} steps)")
    return None


def refuse_too_few_equations(rows: int, free: int, steps: int, weak_window: int = 0,
                             error_bars: bool = True) -> None:
    """Raise :class:`InsufficientDataError` (one line: equations, parameters, about how many more
    steps) when ``rows`` effective equations do not exceed ``free`` parameters -- or, for a solver
    without error bars (``error_bars=False``), when they are fewer than twice the parameters.
    Checked before a rank-deficiency is reported: too few rows is the cause to name."""
    free = max(int(free), 1)
    dof = residual_dof(rows, free, weak_window)
    effective = dof + free
    need = (1.0 + MIN_DOF_PER_PARAMETER) * free
    if dof <= 0 or (not error_bars and effective < need):
        per_step = effective / max(steps, 1)
        more = math.ceil((need - effective) / per_step) if per_step > 0 else None
        what = (f"about {more} more steps (more --episodes or --steps)" if more is not None
                else "longer episodes")
        raise InsufficientDataError(
            f"{rows} equations for {free} free parameters ({dof:.0f} residual degrees of freedom"
            + (", weak-form windows overlapping" if weak_window > 1 else "")
            + f"): too few to estimate the parameters or their error bars; record {what}"
        )


def constrain_inertias(
    sol: Solution,
    resolve: Callable[[dict[int, float]], Solution],
    inertia_index: Callable[[int, int], int],
    n_rods: int,
    rod_names: list[str] | tuple[str, ...],
    fixed: dict[int, float],
    max_rounds: int = 6,
) -> tuple[Solution, list[str], list[tuple[int, int]]]:
    """Hold every non-positive moment of inertia at a positive floor and solve again.

    ``resolve(fixed)`` solves the same problem with ``fixed`` full-vector entries pinned;
    ``inertia_index(rod, axis)`` is the entry of a rod's inertia about an axis.  Returns the
    solution, one warning per held inertia, and the (rod, axis) of each held one (its error bar
    is not estimable).
    """
    pinned: dict[int, float] = {}
    held: list[tuple[int, int]] = []
    notes: list[str] = []
    for _ in range(max_rounds):
        th = sol.theta
        new = {}
        for i in range(n_rods):
            idx = [inertia_index(i, a) for a in range(3)]
            top = max(max(float(th[j]) for j in idx), 0.0)
            for a, j in enumerate(idx):
                if j not in pinned and j not in fixed and not th[j] > 0:
                    floor = INERTIA_FLOOR * top if top > 0 else 1e-9
                    new[j] = floor
                    held.append((i, a))
                    notes.append(f"{rod_names[i]}: inertia about {AXES[a]} came out {th[j]:.3g} kg m^2 "
                                 f"(not positive; the data do not determine it): held at {floor:.3g} "
                                 "(constrained fit)")
        if not new:
            break
        pinned.update(new)
        sol = resolve({**fixed, **pinned})
    return sol, notes, held


def constrain_rigid_bodies(sol: Solution, resolve: Callable[[dict[int, float]], Solution], layout: Any,
                           fixed: dict[int, float]) -> tuple[Solution, list[str], list[tuple[int, int]]]:
    """Make every rod's ten fitted inertial parameters a rigid body's (its pseudo-inertia positive
    definite, :func:`pseudo_inertia`), in two steps per rod that is not, each solved again:

    1. its products of inertia held at 0 and its smallest moment about the centre of mass, where
       it is below the least the triangle inequality allows, held there (a rod whose cables all
       meet its axis leaves the axial moment to the data's noise): its centre of mass is kept;
    2. if it is still none, the diagonal model: its first moment held at 0 too.

    ``fixed`` is updated with what is held. Returns the solution, one warning per held rod and the
    (rod, body axis) of every moment held at a floor (its error bar is not estimable).
    """
    notes: list[str] = []
    held: list[tuple[int, int]] = []
    level: dict[int, int] = {}
    for _ in range(4):
        changed = False
        for i, name in enumerate(layout.rod_names):
            m, c, J_c = _rigid_body(sol.theta, layout, i)
            if m > 0 and np.linalg.eigvalsh(pseudo_inertia(m, c, J_c))[0] > 0:
                continue
            step = level.get(i, 0) + 1
            if step > 2:
                continue
            level[i], changed = step, True
            if step == 1:
                fixed.update({int(layout.product(i, k)): 0.0 for k in range(3)})
                d = np.diag(J_c)
                floor = INERTIA_FLOOR * max(float(d.max()), 1e-12)
                a = int(np.argmin(d))
                b, e = [k for k in range(3) if k != a]
                least = abs(d[b] - d[e]) + 2 * floor  # the smallest moment the triangle inequality allows
                if not d[a] >= least:
                    # J_c,aa = J_o,aa - M (|c|^2 - c_a^2): hold J_o,aa where J_c,aa is that least moment
                    fixed[int(layout.inertia(i, a))] = float(m * (c @ c - c[a] ** 2) + least)
                    held.append((i, a))
                notes.append(f"{name}: the fitted inertia tensor is no rigid body's (the data do not determine it): "
                             f"its products held at 0 and its smallest moment (about {'xyz'[a]}) at the least a rigid "
                             "body allows (constrained fit)")
            else:
                fixed.update({int(layout.first_moment(i, k)): 0.0 for k in range(3)})
                notes.append(f"{name}: the fitted centre of mass ({', '.join(f'{1e3 * v:.3g}' for v in c)}) mm is no "
                             "rigid body's either: its frame is taken at the centre of mass along the principal "
                             "axes (constrained fit)")
        if not changed:
            break
        sol = resolve(dict(fixed))
    return sol, notes, held


def _rigid_body(theta: np.ndarray, layout: Any, i: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Rod ``i``'s mass, centre of mass (3,) and inertia tensor about it (3, 3) from the ten fitted
    parameters (:func:`identified.model.com_and_tensor`; a non-positive mass: the frame's origin)."""
    x = np.asarray(theta)[layout.inertial(i)]
    m = float(x[0])
    c, J_c = com_and_tensor(x if m > 0 else np.concatenate([[1.0], x[1:4], np.zeros(3), x[7:10]]))
    return m, c, J_c


def physical_warnings(
    rod_names: list[str] | tuple[str, ...],
    spring_names: list[str] | tuple[str, ...],
    mass: np.ndarray,
    inertia: np.ndarray,
    stiffness: np.ndarray,
    damping: np.ndarray,
    inertia_stderr: np.ndarray | None = None,
) -> list[str]:
    """One line per violated physical constraint (positive M, I, K; c >= 0; I triangle inequality).

    ``inertia`` holds each rod's principal moments about its centre of mass (the diagonal model's
    moments are principal by assumption): a positive mass, positive principal moments and their
    triangle inequalities are together the full physical consistency of a rigid body's ten
    inertial parameters, the positive definiteness of its pseudo-inertia matrix
    (:func:`pseudo_inertia`; Wensing, Kim & Slotine 2017).

    A thin rod's transverse moments are nearly equal and its axial one small, so the triangle
    inequality is tight: with ``inertia_stderr`` it is reported only when violated by more than
    two standard errors of the difference (a violation within the error bars is not evidence).
    """
    out: list[str] = []
    for i, name in enumerate(rod_names):
        if not mass[i] > 0:
            out.append(f"{name}: mass {mass[i]:.4g} kg is not positive")
        I = np.asarray(inertia[i], dtype=float)
        for a in range(3):
            if not I[a] > 0:
                out.append(f"{name}: inertia about {AXES[a]} {I[a]:.4g} kg m^2 is not positive")
        if np.all(I > 0):
            for a in range(3):
                others = I.sum() - I[a]
                # a principal moment cannot exceed the sum of the other two
                se = None if inertia_stderr is None else np.asarray(inertia_stderr[i], dtype=float)
                margin = 0.0 if se is None else 2.0 * float(np.sqrt(np.nansum(se**2)))
                if I[a] - others > max(margin, 1e-6 * others):
                    out.append(f"{name}: inertia about {AXES[a]} {I[a]:.4g} kg m^2 exceeds the sum of the "
                               f"other two ({others:.4g}): no rigid body has these moments")
    for j, name in enumerate(spring_names):
        if not stiffness[j] > 0:
            out.append(f"{name}: stiffness {stiffness[j]:.4g} N/m is not positive")
        if not damping[j] >= 0:
            out.append(f"{name}: damping {damping[j]:.4g} N s/m is negative")
    return out


def pseudo_inertia(mass: float, com: np.ndarray, inertia_com: np.ndarray) -> np.ndarray:
    """(4, 4) the pseudo-inertia matrix ``[[Σ, M c], [M cᵀ, M]]`` of a rigid body about its frame's
    origin, ``Σ = tr(J_o)/2 E - J_o`` (the second moment of its mass distribution) with ``J_o``
    the inertia about the origin from ``inertia_com`` (3, 3) about the centre of mass ``com`` (3,);
    positive definite exactly when some rigid body of positive density has these parameters."""
    c = np.asarray(com, dtype=float)
    J_o = np.asarray(inertia_com, dtype=float) + mass * (c @ c * np.eye(3) - np.outer(c, c))
    P = np.zeros((4, 4))
    P[:3, :3] = 0.5 * np.trace(J_o) * np.eye(3) - J_o
    P[:3, 3] = P[3, :3] = mass * c
    P[3, 3] = mass
    return P


def apply_checks(model, sol: Solution, not_estimable: str | None, held: list[tuple[int, int]],
                 notes: list[str], weak_window: int = 0) -> list[str]:
    """Mark error bars that cannot be estimated (NaN), record the residual degrees of freedom and
    every warning (``notes`` and the physical checks) in ``model.metrics``; returns the warnings."""
    warnings = list(notes)
    if not_estimable:
        warnings.insert(0, not_estimable)
        model.stderr = {k: np.full(np.shape(v), np.nan) for k, v in model.stderr.items()}
        for e in model.effects:  # the joint effects' error bars came from the same regression
            if isinstance(e, dict) and e.get("stderr") is not None:
                e["stderr"] = json_safe_nan(e["stderr"])
    if "inertia" in model.stderr:
        for i, a in held:
            model.stderr["inertia"][i, a] = np.nan
    topo = model.topology
    warnings += physical_warnings(topo.rod_names, topo.spring_names, model.mass, model.inertia,
                                  model.stiffness, model.damping, model.stderr.get("inertia"))
    if model.full_inertia:  # the smallest eigenvalue of each rod's pseudo-inertia (> 0: a rigid body)
        J = inertia_tensor(model.inertia, model.inertia_frame)
        com = np.zeros((topo.n_rods, 3)) if model.com is None else model.com
        model.metrics["pseudo_inertia_min_eigenvalue"] = [
            float(np.linalg.eigvalsh(pseudo_inertia(model.mass[i], com[i], J[i]))[0]) for i in range(topo.n_rods)]
    model.metrics.setdefault("data", {})["residual_dof"] = round(
        residual_dof(sol.rows, sol.free, weak_window), 1)
    model.metrics["warnings"] = warnings
    return warnings


#: Adam's parameters further than this (relative) from the closed form's count as not converged
ADAM_TOLERANCE = 1e-2


def adam_convergence(sol: Solution, reference: Solution) -> list[str]:
    """A warning when Adam stopped short of the closed-form least squares of the same equations.

    Both minimise the same equations; the closed form is their exact minimiser, so a large
    distance means the 30 epochs were too few steps (too little data per epoch) or the
    learning-rate schedule stalled.
    """
    th, ref = np.asarray(sol.theta), np.asarray(reference.theta)
    scale = np.maximum(np.abs(ref), 1e-12 * max(float(np.max(np.abs(ref))), 1e-300))
    rel = np.abs(th - ref) / scale
    worst = float(np.max(rel)) if rel.size else 0.0
    if not np.isfinite(worst) or worst > ADAM_TOLERANCE:
        return [(f"Adam did not converge: its parameters differ from the closed-form least squares of the "
                 f"same equations by up to {100 * worst:.3g} % (use --solver lstsq, or more data per epoch)")]
    return []


def _is_physical(warning: str) -> bool:
    """Whether a warning line is one of :func:`physical_warnings`' (not a fit note)."""
    return warning.endswith((" is not positive", " is negative", "no rigid body has these moments"))


def refresh_physics(model) -> list[str]:
    """After a step that changed the parameters (refinement, the effect search): replace the
    physical warnings in ``model.metrics["warnings"]`` by those of its final values, keep the
    fit's other notes; returns the warnings."""
    t = model.topology
    kept = [w for w in model.metrics.get("warnings", []) if not _is_physical(w)]
    model.metrics["warnings"] = kept + physical_warnings(t.rod_names, t.spring_names, model.mass, model.inertia,
                                                         model.stiffness, model.damping,
                                                         model.stderr.get("inertia"))
    return model.metrics["warnings"]


#: a joint fit's equation residual below this, relative to its typical force
#: (:func:`relative_residual`), is rounding: the model's equations hold exactly on the data
ROUNDING = 1e-6


def relative_residual(model) -> float | None:
    """The joint fit's equation residual relative to the typical force (rounding level on exact data):
    the larger of the translation and rotation RMS over ``max(0.1 max|K|, max M)``."""
    if model is None:
        return None
    rms = model.metrics.get("equation_residual_rms", {})
    cond = [v for v in (rms.get("translation"), rms.get("rotation")) if v is not None]
    if not cond:
        return None
    scale = max(float(np.max(np.abs(model.stiffness))) * 0.1, float(np.max(model.mass)) * 1.0, 1e-300)
    return float(max(cond)) / scale


#: a fit on clean data whose one-step residual wrench exceeds this share of the recorded inertial
#: wrench does not describe its own data (its equations hold to ~1e-13 on a plant they model)
LARGE_RESIDUAL = 1e-2


def residual_check(model, data) -> dict:
    """Whether the model's equations describe the data it was fitted on, in ``metrics.residual``.

    The one-step residual wrench relative to the recorded inertial wrench
    (:func:`identified.evaluate.relative_one_step_errors`, rows of residual-strategy effects left
    out). Above :data:`LARGE_RESIDUAL` on clean data the fit is flagged ``large`` with a warning in
    ``metrics.warnings``: the model lacks something the plant has (geometry it cannot express, an
    effect), and its parameters absorb it. On data that record sensor noise the differenced
    accelerations carry the noise, so the figure is reported and not judged.
    """
    from identified.evaluate import relative_one_step_errors

    rel = float(relative_one_step_errors([model], data)[0])
    noisy = has_noise(data)  # recorded sensor noise, or states reconstructed from noisy markers
    large = bool(not noisy and not rel <= LARGE_RESIDUAL)
    out = {"relative_one_step": rel if np.isfinite(rel) else None, "threshold": LARGE_RESIDUAL,
           "judged": not noisy, "large": large}
    model.metrics["residual"] = out
    if large:
        line = (f"the fitted equations leave {rel:.3g} of the recorded wrench unexplained on their own data "
                f"(above {LARGE_RESIDUAL:g}): the model lacks something the plant has; its parameters are "
                "not the plant's")
        model.metrics.setdefault("warnings", [])
        if line not in model.metrics["warnings"]:
            model.metrics["warnings"].append(line)
    return out


def json_safe_nan(tree):
    """``tree`` (nested dicts/lists of numbers) with every number replaced by NaN (not estimable)."""
    if isinstance(tree, dict):
        return {k: json_safe_nan(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple, np.ndarray)):
        return [json_safe_nan(v) for v in tree]
    return float("nan") if isinstance(tree, (int, float, np.number)) and not isinstance(tree, bool) else tree
