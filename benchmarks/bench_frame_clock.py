"""The marker windows on a camera's clock against the same frames on the engine's 1 ms grid.

The robot (``--seed``: ``bench_recordings.varied_robot``), ``--takes`` takes of ``--steps`` steps,
clean markers at ``--rate``: once as ``collect --record`` writes them (times rounded to whole
milliseconds) and once at ``k / rate`` s exactly, the plant's markers interpolated between its
steps.  For each, windows of ``--frames`` frames at the true K, c, M, I and the plant's contact law
(``bench_recordings.law_truth``), from the plant's own states: how many windows the recording
offers, what the windows leave of the clean markers at the truth (rounding), and the time of the
cost's residuals (1 ms steps) and of the Jacobians (``--window-step`` steps), side by side, alone
and (``--busy``) beside one busy process.

    python benchmarks/bench_frame_clock.py --windows 8 --busy
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_recordings import law_truth, values_model, varied_robot
from bench_twin import busy_process

from identified.effects.pyramid_contact import PyramidContact
from identified.fit.output_error import window_problem
from identified.recording import site_world_positions
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers


def on_the_clock(rec, data, topology, rate: float):
    """``rec`` with its frames at ``k / rate`` s in every take, the plant's clean markers linear
    between its steps (the encoders' cells of the nearest grid frame: ``data`` gives the fit's)."""
    sites = tuple(s for r in topology.rods for s in r.sites)
    times, eps, marks, rows = [], [], [], []
    for e in range(data.n_episodes):
        every = site_world_positions(topology, data.pos[e], data.quat[e], sites)  # (T + 1, N, 3)
        t = np.arange(int(np.floor(data.n_steps * data.dt * rate)) + 1) / rate
        n = t / data.dt
        i = np.minimum(np.floor(n).astype(int), every.shape[0] - 2)
        f = (n - i)[:, None, None]
        marks.append((1 - f) * every[i] + f * every[i + 1])
        times.append(t)
        eps.append(np.full(t.size, e))
        take = np.flatnonzero(rec.episode == e)
        rows.append(take[np.minimum(np.searchsorted(rec.time[take], t), take.size - 1)])
    rows = np.concatenate(rows)
    return replace(rec, time=np.concatenate(times), episode=np.concatenate(eps), markers=np.concatenate(marks),
                   rest=rec.rest[rows], ctrl=rec.ctrl[rows], length=rec.length[rows], lines=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--takes", type=int, default=3)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--windows", type=int, default=8, help="windows spread over the recording")
    ap.add_argument("--window-step", type=int, default=5, help="the Jacobians' step, in 1 ms steps")
    ap.add_argument("--busy", action="store_true", help="also time beside one busy process")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "robot.xml")
        varied_robot(path, args.seed)
        truth = values_model(path)
        data = collect(path, CollectConfig(episodes=args.takes, steps=args.steps, seed=args.seed))
        grid = record_markers(data, path, RecordConfig(rate=args.rate, noise_pos=0.0, dropout=0.0), seed=args.seed)
        law = PyramidContact.for_system(truth.topology, path)
        law.values = law_truth(path)
        held = [(i, 2) for i in range(truth.topology.n_rods)]
        probs = {}
        for name, rec in (("1 ms grid", grid), ("k / rate", on_the_clock(grid, data, truth.topology, args.rate))):
            win, available, prob, dx, _ = window_problem(truth, rec, data, [0.0] * rec.n_episodes, path, 1e-3, held,
                                                         frames=args.frames, max_windows=args.windows, contact=law)
            with torch.no_grad():
                rms = float(prob.residuals(prob.theta0, dx).square().mean().sqrt()) * 1e-3
            print(f"{name:>10}: {available} windows of {args.frames} frames offered; {win.n_windows} stepped; "
                  f"at the truth the clean markers {rms:.1e} m RMS off", flush=True)
            probs[name] = (prob, dx)
        for cond in ("alone", "1 busy process") if args.busy else ("alone",):
            with busy_process(cond != "alone"):
                t = {}
                for name, (prob, dx) in probs.items():
                    t0 = time.perf_counter()
                    prob.window_residuals(prob.theta0, dx)
                    t1 = time.perf_counter()
                    prob.at_step(args.window_step).jacobians(prob.theta0, dx)
                    t[name] = (t1 - t0, time.perf_counter() - t1)
            (ra, ja), (rb, jb) = t.values()
            print(f"{cond}: residuals {ra:.2f} s (grid) / {rb:.2f} s (clock) = {rb / ra:.2f}; "
                  f"Jacobians {ja:.1f} s / {jb:.1f} s = {jb / ja:.2f}", flush=True)


if __name__ == "__main__":
    main()
