"""How the marker fit's state steps converge through the ground's contact, and what smoothing the
contact law does to them (the windows' initial states alone, at the truth).

A robot with every K, c, M drawn 15 % off the preset's (``bench_recordings.varied_robot``), 10 takes
of 10 s, markers at ``--rate`` with ``--noise`` and 2 % missing; windows of 9 frames at the true
K, c, M, I and the plant's own contact law (``bench_recordings.law_truth``: the truth, which only a
benchmark knows), started from the plant's own states.  Two measurements:

* ``--roughness``: each window's Jacobian in its initial state along its Gauss-Newton step against
  central differences at fractions of that step, through the exact law and the smoothed ones
  (``--widths``): where the derivative stops describing the markers;
* else: ``--steps`` state steps (:func:`identified.fit.marker_bound.nuisance_step`), each on the
  Jacobians through the law smoothed over ``--widths`` (one width per step, 0 the exact law; the
  cost the exact law's) or, with ``--homotopy``, on the smoothed law's own cost.  Prints the exact
  cost per residual after each step and the minimum the noise alone would leave, (seen
  coordinates - free states) / residuals.

    python benchmarks/bench_state_steps.py --roughness --windows 6 --widths 0,0.001
    python benchmarks/bench_state_steps.py --windows 8 --widths 0,0,0,0,0,0,0,0
    python benchmarks/bench_state_steps.py --windows 8 --widths 0.001,0.001,0.001,0.001,0.001,0.001,0.001,0.001
    python benchmarks/bench_state_steps.py --windows 8 --widths 0.002,0.002,0.001,0.001,0.0005,0,0,0 --homotopy
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_recordings import truth_window_args, truth_windows

from identified.fit.marker_bound import nuisance_step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    truth_window_args(ap)
    ap.add_argument("--widths", default="0,0.001", help="smoothing widths (m), one a step (or a probe)")
    ap.add_argument("--homotopy", action="store_true", help="the steps on the smoothed law's own cost")
    ap.add_argument("--roughness", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    widths = [float(w) for w in args.widths.split(",")]

    with tempfile.TemporaryDirectory() as tmp:
        truth, win, _, prob, dx, acts = truth_windows(tmp, args)
        held = [(i, 2) for i in range(truth.topology.n_rods)]
        theta = prob.theta0
        if args.roughness:
            roughness(prob, theta, dx, acts, widths)
        else:
            steps(prob, theta, dx, acts, widths, args.homotopy, win, held)


def roughness(prob, theta, dx, acts, widths) -> None:
    """The derivative along each window's Gauss-Newton step against central differences."""
    r, Jx, _ = prob.jacobians(theta, dx, params=False)
    Jx = Jx * acts.unsqueeze(1)
    A = Jx.transpose(1, 2) @ Jx + torch.diag_embed((1 - acts) + 1e-9)
    step = -torch.cholesky_solve(Jx.transpose(1, 2) @ r.unsqueeze(-1), torch.linalg.cholesky(A)).squeeze(-1)
    step = (step * acts).reshape(dx.shape)
    print("Gauss-Newton step, largest rod displacement per window (mm):",
          np.round(step[..., :3].norm(dim=-1).amax(-1).numpy() * 1e3, 1))
    for width in widths:
        p = prob.with_smoothing(width)
        J = Jx if p is prob else p.jacobians(theta, dx, params=False)[1]  # the exact law's: the one above
        lin = (J @ step.reshape(step.shape[0], -1, 1)).squeeze(-1)
        for h in (1e-6, 1e-4, 1e-3, 1e-2, 1e-1):
            fd = (p.window_residuals(theta, dx + h * step) - p.window_residuals(theta, dx - h * step)) / (2 * h)
            err = ((fd - lin).norm(dim=1) / lin.norm(dim=1)).numpy()
            print(f"width {width * 1e3:g} mm, {h:g} of the step: derivative off by {np.round(100 * err, 1)} %",
                  flush=True)


def steps(prob, theta, dx, acts, widths, homotopy: bool, win, held) -> None:
    """State steps, each on the Jacobians through the law smoothed over its width."""
    n = win.seen.numel() * 3
    seen = float(win.seen.sum()) * 3
    free = float(acts.sum()) - 2.0 * len(held) * win.n_windows  # no spin about the held axes
    cost = lambda d: float(prob.window_residuals(theta, d).square().sum()) / n
    print(f"{n} residuals, {seen:.0f} seen, {free:.0f} free states: the noise alone leaves {(seen - free) / n:.4f} "
          f"per residual at the minimum; at the plant's states {cost(dx):.4f}", flush=True)
    mu = 1e-3
    t0 = time.perf_counter()
    for k, width in enumerate(widths, 1):
        if homotopy:
            smooth = prob.with_smoothing(width)
            if smooth is not prob:
                smooth.contact.smoothed_iterations = None  # its own cost: the smoothed law solved to rounding
            dx, _, c, mu, _ = nuisance_step(smooth, theta, dx, acts, mu)
            own = f", its own {c / n:.4f}"
        else:
            dx, _, _, mu, _ = nuisance_step(prob, theta, dx, acts, mu, jac=prob.with_smoothing(width))
            own = ""
        print(f"step {k} (width {width * 1e3:g} mm): cost per residual {cost(dx):.4f}{own}, median damping "
              f"{float(mu.median()):.2g}, {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
