"""Twin throughput: TensegrityIco-v0 on the identified engine beside the MuJoCo plant, as found and loaded.

    python benchmarks/bench_twin.py [--sizes 256 1024] [--steps 200] [--repeats 2] [--no-load]
                                    [--no-ppo] [--ppo-steps 8192] [--device cpu]

One run, one table of env steps per second (random actions, frame_skip 20: 20 physics steps per
env step; resets on episode end count toward the time), every row measured side by side:

* the plant: ``gym.make("TensegrityIco-v0")`` (MuJoCo), single env;
* the single twin: ``gym.make("TensegrityIco-v0", backend="identified")`` with the shipped model
  and the defaults (float32, one intra-op thread, the substep compiled), and the same eager
  (``compile=False``);
* the batched twin: ``gym.make_vec(..., num_envs=N, backend="identified")`` for each N, defaults,
  and the same with torch's own thread setting (``num_threads=None``: 2 threads here) and eager;
* each row twice: on the machine as it is ("as found") and with ONE busy process beside it (a
  Python busy loop started by this script, killed at the end and ending by itself if the script
  dies),
  the situation of a laptop with a browser open;
* where a single twin env step goes (a profiled line): the physics' share of the env step, and per
  compiled substep torch.compile's guard check against the compiled graph;
* SB3 PPO training steps/s (``learn``: rollouts and updates) through
  :class:`~tensegrity_gym.envs.sb3.SB3VecEnvAdapter`, on the batched twin and on the plant
  (``gym.make_vec`` of single plants), same PPO settings.

Compilation happens while the envs are built (timed, printed): inductor caches its work on disk, so
a second run compiles faster. The best of ``--repeats`` runs is reported. The machine's load average
is printed: on a shared machine the figures move with it; read the ratios, within one run.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator

import gymnasium as gym
import numpy as np
import torch

import tensegrity_gym  # noqa: F401  (registers the env)


@contextlib.contextmanager
def busy_process(on: bool) -> Iterator[None]:
    """One CPU-bound process beside the benchmark while the block runs (killed after, always)."""
    if not on:
        yield
        return
    # the busy loop ends by itself if this process dies (its parent changes)
    proc = subprocess.Popen([sys.executable, "-c", "import os\np = os.getppid()\nwhile os.getppid() == p: pass"])
    try:
        time.sleep(0.5)
        yield
    finally:
        proc.kill()
        proc.wait()


def single_runner(env: gym.Env, steps: int, seed: int = 0) -> Callable[[], float]:
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps,) + env.action_space.shape).astype(np.float32)
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up (and compilation)

    def run() -> float:
        env.reset(seed=seed)
        t0 = time.perf_counter()
        for a in actions:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        return steps / (time.perf_counter() - t0)

    return run


def batched_runner(venv: gym.vector.VectorEnv, steps: int, seed: int = 0) -> Callable[[], float]:
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps,) + venv.action_space.shape).astype(np.float32)
    venv.reset(seed=seed)
    venv.step(actions[0])  # warm-up (and compilation)

    def run() -> float:
        venv.reset(seed=seed)
        t0 = time.perf_counter()
        for a in actions:
            venv.step(a)
        return venv.num_envs * steps / (time.perf_counter() - t0)

    return run


def ppo_rate(venv: gym.vector.VectorEnv, total: int, seed: int = 0) -> float:
    """SB3 PPO ``learn`` steps/s (env steps collected and trained on, per wall second)."""
    from stable_baselines3 import PPO

    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    n = venv.num_envs
    model = PPO("MlpPolicy", SB3VecEnvAdapter(venv), n_steps=max(8, 1024 // n), batch_size=256,
                n_epochs=2, seed=seed, device="cpu", verbose=0)
    model.learn(total_timesteps=n * max(8, 1024 // n))  # warm-up: one rollout and update
    t0 = time.perf_counter()
    model.learn(total_timesteps=total, reset_num_timesteps=True)
    return model.num_timesteps / (time.perf_counter() - t0)


def single_env_profile(twin: gym.Env, plant: gym.Env, steps: int = 50) -> None:
    """Where a single twin env step goes: the 20 physics substeps against the rest of the env step,
    and per compiled substep torch.compile's guard check (``TorchDynamo Cache Lookup``) against
    the compiled graph (kernels and their Python wrapper), from the torch profiler."""
    from torch.profiler import ProfilerActivity, profile

    ph = twin.unwrapped.backend.physics
    spent: list[float] = []
    advance = ph._advance

    def timed(*a: object, **k: object) -> object:
        t = time.perf_counter()
        out = advance(*a, **k)
        spent.append(time.perf_counter() - t)
        return out

    actions = np.random.default_rng(1).uniform(-1, 1, (steps,) + twin.action_space.shape).astype(np.float32)
    twin.reset(seed=1)
    plant.reset(seed=1)
    ph._advance = timed
    try:
        t0 = time.perf_counter()
        for a in actions:
            twin.step(a)
        t_twin = (time.perf_counter() - t0) / steps
        t0 = time.perf_counter()
        for a in actions:
            plant.step(a)
        t_plant = (time.perf_counter() - t0) / steps
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for a in actions[:10]:
                twin.step(a)
    finally:
        ph._advance = advance
    n_sub = 10 * twin.unwrapped.frame_skip
    parts = {"guards": 0.0, "graph": 0.0}
    for ev in prof.key_averages():
        if ev.key == "TorchDynamo Cache Lookup":
            parts["guards"] += ev.self_cpu_time_total / n_sub
        elif "CompiledFxGraph" in ev.key:
            parts["graph"] += ev.cpu_time_total / n_sub
    print(f"single env step: twin {t_twin * 1e6:,.0f} us, of which the physics (20 substeps) "
          f"{np.mean(spent) * 1e6:,.0f} us ({np.mean(spent) / t_twin:.0%}); plant {t_plant * 1e6:,.0f} us "
          f"(ratio {t_plant / t_twin:.2f}x); per compiled substep (profiler): guard check "
          f"{parts['guards']:.0f} us, compiled graph {parts['graph']:.0f} us; load average {os.getloadavg()[0]:.1f}")


def batched_substep_profile(venv: gym.vector.VectorEnv, substeps: int = 400) -> dict[str, float]:
    """Where one compiled substep of a batched twin goes, us per call (cProfile over ``substeps``
    calls, outside any env step): dynamo's guard check and the calling layers, inductor's wrapper (the
    Python of its ``call``, allocating the graph's intermediate buffers one tensor each), and the
    fused C++ kernels doing the arithmetic.  With ``cpp_wrapper`` the wrapper is C++ and its
    allocations are counted with the kernels (``inductor_entry_cpp``)."""
    import cProfile
    import pstats

    ph = venv.physics
    n = max(1, substeps // 20)
    for _ in range(2):  # warm
        ph.step(20)
    t0 = time.perf_counter()
    for _ in range(n):
        ph.step(20)
    plain = (time.perf_counter() - t0) / (20 * n) * 1e6
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(n):
        ph.step(20)
    prof.disable()
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    generated = os.path.realpath(cache_dir())  # where inductor writes the wrapper's module
    stats = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tottime, cumtime, callers)
    calls = 20 * n
    part = {"kernels": 0.0, "allocations": 0.0, "wrapper": 0.0, "total": 0.0, "buffers": 0.0}
    for (file, _line, name), (_cc, nc, tt, ct, _) in stats.items():
        if ".kernel.kernel" in name or "inductor_entry_cpp" in name:
            part["kernels"] += tt
        elif "_empty_strided" in name or "_reinterpret_tensor" in name or "assert_size_stride" in name:  # and views
            part["allocations"] += tt
            if "_empty_strided" in name:
                part["buffers"] += nc / calls
        elif name == "call" and os.path.realpath(file).startswith(generated):
            part["wrapper"] += tt
        elif name == "_eager_substep":
            part["total"] += ct
    out = {k: (v if k == "buffers" else v / calls * 1e6) for k, v in part.items()}
    out["other"] = out["total"] - out["kernels"] - out["allocations"] - out["wrapper"]
    out["unprofiled"] = plain
    return out


def main() -> None:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the finally blocks (kill the load)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024], help="batch sizes N")
    ap.add_argument("--steps", type=int, default=200, help="env steps per single-env run")
    ap.add_argument("--batched-steps", type=int, default=2048,
                    help="env steps (N x vector steps) per batched run, at least 2 vector steps")
    ap.add_argument("--repeats", type=int, default=2, help="runs per row; the best is reported")
    ap.add_argument("--device", default="cpu", help="torch device of the twin engine (cpu, cuda)")
    ap.add_argument("--no-load", action="store_true", help="skip the rows with a busy process")
    ap.add_argument("--no-ppo", action="store_true", help="skip SB3 PPO")
    ap.add_argument("--ppo-steps", type=int, default=8192, help="PPO timesteps per measurement")
    ap.add_argument("--ppo-envs", type=int, default=64, help="batched twin envs for PPO (plant: 8)")
    ap.add_argument("--substep-profile", action="store_true",
                    help="only: where one compiled substep of the batched twin goes, per size of --sizes")
    ap.add_argument("--cpp-wrapper", action="store_true",
                    help="with --substep-profile: inductor's C++ wrapper for the batched twin too (compile timed)")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    dev = args.device
    kw = {"dtype": "float32", "device": dev}

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}; python {platform.python_version()}, torch {torch.__version__} "
          f"(global threads {torch.get_num_threads()}), device {dev}")
    if args.substep_profile:
        if args.cpp_wrapper:
            from tensegrity_gym.backends.twin_physics import TwinPhysics

            TwinPhysics._inductor_options = lambda self: {"cpp_wrapper": True}
        for n in args.sizes:
            venv = gym.make_vec("TensegrityIco-v0", num_envs=n, backend="identified", backend_kwargs=kw)
            venv.reset(seed=0)
            venv.physics.step(1)  # compiles (or loads) the substep
            print(f"N={n}: substep compiled in {venv.physics.compile_seconds:.0f} s ({venv.physics.cache_status})")
            p = batched_substep_profile(venv)
            print(f"N={n}: one compiled substep {p['unprofiled']:.0f} us ({p['unprofiled'] / n:.1f} us an env); "
                  f"profiled {p['total']:.0f} us: kernels {p['kernels']:.0f}, the wrapper's {p['buffers']:.0f} "
                  f"buffer allocations {p['allocations']:.0f}, the wrapper's Python {p['wrapper']:.0f}, guards and "
                  f"calling layers {p['other']:.0f}; load average {os.getloadavg()[0]:.1f}", flush=True)
        return
    cases: list[tuple[str, Callable[[], float]]] = []
    t0 = time.perf_counter()
    cases.append(("plant (MuJoCo), single", single_runner(gym.make("TensegrityIco-v0"), args.steps * 2)))
    twin = gym.make("TensegrityIco-v0", backend="identified", backend_kwargs=kw)
    cases.append(("twin, single (defaults)", single_runner(twin, args.steps)))
    ph = twin.unwrapped.backend.physics
    print(f"single twin: compiled {ph.compiled}, compile {ph.compile_seconds:.1f} s, threads {ph.num_threads}")
    if ph.compiled:
        single_env_profile(twin, gym.make("TensegrityIco-v0"))
    cases.append(("twin, single, eager", single_runner(gym.make(
        "TensegrityIco-v0", backend="identified", backend_kwargs={**kw, "compile": False}), args.steps)))
    for n in args.sizes:
        steps = max(2, args.batched_steps // n)
        for label, extra in (("defaults", {}), ("torch's threads", {"num_threads": None}),
                             ("eager", {"compile": False})):
            venv = gym.make_vec("TensegrityIco-v0", num_envs=n, backend="identified",
                                backend_kwargs={**kw, **extra})
            cases.append((f"twin, batched N={n}, {label}", batched_runner(venv, steps)))
            if label == "defaults":
                print(f"N={n}: compile {venv.physics.compile_seconds:.1f} s")
    print(f"set-up (env builds, compilation, warm-up): {time.perf_counter() - t0:.0f} s")

    conditions = ["as found"] + ([] if args.no_load else ["1 busy process"])
    table: dict[str, dict[str, float]] = {name: {} for name, _ in cases}
    for cond in conditions:
        with busy_process(cond != "as found"):
            load = os.getloadavg()[0]
            for name, run in cases:
                table[name][cond] = max(run() for _ in range(args.repeats))
        print(f"{cond}: load average {load:.1f} at the start")

    head = f"{'TensegrityIco-v0, env steps/s':40s}" + "".join(f"{c:>16s} {'vs plant':>9s}" for c in conditions)
    print(head)
    plant = table[cases[0][0]]
    for name, _ in cases:
        row = table[name]
        print(f"{name:40s}" + "".join(f"{row[c]:16,.0f} {row[c] / plant[c]:8.2f}x" for c in conditions))

    if not args.no_ppo:
        for cond in conditions:
            with busy_process(cond != "as found"):
                twin_v = gym.make_vec("TensegrityIco-v0", num_envs=args.ppo_envs, backend="identified",
                                      backend_kwargs=kw)
                plant_v = gym.make_vec("TensegrityIco-v0", num_envs=8)
                r_twin = ppo_rate(twin_v, args.ppo_steps)
                r_plant = ppo_rate(plant_v, args.ppo_steps)
            print(f"SB3 PPO learn, {cond}: twin (batched, N={args.ppo_envs}) {r_twin:,.0f} steps/s; "
                  f"plant (8 envs, SyncVectorEnv) {r_plant:,.0f} steps/s; ratio {r_twin / r_plant:.2f}x")


if __name__ == "__main__":
    main()
