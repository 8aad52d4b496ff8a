"""K, c and M from markers too coarse for the regression: output error from a start, states first.

At a low rate or with coarse markers (30 Hz with 1 cm of noise, 10 Hz) the splines of
:mod:`identified.fit.markers` cannot reconstruct accelerations, and the regression's
errors-in-variables estimator finds that the noise accounts for all of its rows' signal.  The
markers still carry the information (:mod:`identified.fit.marker_bound`); the estimator that
reaches it fits them directly, through the engine (the windows, nuisances and cost of
:mod:`identified.fit.output_error`), from a start -- the model's nominal values, the total mass
known:

1. the windows' nuisances (initial states, the ground's wrench) alone, the parameters held at the
   start: Levenberg-Marquardt, window by window (``state_iters``;
   :func:`identified.fit.marker_bound.nuisance_step`, the steps of the bound's ``settle``);
2. then parameters and nuisances together, the nuisances eliminated by their Schur complement
   (``joint_iters``; :mod:`identified.fit.window_solve`), with the total mass held (which also
   fixes the scale no marker sees); each window takes the share of the step's state change that
   serves it best at the new parameters (:func:`window_states_at`), and every joint step is
   followed by one step of the windows' states alone, each window with its own damping, on the
   exact step's Jacobians.  The joint step has one damping for all: where a few windows' cost is
   rough it rises and holds every window's states back, and the coarse step's state columns stall
   short of the states' minimum (measured, 30 Hz / 1 cm, a 64-window fit stalled after 20 joint
   steps at 0.882 per residual with the damping at 5: a state step on the coarse Jacobians took it
   0.8808 -> 0.8803, two on the exact ones 0.8817 -> 0.8615 -> 0.8501).

Joint steps from states that the start parameters have not yet fitted move the parameters far
(measured: the joint refinement from such a start, 30 Hz / 1 cm, stalled at a marker residual of
3 cm); the nuisance-only steps are cheap in their effect and bring the residual to the noise's
size first.  Standard errors: the Gauss-Newton covariance at the end, scaled by the residual's
variance per degree of freedom; a parameter is reported not identifiable where that covariance
says it is (:class:`identified.fit.bound.CramerRao`).
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import torch

from identified.dataset import Dataset, atomic_write
from identified.effects.ground_contact import CONTACT_MARGIN
from identified.fit.bound import CramerRao, constrained_bound, window_gradient, window_information
from identified.fit.marker_bound import _names, natural_values, nuisance_step
from identified.fit.output_error import _Problem, window_problem
from identified.fit.window_solve import window_schur
from identified.model import IdentifiedModel
from identified.recording import Recording

__all__ = ["Agreement", "MarkerFit", "fit_markers"]


@dataclass(frozen=True)
class Agreement:
    """How well the estimates of blocks of windows fitted on their own agree
    (:func:`identified.fit.marker_blocks.combine`): ``chi2`` of their scatter about the combined
    estimate in their own information, over ``dof`` degrees of freedom, and its upper tail ``p``
    under the noise alone (NaN where ``dof`` is 0)."""

    chi2: float
    dof: int
    p: float


@dataclass
class MarkerFit:
    """The estimate: ``cov`` (a :class:`CramerRao` of the estimate's own Gauss-Newton covariance,
    its ``values`` the estimates at the known total mass), ``windows`` used of ``available``,
    ``residual_rms`` (m), ``history`` (cost per residual after each iteration), ``seconds`` (those of
    the runs before a resume too),
    ``converged`` (a joint step lowered the cost by less than a millionth before the iterations ran out),
    ``to_minimum`` (P,): the Gauss-Newton step left from the estimate to the minimum of the cost's
    quadratic model there, in each parameter's standard errors (NaN where it has none): an estimate
    whose error bar means what it says is within a fraction of one of the minimum; ``dof`` the
    residual's degrees of freedom (marker coordinates seen less the unknowns fitted; 0: not known).
    What a combination of fits needs (:func:`identified.fit.marker_blocks.combine_fits`):
    ``theta`` (P,) the estimate's unknowns (logarithms; logits of the contact law's impedances),
    ``information`` (P, P) their Fisher information ``JᵀJ / s²`` (nuisances eliminated, the
    residual's variance ``s²``), ``constraint`` (P,) the known total mass's row there; a fit of
    blocks of windows combined also has the ``blocks``' fits and their ``agreement``."""

    cov: CramerRao
    windows: int
    available: int
    residual_rms: float
    history: list[float]
    seconds: float
    converged: bool = False
    to_minimum: np.ndarray | None = None
    dof: float = 0.0
    theta: np.ndarray | None = None
    information: np.ndarray | None = None
    constraint: np.ndarray | None = None
    blocks: list[MarkerFit] = field(default_factory=list)
    agreement: Agreement | None = None

    @property
    def rel_se(self) -> np.ndarray:
        """(P,) the relative standard errors to report: the Gauss-Newton ones widened by half the step
        left to the minimum of the cost's quadratic model, ``se (1 + |step| / 2)`` (the step in
        standard errors): the estimate lies between here and there, the truth within two error bars
        of there (measured: 30 Hz / 1 cm, 64 windows, the contacts' windows keep every Gauss-Newton
        step from lowering the cost, exact Jacobians' too, and the fit stops with the step left
        moving K by 0.4-0.7 of their standard errors, towards the truth: RMS z 1.04 here, 0.68 there)."""
        if self.to_minimum is None:
            return self.cov.rel_se
        return self.cov.rel_se * (1.0 + 0.5 * np.nan_to_num(np.abs(self.to_minimum)))

    def group(self, prefix: str) -> tuple[np.ndarray, np.ndarray]:
        """Estimates and relative standard errors (:attr:`rel_se`) of the parameters named ``prefix[...]``."""
        idx = [i for i, n in enumerate(self.cov.names) if n.startswith(prefix + "[")]
        return self.cov.values[idx], self.rel_se[idx]


def fit_markers(start: IdentifiedModel, rec: Recording, data: Dataset, starts: list[float], mjcf: str | None,
                sigma: float, hold_inertia: list[tuple[int, int]] = (), frames: int = 10, max_windows: int = 64,
                state_iters: int = 4, joint_iters: int = 6, contact_margin: float | None = None,
                wrench_order: int = 3, contact=None, law_free: tuple[str, ...] = (), substeps: int = 1,
                progress: bool = False, checkpoint: str | None = None, block: tuple[int, int] = (0, 1)) -> MarkerFit:
    """Fit K, c, M and the observable moments to the markers from ``start`` (its total mass is the
    known one), the module docstring's two stages; ``data`` and ``starts``: the reconstructed
    states aligned with the recording (:func:`identified.fit.markers.states_from_recording`).
    ``contact_margin`` (m): a rod whose reconstructed end sphere comes this close to the ground
    feels the free wrench (``None``: :data:`~identified.fit.output_error.CONTACT_MARGIN`), a Legendre
    polynomial in time of ``wrench_order`` terms (2: constant and linear; 3: and quadratic -- measured
    at 30 Hz / 1 cm, 32 windows of 0.27 s, a varied robot: with 2 the worst K 9.3 % off at |z| 4.7,
    with 3 2.1 % at 0.9: a linear wrench does not follow the contacts, and the misfit biases K).
    ``contact``: the windows follow this contact law instead (every rod simulated; its ``values``
    the start, never the plant's), ``law_free`` its parameters estimated with K, c, M (the others
    held); :func:`identified.fit.output_error.window_problem`.  ``substeps``: the Jacobians taken on
    the windows stepped at up to that many of ``data.dt`` (:func:`identified.fit.output_error.coarse_steps`:
    ``substeps`` times fewer steps through the forward-mode derivatives), the cost and its residuals
    at ``data.dt`` still: Gauss-Newton with an approximate Jacobian stops where ``J_kᵀ r = 0``, which
    the noise in ``r`` does not bias, while the coarse step's own windows would (measured, 30 Hz /
    1 cm, the clean markers' residual at the truth, linearised: c 10 % off at 4 ms, 1.8 times the
    recording's bound; K 0.5 %, 1.4 times); the state step after each joint step on the exact
    Jacobians; the standard errors from the last Jacobian.  Where the
    coarse Jacobians stall (no step lowers the cost, or only at a damping above
    :data:`STALL_DAMPING`), the fit goes on with the exact step's Jacobians.
    ``checkpoint``: a file the fit's state is written to (atomically) after every step, and resumed
    from when it holds a fit of the same windows from the same start (:func:`_resume`): an
    interrupted fit of hours goes on where it stopped, to the same result.  ``block`` ``(b, B)``: the
    fit of block ``b`` of ``B`` interleaved blocks of the windows (:mod:`identified.fit.marker_blocks`)."""
    t0 = time.perf_counter()
    win, available, prob, dx, acts = window_problem(
        start, rec, data, starts, mjcf, sigma, hold_inertia, frames, max_windows, wrench_order,
        margin=CONTACT_MARGIN if contact_margin is None else contact_margin, contact=contact, law_free=law_free,
        block=block, free_gains=True)
    jac = prob.at_step(substeps)  # the Jacobians' windows; the cost's at data.dt
    W, R, k = win.n_windows, start.topology.n_rods, prob.n_x
    theta = prob.theta0.clone()
    P = theta.numel()
    msl = prob.mass_slice
    U = torch.as_tensor(sla.null_space(prob.total_mass_row(start.mass)[None]))  # steps that keep the total mass

    r = prob.window_residuals(theta, dx)
    n = r.numel()
    cost = float(r.square().sum())
    history = [cost / n]
    mu = 1e-3
    mu_x = torch.full((W,), 1e-3, dtype=torch.float64)  # each window's own damping in its state steps
    converged = False
    first = 0
    key = _fit_key((theta, dx, win.x0, win.obs, win.seen, win.rest), sigma, substeps, state_iters)
    saved = _resume(checkpoint, key)
    if saved is not None:
        theta, dx, mu, history, first, converged = (saved["theta"], saved["dx"], saved["mu"], saved["history"],
                                                     saved["steps"], saved["converged"])
        mu_x = saved.get("mu_x", mu_x)
        t0 -= float(saved.get("seconds", 0.0))  # the fit's seconds count those before the interruption
        if saved.get("exact"):
            jac = prob
        r = prob.window_residuals(theta, dx)
        cost = float(r.square().sum())
        if progress:
            done = f"{min(first, state_iters)} state + {max(first - state_iters, 0)} joint steps"
            print(f"marker fit: resumed from '{checkpoint}' after {done}, cost per residual {history[-1]:.4f}",
                  flush=True)
    for it in range(first, state_iters + joint_iters):
        if converged:
            break
        joint = it >= state_iters
        if not joint:  # the nuisances alone, the parameters held (the bound's settle)
            dx, r, cost, mu_x, moved = nuisance_step(prob, theta, dx, acts, mu_x, jac=jac)
        else:
            _, Jx, Jp = jac.jacobians(theta, dx)
            Jx = Jx * acts.unsqueeze(1)
            Jp = Jp @ U
            A0 = Jx.transpose(1, 2) @ Jx
            gx = Jx.transpose(1, 2) @ r.unsqueeze(-1)
            B = Jx.transpose(1, 2) @ Jp
            C = (Jp.transpose(1, 2) @ Jp).sum(0)
            gp = (Jp.transpose(1, 2) @ r.unsqueeze(-1)).sum(0)
            moved, mu_before = False, mu
            for _ in range(8):  # Levenberg-Marquardt: damping raised until a step lowers the cost
                A = A0 + torch.diag_embed(mu * torch.diagonal(A0, dim1=-2, dim2=-1) + (1 - acts) + 1e-12)
                sc = window_schur(A, B, C)
                Aig, gs = sc.reduce(gx, gp)
                # a parameter the windows do not move (a contact law's impedance width when every
                # contact is deeper) has a zero row: a ridge keeps it where it is
                ridge = 1e-12 * float(sc.S.diagonal().max()) * torch.eye(P - 1, dtype=torch.float64)
                dphi = -torch.linalg.solve(sc.S + mu * torch.diag(sc.S.diagonal()) + ridge, gs)
                th_new = theta + (U @ dphi).squeeze(-1)
                step_x = (sc.back_substitute(Aig, dphi).squeeze(-1) * acts).reshape(W, R, k)
                dx_new, r_new = window_states_at(prob, th_new, dx, step_x)
                c_new = float(r_new.square().sum())
                if np.isfinite(c_new) and c_new < cost:
                    theta, dx, r, cost, moved = th_new, dx_new, r_new, c_new, True
                    mu = max(mu / 3, 1e-7)
                    break
                mu *= 4
            if not moved:
                mu = mu_before  # tried again from there once the states below have moved
            joint_cost = cost
            # then the windows' states alone, each window with its own damping, on the exact step's
            # Jacobians: the joint step's one damping, raised by the windows whose cost is rough,
            # holds every window's states back, and the coarse step's state columns stall short of
            # the states' minimum
            dx, r, cost, mu_x, _ = nuisance_step(prob, theta, dx, acts, mu_x)
        history.append(cost / n)
        if progress:
            step = f"joint step {it + 1 - state_iters}" if joint else f"states step {it + 1}"
            damping = mu if joint else float(mu_x.median())
            after = f" ({joint_cost / n:.4f} before the states' step)" if joint else ""
            print(f"marker fit: {step}, cost per residual {history[-1]:.4f}{after} "
                  f"(damping {damping:.1e}), {time.perf_counter() - t0:.0f} s", flush=True)
        small = history[-2] - history[-1] < 1e-6 * history[-1]
        if joint and jac is not prob and (not moved or (small and mu > STALL_DAMPING)):
            # the coarse step's Jacobian no longer finds a way down the cost at data.dt (measured: 30 Hz /
            # 1 cm, 16 windows at 5 ms, stalled at 1.40 sigma^2 with the damping at 1e4): exact from here
            jac, mu = prob, 1e-3
            if progress:
                print(f"marker fit: the {substeps}-step Jacobians stalled; the exact step's from joint step {it + 2 - state_iters}",
                      flush=True)
        elif joint and small:
            converged = True  # neither step lowers the cost any more, or by a millionth
        if checkpoint is not None:
            _save(checkpoint, {"key": key, "theta": theta, "dx": dx, "mu": mu, "mu_x": mu_x, "history": history, "steps": it + 1,
                               "converged": converged, "exact": jac is prob, "seconds": time.perf_counter() - t0})
    _, Jx, Jp = jac.jacobians(theta, dx)
    Jx, Jp = (Jx * acts.unsqueeze(1)).numpy(), Jp.numpy()
    F = window_information(Jx, Jp)
    held_rods = {i for i, _ in hold_inertia}
    n_x = float(acts.sum()) - sum(2.0 for i in range(R) if i in held_rods) * W  # no spin along the held axes
    dof = float(win.seen.sum()) * 3 - n_x - (P - 1)
    s2 = float(r.square().sum()) / max(dof, 1.0)
    scale = torch.zeros(P, dtype=torch.float64)
    scale[:prob.n_spring_rod] = 1.0  # the global scale moves K, c, M, I, not the contact law
    theta = theta + scale * float(np.log(start.mass.sum()) - torch.logsumexp(theta[msl], 0))  # the exact total mass
    gt = prob.total_mass_row(theta[msl].exp().numpy())
    cov = constrained_bound(F / s2, _names(prob, start), natural_values(prob, theta), constraints=gt[None])
    # the Gauss-Newton step that remains to the minimum of the cost's quadratic model (nuisances
    # re-fitted; within the known total mass), in each parameter's standard errors: -C g / s²
    step = -(cov.cov @ window_gradient(Jx, Jp, r.numpy())) / s2
    with np.errstate(divide="ignore", invalid="ignore"):
        to_minimum = np.where(cov.finite, step / cov.rel_se, np.nan)
    return MarkerFit(cov, W, available, float(np.sqrt(s2)) * float(sigma), history, time.perf_counter() - t0,
                     converged, to_minimum, dof, theta.numpy().copy(), F / s2, gt)


#: the shares of a joint step's state change each window may take (:func:`window_states_at`)
STATE_SHARES = (1.0, 0.5, 0.0)


def window_states_at(prob: _Problem, theta: torch.Tensor, dx: torch.Tensor, step_x: torch.Tensor,
                     shares: tuple[float, ...] = STATE_SHARES) -> tuple[torch.Tensor, torch.Tensor]:
    """The states ``dx + a step_x`` at the parameters ``theta``, ``a`` in ``shares`` chosen for each
    window on its own (the lowest cost; a window's residuals depend on its own states only), and
    their residuals (W, m).  The joint step's state change is the Gauss-Newton one, linear in the
    parameters' step; where a window's cost is far from quadratic (rods on the ground at 1 cm noise)
    its full change can raise that window's cost while the other windows' fall, and the whole step
    is refused: a window keeps the share that serves it at the new parameters instead."""
    best_dx, best_r, best_c = None, None, None
    for a in shares:
        cand = dx + a * step_x
        r = prob.window_residuals(theta, cand)  # a broken contact solve: infinity
        c = r.square().sum(1)
        c = torch.where(torch.isfinite(c), c, torch.full_like(c, np.inf))
        if best_c is None:
            best_dx, best_r, best_c = cand, r, c
            continue
        take = c < best_c
        best_dx = torch.where(take[:, None, None], cand, best_dx)
        best_r = torch.where(take[:, None], r, best_r)
        best_c = torch.where(take, c, best_c)
    return best_dx, best_r


#: Levenberg-Marquardt's damping (relative to the normal matrix's diagonal) above which a joint step
#: of the coarse Jacobians that barely lowers the cost is a stall, not convergence
STALL_DAMPING = 10.0


def _fit_key(tensors: tuple[torch.Tensor, ...], sigma: float, substeps: int, state_iters: int) -> str:
    """What a checkpoint must match to be resumed: the start (parameters, the windows' nuisances,
    their reconstructed initial states), the windows' markers and rest lengths, the markers' noise,
    the Jacobians' step and the state-only steps (a different number would change which steps were
    joint)."""
    h = hashlib.sha256()
    for t in tensors:
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().numpy().tobytes())
    h.update(f"{float(sigma)!r} {int(substeps)} {int(state_iters)}".encode())
    return h.hexdigest()


def _resume(path: str | None, key: str) -> dict | None:
    """The checkpoint at ``path`` if it is one of this fit (its key), else ``None`` (none there, or
    another fit's: then said, and overwritten by this one's first step)."""
    if path is None or not os.path.exists(path):
        return None
    try:
        saved = torch.load(path, weights_only=True)
    except Exception:  # noqa: BLE001 -- a truncated or foreign file is not a checkpoint of this fit
        saved = None
    if not isinstance(saved, dict) or saved.get("key") != key:
        warnings.warn(f"checkpoint '{path}' is not of this fit (other windows, start or noise): starting afresh",
                      stacklevel=3)
        return None
    return saved


def _save(path: str, state: dict) -> None:
    """Write ``state`` to ``path`` whole or not at all (:func:`identified.dataset.atomic_write`)."""
    atomic_write(path, lambda fh: torch.save(state, fh), binary=True)
