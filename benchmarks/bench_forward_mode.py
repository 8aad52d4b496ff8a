"""The marker windows' Jacobians with and without the shape-only ``Meta`` kernels
(:mod:`identified.fit.forward_mode`), side by side, alone and (``--busy``) beside one busy process.

The windows of a probe at the truth (``bench_recordings.truth_windows``: the robot of ``--seed``,
10 takes of 10 s, markers at ``--rate`` with ``--noise``, ``--windows`` windows of 9 frames through
the plant's contact law), the Jacobians at ``--window-step`` seconds' steps: the time of each (the lesser of two
runs taken in turn) and the largest difference between them (0: the same numbers).

    python benchmarks/bench_forward_mode.py --windows 4 --busy
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_recordings import truth_window_args, truth_windows
from bench_twin import busy_process

from identified.fit import output_error


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    truth_window_args(ap)
    ap.add_argument("--window-step", type=float, default=0.005, help="the Jacobians' step (s), as the fit's")
    ap.add_argument("--busy", action="store_true", help="also time beside one busy process")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        truth, win, _, prob, dx, _ = truth_windows(tmp, args)
        jac = prob.at_step(max(1, round(args.window_step / truth.dt)))
        print(f"{win.n_windows} windows of {win.at.shape[1]} frames at {args.rate:g} Hz, Jacobians at "
              f"{1e3 * args.window_step:g} ms: {dx[0].numel()} state and {prob.theta0.numel()} parameter columns", flush=True)
        own = output_error.shape_only_meta
        for cond in ("alone", "1 busy process") if args.busy else ("alone",):
            with busy_process(cond != "alone"):
                t, J = {}, {}
                for _ in range(2):  # each twice, in turn: the least of its times (the first pays warm-up)
                    for name, meta in (("torch's meta", contextlib.nullcontext), ("shape-only meta", own)):
                        output_error.shape_only_meta = meta
                        t0 = time.perf_counter()
                        J[name] = jac.jacobians(prob.theta0, dx)
                        t[name] = min(t.get(name, float("inf")), time.perf_counter() - t0)
                output_error.shape_only_meta = own
            (a, ta), (b, tb) = t.items()
            diff = max(float((x - y).abs().max()) for x, y in zip(J[a], J[b]))
            print(f"{cond}: {a} {ta:.1f} s, {b} {tb:.1f} s = {ta / tb:.2f}x faster; largest difference "
                  f"{diff:.1e}", flush=True)


if __name__ == "__main__":
    main()
