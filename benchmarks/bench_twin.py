"""Twin throughput: TensegrityIco-v0 on the identified engine, single and batched, beside the plant.

    python benchmarks/bench_twin.py [--steps 200] [--batched-steps 20] [--sizes 64 1024]
                                    [--device cpu] [--repeats 2]

One run, one table (env steps per second; random actions, frame_skip 20, i.e. 20 physics steps
per env step; resets on episode end count toward the time):

* the plant: ``gym.make("TensegrityIco-v0")`` (MuJoCo), single env;
* the twin: ``gym.make("TensegrityIco-v0", backend="identified")`` with the shipped model, single
  env, engine in float64 and in float32;
* the batched twin: ``gym.make_vec(..., num_envs=N, backend="identified")`` for each N, float64
  and float32: env steps/s = N x batched steps/s (autoreset included); for N > ``--chunk`` also
  with ``chunk_size=CHUNK`` (blocks of CHUNK envs per engine call);
* for the batched env, where the time goes: the engine alone (N copies, 20 substeps) and the
  observation/termination/reward of N envs with the batched functions vs a Python loop over the
  single-env functions (the choice made in ``tensegrity_gym.envs.vector``).

The best of ``--repeats`` runs is reported. Figures depend on the machine and on its load: read
them side by side, from one run.
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings

import gymnasium as gym
import numpy as np
import torch

import tensegrity_gym  # noqa: F401  (registers the env)
from tensegrity_gym.envs.tensegrity_ico_v0 import observation, reward_terms, termination_reason
from tensegrity_gym.envs.vector import batch_observation, batch_reward_terms, batch_termination_reason
from tensegrity_gym.plant import RodStates


def bench_single(steps: int, seed: int = 0, **make_kwargs) -> float:
    env = gym.make("TensegrityIco-v0", **make_kwargs)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps,) + env.action_space.shape).astype(np.float32)
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - t0
    env.close()
    return steps / elapsed


def bench_batched(n: int, steps: int, dtype: str, device: str, seed: int = 0,
                  chunk_size: int | None = None) -> float:
    venv = gym.make_vec("TensegrityIco-v0", num_envs=n, backend="identified", chunk_size=chunk_size,
                        backend_kwargs={"dtype": dtype, "device": device})
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps,) + venv.action_space.shape).astype(np.float32)
    venv.reset(seed=seed)
    venv.step(actions[0])  # warm-up
    t0 = time.perf_counter()
    for a in actions:
        venv.step(a)
    elapsed = time.perf_counter() - t0
    venv.close()
    return n * steps / elapsed


def bench_parts(n: int, dtype: str, device: str, seed: int = 0) -> dict[str, float]:
    """Seconds per batched env step spent in the engine, and in obs/termination/reward batched vs looped."""
    venv = gym.make_vec("TensegrityIco-v0", num_envs=n, backend="identified",
                        backend_kwargs={"dtype": dtype, "device": device})
    venv.reset(seed=seed)
    e, ph = venv.env, venv.physics
    ph.step(1)
    t0 = time.perf_counter()
    ph.step(e.frame_skip)
    if device != "cpu":
        torch.cuda.synchronize()
    engine = time.perf_counter() - t0
    pos, quat, vel, angvel = ph.states_numpy()
    rest = ph.rest_numpy()
    a = np.random.default_rng(seed).uniform(-1, 1, (n, e.action_space.shape[0]))
    com0 = pos.mean(axis=1)
    args = (e.actuated_index, e.rest_min, e.rest_max, e.exclude_current_positions)
    t0 = time.perf_counter()
    batch_observation(pos, quat, vel, angvel, rest, *args)
    batch_termination_reason(pos, quat, vel, angvel, rest, e.healthy_z_range)
    batch_reward_terms(com0, com0, a, e.dt, e.forward_reward_weight, e.ctrl_cost_weight)
    batched = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(n):
        s = RodStates(pos[i], quat[i], vel[i], angvel[i])
        observation(s, rest[i], *args)
        termination_reason(s, rest[i], e.healthy_z_range)
        reward_terms(com0[i], com0[i], a[i], e.dt, e.forward_reward_weight, e.ctrl_cost_weight)
    looped = time.perf_counter() - t0
    venv.close()
    return {"engine": engine, "batched": batched, "looped": looped}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200, help="env steps per single-env run")
    ap.add_argument("--batched-steps", type=int, default=20, help="vector steps per batched run (N=64)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 1024], help="batch sizes N")
    ap.add_argument("--device", default="cpu", help="torch device of the twin engine (cpu, cuda)")
    ap.add_argument("--chunk", type=int, default=64,
                    help="also time N > CHUNK in blocks of CHUNK envs (chunk_size; 0: skip)")
    ap.add_argument("--repeats", type=int, default=2, help="runs; the best is reported")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")

    def best(fn, *a, **k) -> float:
        return max(fn(*a, **k) for _ in range(args.repeats))

    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, "
          f"torch {torch.__version__} ({torch.get_num_threads()} threads), device {args.device}")
    rows = [("plant (MuJoCo), single", best(bench_single, args.steps * 4))]
    for dtype in ("float64", "float32"):
        rows.append((f"twin {dtype}, single",
                     best(bench_single, args.steps, backend="identified",
                          backend_kwargs={"dtype": dtype, "device": args.device})))
    for n in args.sizes:
        steps = max(2, args.batched_steps * 64 // n)
        for dtype in ("float64", "float32"):
            rows.append((f"twin {dtype}, batched N={n}", best(bench_batched, n, steps, dtype, args.device)))
        if args.chunk and n > args.chunk:
            rows.append((f"twin float64, batched N={n}, chunks of {args.chunk}",
                         best(bench_batched, n, steps, "float64", args.device, chunk_size=args.chunk)))
    plant = rows[0][1]
    print(f"{'TensegrityIco-v0 (frame_skip 20)':46s} {'env steps/s':>12s} {'vs plant':>9s}")
    for name, sps in rows:
        print(f"{name:46s} {sps:12,.0f} {sps / plant:8.2f}x")
    for n in args.sizes:
        p = bench_parts(n, "float64", args.device)
        print(f"N={n} float64, per batched step: engine (20 substeps) {p['engine'] * 1e3:,.1f} ms; "
              f"obs+termination+reward batched {p['batched'] * 1e3:,.2f} ms, looped over N "
              f"{p['looped'] * 1e3:,.1f} ms")


if __name__ == "__main__":
    main()
