"""Env throughput: TensegrityIco-v0 steps per second on the MuJoCo plant (single process, CPU).

    python benchmarks/bench_env.py [--steps 5000] [--frame-skip 20] [--repeats 3]

Prints env steps/s (random actions; resets on termination count toward the time), the physics
steps/s this implies, the real-time factor, and, for reference, the bare plant (``MujocoPlant.step``
without the env: motors + mj_step). The best of ``--repeats`` runs is reported.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

import tensegrity_gym  # noqa: F401
from tensegrity_gym.envs.tensegrity_ico_v0 import TensegrityIcoEnv


def bench_env(steps: int, frame_skip: int, seed: int = 0) -> tuple[float, int]:
    env = TensegrityIcoEnv(frame_skip=frame_skip)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps, env.action_space.shape[0])).astype(np.float32)
    env.reset(seed=seed)
    resets = 0
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, _, _ = env.step(a)
        if terminated:
            env.reset()
            resets += 1
    elapsed = time.perf_counter() - t0
    env.close()
    return steps / elapsed, resets


def bench_plant(steps: int) -> float:
    env = TensegrityIcoEnv()
    plant = env.backend.plant
    plant.reset()
    plant.set_targets(plant.motor.rest_min)
    t0 = time.perf_counter()
    for _ in range(steps):
        plant.step()
    return steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=5000, help="env steps per run")
    ap.add_argument("--frame-skip", type=int, default=20, help="physics steps per env step")
    ap.add_argument("--repeats", type=int, default=3, help="runs; the best is reported")
    args = ap.parse_args()

    runs = [bench_env(args.steps, args.frame_skip, seed=i) for i in range(args.repeats)]
    sps, resets = max(runs)
    env = TensegrityIcoEnv(frame_skip=args.frame_skip)
    physics_dt = env.backend.dt
    plant_sps = max(bench_plant(args.steps * args.frame_skip // 4) for _ in range(args.repeats))
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
    print(f"TensegrityIco-v0 (mujoco plant, frame_skip={args.frame_skip}, control {1 / env.dt:g} Hz): "
          f"{sps:,.0f} env steps/s (best of {args.repeats} x {args.steps} random-action steps, "
          f"{resets} resets)")
    print(f"  = {sps * args.frame_skip:,.0f} physics steps/s, {sps * env.dt:,.1f}x real time")
    print(f"bare plant (MujocoPlant.step, motors + mj_step): {plant_sps:,.0f} physics steps/s "
          f"({plant_sps * physics_dt:,.1f}x real time); env overhead "
          f"{100 * (1 - sps * args.frame_skip / plant_sps):.0f}%")


if __name__ == "__main__":
    main()
