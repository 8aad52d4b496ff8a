"""The marker windows' Jacobians with and without the shape-only ``Meta`` kernels
(:mod:`identified.fit.forward_mode`), side by side, alone and (``--busy``) beside one busy process.

The robot (``--seed``: ``bench_recordings.varied_robot``), ``--takes`` takes of ``--steps`` steps,
markers at ``--rate`` with 1 cm noise, ``--windows`` windows of ``--frames`` frames at the true
parameters and the plant's contact law (``bench_recordings.law_truth``), the Jacobians at
``--window-step`` steps: the time of each and the largest difference between them (0: the same
numbers).

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

from bench_recordings import law_truth, values_model, varied_robot
from bench_twin import busy_process

from identified.effects.pyramid_contact import PyramidContact
from identified.fit import output_error
from identified.fit.output_error import window_problem
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--takes", type=int, default=2)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--windows", type=int, default=4, help="windows spread over the recording")
    ap.add_argument("--window-step", type=int, default=5, help="the Jacobians' step, in 1 ms steps")
    ap.add_argument("--busy", action="store_true", help="also time beside one busy process")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "robot.xml")
        varied_robot(path, args.seed)
        truth = values_model(path)
        data = collect(path, CollectConfig(episodes=args.takes, steps=args.steps, seed=args.seed))
        rec = record_markers(data, path, RecordConfig(rate=args.rate, noise_pos=0.01, dropout=0.0), seed=args.seed)
        law = PyramidContact.for_system(truth.topology, path)
        law.values = law_truth(path)
        held = [(i, 2) for i in range(truth.topology.n_rods)]
        win, _, prob, dx, _ = window_problem(truth, rec, data, [0.0] * rec.n_episodes, path, 1e-2, held,
                                             frames=args.frames, max_windows=args.windows, contact=law)
        jac = prob.at_step(args.window_step)
        print(f"{win.n_windows} windows of {args.frames} frames at {args.rate:g} Hz, Jacobians at "
              f"{args.window_step} ms: {jac.n_x * truth.topology.n_rods} state and {prob.theta0.numel()} parameter "
              "columns", flush=True)
        own = output_error.shape_only_meta
        for cond in ("alone", "1 busy process") if args.busy else ("alone",):
            with busy_process(cond != "alone"):
                t, J = {}, {}
                for name, meta in (("torch's meta", contextlib.nullcontext), ("shape-only meta", own)):
                    output_error.shape_only_meta = meta
                    t0 = time.perf_counter()
                    J[name] = jac.jacobians(prob.theta0, dx)
                    t[name] = time.perf_counter() - t0
                output_error.shape_only_meta = own
            (a, ta), (b, tb) = t.items()
            diff = max(float((x - y).abs().max()) for x, y in zip(J[a], J[b]))
            print(f"{cond}: {a} {ta:.1f} s, {b} {tb:.1f} s = {ta / tb:.2f}x faster; largest difference "
                  f"{diff:.1e}", flush=True)


if __name__ == "__main__":
    main()
