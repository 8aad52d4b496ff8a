"""Training on the twin against training on the plant: wall clock, and the plant steps each needs.

    python benchmarks/bench_train.py [--identified identified/data/robot.json] [--timesteps 100000]
                                     [--seed 0] [--episodes 10] [--target 0.5] [--points 8]
                                     [--threads 1] [--no-curve] [--out runs/bench_train]

One run, one machine, the same algorithm with the same settings (``tensegrity train``'s PPO,
:data:`tensegrity_gym.training.PPO_HYPERPARAMETERS`, one torch thread), one after the other:

1. ``twin``: ``--timesteps`` steps on the batched identified twin (64 envs, one engine call for all;
   MuJoCo never steps), then the policy on the plant (``tensegrity gap``'s evaluation,
   ``--episodes`` episodes from reset seeds 0..);
2. ``plant``: the same steps on the MuJoCo plant (8 envs, SubprocVecEnv), keeping the policy after
   every update (``snapshots=True``), and ``--points`` of the snapshots (evenly spaced) and the final
   policy evaluated on the plant from the same reset seeds: the plant-trained policy's progress
   versus the plant steps it was trained on.

It prints the wall clock and CPU time (this process and the plant's SubprocVecEnv workers) of
each training and their ratio (on a machine shared with other jobs the plant's 8 worker processes
take a larger share of the cores than the twin's one process: read the CPU time there), the learning curve of direct training on the plant, the first
plant step count at which that curve reaches the twin policy's plant progress (and ``--target``),
and the plant data the twin pipeline used: the collection of ``scripts/make_shipped_model.sh``
(10 episodes x 3000 physics steps of 1 ms = 30 s of robot time = 1,500 control steps), against
control steps of 20 ms on the plant for direct training. Results also go to ``OUT/bench_train.json``.

The machine's load average is printed: on a shared machine read the ratio, within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

#: The plant data behind the shipped model (scripts/make_shipped_model.sh): episodes x physics steps.
COLLECTION = {"episodes": 10, "physics_steps": 3000, "physics_dt_s": 0.001}


#: CPU seconds of SubprocVecEnv workers, read just before they close: SB3 starts them through a
#: forkserver, so they are not this process's children and RUSAGE_CHILDREN misses them.
WORKER_CPU = [0.0]


def _proc_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def count_worker_cpu() -> None:
    """Make SubprocVecEnv.close add its workers' CPU time to :data:`WORKER_CPU` (Linux /proc)."""
    from stable_baselines3.common.vec_env import SubprocVecEnv

    close = SubprocVecEnv.close

    def counted(self) -> None:
        for proc in getattr(self, "processes", []):
            try:
                WORKER_CPU[0] += _proc_cpu_s(proc.pid)
            except (OSError, ValueError, IndexError):
                pass
        close(self)

    SubprocVecEnv.close = counted  # type: ignore[method-assign]


