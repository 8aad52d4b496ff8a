"""The Cramér-Rao bound of a recording: how well any estimator can know K, c, M and the moments of
inertia from its markers (:mod:`identified.fit.bound` on the output-error model of
:mod:`identified.fit.output_error`).

At a given model (the truth, in a benchmark) the recording is cut into windows of ``frames``
frames; each window's rods start from a free state and the rods near the ground feel a free wrench
(linear in time), all of them nuisances; the markers' noise is Gaussian with the stated ``σ`` per
coordinate.  The Jacobians of the marker positions in the log-parameters and in every window's
nuisances are exact (forward mode through the engine).  The linearisation point: the window's
states and wrenches that best explain the markers at the given parameters (``state_steps``
Gauss-Newton steps in the nuisances alone).  The information of an even subsample of
``max_windows`` windows is scaled by ``available / used``: the bound of the whole recording's
windows.  The total mass is known (the constraint that also fixes the global scale no marker
sees).  Short windows keep the engine's free runs from the divergence of rolling contact; the
bound is then that of estimators which use the windows alone (they do not know the contact law).
With a ``contact`` law the windows follow the contacts through it instead (every rod simulated,
the initial states the only nuisances): the bound of estimators that know the law's form, its
parameters unknowns too where ``law_free`` names them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from identified.dataset import Dataset
from identified.fit.bound import CramerRao, constrained_bound, window_information
from identified.fit.output_error import _Problem, window_problem
from identified.model import IdentifiedModel
from identified.recording import Recording

__all__ = ["RecordingBound", "recording_bound"]


@dataclass
class RecordingBound:
    """The bound and how it was taken: ``windows`` used of ``available``, the markers' residual
    RMS (m) at the linearisation point, ``seconds``."""

    bound: CramerRao
    windows: int
    available: int
    residual_rms: float
    seconds: float

    def group(self, prefix: str) -> np.ndarray:
        """The relative bounds of the parameters named ``prefix[...]`` (``K``, ``c``, ``M``, ``I``)."""
        return np.array([r for n, r in zip(self.bound.names, self.bound.rel_se) if n.startswith(prefix + "[")])


def _names(prob: _Problem, model: IdentifiedModel) -> list[str]:
    topo = model.topology
    axes = "xyz"
    return ([f"K[{s}]" for s in topo.spring_names] + [f"c[{s}]" for s in topo.spring_names]
            + [f"M[{r}]" for r in topo.rod_names]
            + [f"I[{topo.rod_names[i]}:{''.join(axes[a] for a in ax)}]" for i, ax in prob.groups]
            + [f"gain[{n}]" for n in prob.gain_names] + [f"law[{n}]" for n in prob.law_names])


def natural_values(prob: _Problem, theta: torch.Tensor) -> np.ndarray:
    """The parameters at the unknowns ``theta`` in their own units: K, c, M, I (their logarithms'
    exponentials), the actuators' gains (the start's times their unknowns' exponentials), then the
    contact law's free parameters."""
    out = theta[:prob.n_spring_rod].exp()
    out = torch.cat([out[:prob.gain_slice.start], prob.gain0 * out[prob.gain_slice], out[prob.gain_slice.stop:]])
    if prob.law_idx:
        out = torch.cat([out, prob.law_theta(theta)[prob.law_idx]])
    return out.detach().numpy()


