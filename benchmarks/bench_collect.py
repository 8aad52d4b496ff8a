"""Collection throughput: recorded steps per second of ``tensegrity collect``, by preset and pushes.

    python benchmarks/bench_collect.py [--quick] [--episodes 5] [--steps 2000] [--repeats 2]

For the paper's icosahedron (``ico/paper-nonuniform``, seed 0: no ground, gravity) and the robot
(``ico/robot``: ground contact, motor-driven cables), with and without pushes (50 N every 100
steps, held 10 steps), it times :func:`tensegrity_gym.collect.collect` (the whole loop: random
initial states, command schedule, per-step read-out, motors, pushes, MuJoCo step) and prints

* steps/s (best of ``--repeats``), and the projected time of the paper's data scale
  (1000 trajectories x 2000 steps) on one core;
* the dataset's size in memory per step and at the paper's scale, and the time to write it
  (``save_dataset``: compressed ``.npz``, atomically) in MB/s.

Figures, not assertions: the machine's other load shows in them.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import fields

import mujoco
import numpy as np

from identified.dataset import Dataset, save_dataset
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model

PAPER_STEPS = 1000 * 2000  # paper, Sec. Experiments: 1000 training trajectories of 2000 steps
CASES = (("paper ico", "paper-nonuniform", 0), ("robot", "robot", None))


def nbytes(d: Dataset) -> int:
    return sum(getattr(d, f.name).nbytes for f in fields(d) if isinstance(getattr(d, f.name), np.ndarray))


def bench(xml: str, episodes: int, steps: int, push_every: int | None, repeats: int) -> tuple[float, Dataset]:
    best, data = 0.0, None
    for r in range(repeats):
        cfg = CollectConfig(episodes=episodes, steps=steps, seed=r, push_every=push_every)
        t0 = time.perf_counter()
        data = collect(xml, cfg)
        best = max(best, episodes * steps / (time.perf_counter() - t0))
    return best, data


def fmt_time(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.1f} min" if s >= 60 else f"{s:.1f} s"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 x 500 steps, one repeat (seconds)")
    ap.add_argument("--episodes", type=int, default=5, help="trajectories per measurement (default 5)")
    ap.add_argument("--steps", type=int, default=2000, help="steps per trajectory (default 2000)")
    ap.add_argument("--repeats", type=int, default=2, help="best of N (default 2)")
    args = ap.parse_args(argv)
    if args.quick:
        args.episodes, args.steps, args.repeats = 2, 500, 1
    n = args.episodes * args.steps
    print(f"bench_collect: {args.episodes} x {args.steps} steps per measurement, best of {args.repeats}"
          f"{'  [QUICK]' if args.quick else ''}")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"mujoco {mujoco.__version__}, numpy {np.__version__}, python {sys.version.split()[0]}; "
          "collection runs on one core")
    print()
    head = (f"{'model':<10} {'pushes':<14} {'steps/s':>9} {'x real time':>11} {'paper scale (2e6 steps)':>24} "
            f"{'bytes/step':>10} {'paper-scale size':>17} {'write MB/s':>10}")
    print(head)
    print("-" * len(head))
    for label, preset, seed in CASES:
        xml = build_model("ico", preset, seed=seed)
        for push_every in (None, 100):
            rate, data = bench(xml, args.episodes, args.steps, push_every, args.repeats)
            dt = data.dt
            per_step = nbytes(data) / n
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                save_dataset(os.path.join(tmp, "d.npz"), data)
                write = nbytes(data) / (time.perf_counter() - t0) / 1e6
            pushes = "none" if push_every is None else f"50 N / {push_every}"
            print(f"{label:<10} {pushes:<14} {rate:>9,.0f} {rate * dt:>11.1f} {fmt_time(PAPER_STEPS / rate):>24} "
                  f"{per_step:>10,.0f} {per_step * PAPER_STEPS / 1e9:>14.2f} GB {write:>10.0f}", flush=True)
    print()
    print("x real time: simulated seconds per wall-clock second (dt = 1 ms). Paper scale: projected wall time of "
          "1000 x 2000 steps in one process;\nepisodes are independent, so N processes divide it by about N. "
          "Size: float64 arrays in memory (the compressed .npz is smaller).")


if __name__ == "__main__":
    main()