def cpu_s() -> float:
    """CPU seconds of this process, its finished children and the SubprocVecEnv workers."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime + WORKER_CPU[0]


def plant_progress(policy: str, identified: str, episodes: int) -> float:
    """Mean forward progress (m) of ``policy`` on the plant, reset seeds 0 .. episodes - 1."""
    from tensegrity_gym.gap import _plant_venv, run_episodes
    from tensegrity_gym.training import load_policy, plant_mjcf

    pol = load_policy(policy)
    venv = _plant_venv(plant_mjcf(identified), episodes, pol.episode_steps, pol.env_kwargs)
    try:
        return float(run_episodes(venv, pol.act, list(range(episodes))).progress.mean())
    finally:
        venv.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--identified", default=os.path.join(ROOT, "identified", "data", "robot.json"))
    ap.add_argument("--timesteps", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=10, help="evaluation episodes on the plant")
    ap.add_argument("--target", type=float, default=0.5, help="a progress (m) to report the plant steps of")
    ap.add_argument("--points", type=int, default=8,
                    help="snapshots of the plant run evaluated (evenly spaced; plus the final policy)")
    ap.add_argument("--out", default=os.path.join(ROOT, "runs", "bench_train"))
    ap.add_argument("--threads", type=int, default=1, help="torch threads of both trainings (default 1)")
    ap.add_argument("--no-curve", action="store_true",
                    help="wall clock and CPU only: no evaluation, no learning curve of the plant run")
    args = ap.parse_args()
    if sys.platform.startswith("linux"):
        count_worker_cpu()

    import tensegrity_gym  # noqa: F401
    from tensegrity_gym.gap import measure_gap
    from tensegrity_gym.training import TrainConfig, snapshot_path, train

    os.makedirs(args.out, exist_ok=True)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {args.timesteps} steps, seed {args.seed}, "
          f"{args.threads} torch thread(s)")
    rows = {}
    for where in ("twin", "plant"):
        out = os.path.join(args.out, f"{where}.zip")
        cfg = TrainConfig(timesteps=args.timesteps, seed=args.seed, identified=args.identified,
                          plant=where == "plant", snapshots=where == "plant" and not args.no_curve,
                          threads=args.threads)
        c0, t0 = cpu_s(), time.perf_counter()
        r = train(cfg, out, progress=False)
        wall, cpu = time.perf_counter() - t0, cpu_s() - c0
        rows[where] = {"wall_s": wall, "cpu_s": cpu, "train_wall_s": r.wall_s, "timesteps": r.timesteps,
                       "envs": cfg.n_envs, "steps_per_s": r.timesteps / wall, "policy": out,
                       "load_after": os.getloadavg()[0]}
        print(f"{where:5s}: {r.timesteps} steps, {cfg.n_envs} envs: {wall:.0f} s wall ({r.timesteps / wall:.0f} "
              f"steps/s), {cpu:.0f} s CPU; load average {os.getloadavg()[0]:.1f}", flush=True)
    ratio = rows["plant"]["wall_s"] / rows["twin"]["wall_s"]
    print(f"twin {ratio:.2f}x faster than the plant (wall clock), "
          f"{rows['plant']['cpu_s'] / rows['twin']['cpu_s']:.2f}x in CPU time")
    if args.no_curve:
        with open(os.path.join(args.out, "bench_train.json"), "w") as fh:
            json.dump({"rows": rows, "twin_over_plant_speed": ratio}, fh, indent=1)
        return

    gap = measure_gap(rows["twin"]["policy"], args.identified, args.episodes, seed=0, progress=False)
    twin_on_plant = gap["plant"]["progress_m"]
    print(f"twin policy: {gap['twin']['progress_m']:.3f} m on the twin, {twin_on_plant:.3f} m on the plant, "
          f"random {gap['random_plant']['progress_m']:.3f} m")

    curve = []
    plant_out = rows["plant"]["policy"]
    stem = os.path.basename(plant_out).removesuffix(".zip") + ".step"
    steps = sorted(int(f[len(stem):-4]) for f in os.listdir(args.out) if f.startswith(stem) and f.endswith(".zip"))
    if len(steps) > args.points:  # evenly spaced, the last included
        steps = [steps[round(i)] for i in np.linspace(len(steps) - 1, 0, args.points)][::-1]
    for n in steps:
        curve.append((n, plant_progress(snapshot_path(plant_out, n), args.identified, args.episodes)))
    curve.append((rows["plant"]["timesteps"], plant_progress(plant_out, args.identified, args.episodes)))
    print("direct training on the plant: progress on the plant (m) after N plant control steps")
    for n, p in curve:
        print(f"  {n:7d}  {p:7.3f}")

    coll_physics = COLLECTION["episodes"] * COLLECTION["physics_steps"]
    coll_robot_s = coll_physics * COLLECTION["physics_dt_s"]
    dt = 0.02  # the env's control period: frame_skip 20 x 1 ms
    anchors = {}
    for name, level in (("twin_policy_on_plant", twin_on_plant), ("target", args.target)):
        first = next((n for n, p in curve if p >= level), None)
        anchors[name] = {"progress_m": level, "plant_control_steps": first,
                         "plant_robot_s": None if first is None else first * dt,
                         "pipeline_over_direct": None if first is None else coll_robot_s / (first * dt)}
        if first is None:
            print(f"  direct training did not reach {level:.3f} m within {rows['plant']['timesteps']} steps")
        else:
            print(f"  {level:.3f} m reached after {first} plant control steps ({first * dt:.0f} s of robot time); "
                  f"the twin pipeline used {coll_robot_s:.0f} s of plant time (collection): "
                  f"{100 * coll_robot_s / (first * dt):.1f} % of it")
    result = {"rows": rows, "twin_over_plant_speed": ratio, "gap": {k: gap[k] for k in ("twin", "plant", "random_plant")},
              "plant_curve": curve, "anchors": anchors,
              "collection": {**COLLECTION, "robot_s": coll_robot_s, "control_steps": coll_robot_s / dt}}
    with open(os.path.join(args.out, "bench_train.json"), "w") as fh:
        json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main()