def nuisance_step(prob: _Problem, theta: torch.Tensor, dx: torch.Tensor, acts: torch.Tensor,
                  mu: float | torch.Tensor, tries: int = 8, jac: _Problem | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, float, torch.Tensor, bool]:
    """One Levenberg-Marquardt step in the windows' nuisances ``dx`` (W, R, n_x) alone at the
    parameters ``theta``, each window on its own (they share nothing once ``theta`` is held): with
    ``J`` a window's Jacobian in its nuisances (the columns of ``acts`` (W, R n_x) that act),
    ``dx - (JᵀJ + μ diag(JᵀJ) + diag(1 - acts) + 1e-12 I)⁻¹ Jᵀ r``, the window's own damping ``μ``
    raised fourfold (at most ``tries`` times) until the step lowers that window's cost, then lowered
    threefold (not below 1e-7); a trial is run on the windows still without a step only.  One
    damping and one test for all the windows together would let a window whose cost is rough hold
    back the others, and accept steps that raise some windows' cost (measured: 30 Hz, clean
    markers, 22 windows at the truth: a shared step left the markers 0.60 mm off after 6 steps,
    each window's own 0.33 mm).  ``mu``: a damping for every window (W,), or one to start them at.
    Returns ``(dx, r, cost, mu, moved)``: the nuisances, their residuals (W, m) and cost ``Σ r²``,
    the dampings (W,), and whether any window took a step.  ``jac``: the problem whose Jacobian
    steps (a coarser step's, :meth:`_Problem.at_step`), ``prob``'s residuals the cost."""
    W, R, k = dx.shape
    r, Jx, _ = (prob if jac is None else jac).jacobians(theta, dx, params=False)
    if jac is not None and jac is not prob:
        r = prob.window_residuals(theta, dx)
    mu = torch.as_tensor(mu, dtype=torch.float64).expand(W).clone()
    Jx = Jx * acts.unsqueeze(1)
    A0 = Jx.transpose(1, 2) @ Jx
    gx = Jx.transpose(1, 2) @ r.unsqueeze(-1)
    dx, r = dx.clone(), r.clone()  # the caller's are not changed
    window_cost = r.square().sum(1)
    done = torch.zeros(W, dtype=torch.bool)
    for _ in range(tries):
        A = A0 + torch.diag_embed(mu[:, None] * torch.diagonal(A0, dim1=-2, dim2=-1) + (1 - acts) + 1e-12)
        ddx = torch.cholesky_solve(gx, torch.linalg.cholesky(A))
        keep = (~done).nonzero().squeeze(-1)
        trial = dx[keep] - (ddx.squeeze(-1) * acts)[keep].reshape(-1, R, k)
        r_new = prob.window_residuals(theta, trial, keep)
        c_new = r_new.square().sum(1)
        better = torch.isfinite(c_new) & (c_new < window_cost[keep])
        took = keep[better]
        dx[took], r[took], window_cost[took] = trial[better], r_new[better], c_new[better]
        mu[took] = (mu[took] / 3).clamp(min=1e-7)
        mu[keep[~better]] *= 4
        done[took] = True
        if bool(done.all()):
            break
    return dx, r, float(window_cost.sum()), mu, bool(done.any())


def settle(prob: _Problem, theta: torch.Tensor, dx: torch.Tensor, acts: torch.Tensor, steps: int,
           progress: bool = False) -> torch.Tensor:
    """The windows' nuisances ``dx`` after ``steps`` Levenberg-Marquardt steps in them alone at the
    parameters ``theta`` (:func:`nuisance_step`: a step taken only where it lowers the cost; plain
    Gauss-Newton steps from a constant ground wrench overshoot: measured 30 Hz, clean markers,
    0.27 s windows, 310 mm of residual after two)."""
    mu = 1e-3
    for j in range(steps):
        dx, r, cost, mu, _ = nuisance_step(prob, theta, dx, acts, mu)
        if progress:
            rms = np.sqrt(cost / max(r.numel(), 1)) * prob.sigma
            print(f"bound: nuisance step {j + 1}, marker residual {1e3 * rms:.3f} mm", flush=True)
    return dx


def recording_bound(model: IdentifiedModel, rec: Recording, data: Dataset, starts: list[float], mjcf: str | None,
                    sigma: float, hold_inertia: list[tuple[int, int]] = (), frames: int = 10, max_windows: int = 64,
                    state_steps: int = 2, order: int = 2, contact=None, law_free: tuple[str, ...] = (),
                    substeps: int = 1, progress: bool = False) -> RecordingBound:
    """The Cramér-Rao bound of ``rec`` at ``model``'s parameters (the module docstring); ``data``
    and ``starts`` the rod states aligned with the recording (as :func:`identified.fit.output_error.
    refine_markers` takes them).  ``hold_inertia``'s moments are parameters here too: their bound
    says they are not identifiable.  ``contact``: the windows follow this contact law (at its
    ``values``) instead of a free ground wrench, ``law_free`` its parameters that are unknowns too
    (:func:`identified.fit.output_error.window_problem`): the bound of an estimator that knows the
    law's form (and, where not free, its values).  ``substeps``: the windows stepped at up to that
    many of ``data.dt`` (:func:`identified.fit.output_error.coarse_steps`)."""
    if not sigma > 0:
        raise ValueError(f"marker noise {sigma!r}: the bound needs a positive noise (m)")
    t0 = time.perf_counter()
    win, available, prob, dx, acts = window_problem(model, rec, data, starts, mjcf, sigma, hold_inertia, frames,
                                                    max_windows, order, axial=True, contact=contact,
                                                    law_free=law_free, substeps=substeps, free_gains=True)
    W = win.n_windows
    theta = prob.theta0
    dx = settle(prob, theta, dx, acts, state_steps, progress)
    r, Jx, Jp = prob.jacobians(theta, dx)
    Jx = Jx * acts.unsqueeze(1)
    F = window_information(Jx.numpy(), Jp.numpy()) * (available / W)
    g = prob.total_mass_row(model.mass)
    cr = constrained_bound(F, _names(prob, model), natural_values(prob, theta), constraints=g[None])
    seen = (win.seen.sum() * 3).clamp(min=1)
    res = float((r.square().sum() / seen).sqrt()) * sigma
    return RecordingBound(cr, W, available, res, time.perf_counter() - t0)
