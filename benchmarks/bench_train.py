"""Training on the twin against training on the plant: wall clock side by side, where the time goes,
and the plant steps each needs.

    python benchmarks/bench_train.py [--identified identified/data/robot.json] [--timesteps 100000]
                                     [--seed 0] [--busy both|none|only] [--twin-envs 64] [--plant-envs 8]
                                     [--batch-size B] [--n-epochs E] [--rollout R] [--fused-adam]
                                     [--curve] [--episodes 10] [--target 0.5] [--points 8]
                                     [--threads 1] [--physics-dt S] [--out runs/bench_train]
    python benchmarks/bench_train.py --updates      # PPO's update alone, per mini-batch size

One run, one machine, the same algorithm with the same settings on both sides (``tensegrity
train``'s PPO, :data:`tensegrity_gym.training.PPO_HYPERPARAMETERS` with the overrides given here,
one torch thread), one after the other, first on the machine as it is (``quiet``), then with one
more process busy on one core (a Python busy loop this script starts and stops: ``busy``):

* ``twin``: ``--timesteps`` steps on the batched identified twin (``--twin-envs`` envs in this one
  process, one engine call for all; MuJoCo never steps);
* ``plant``: the same steps on the MuJoCo plant (``--plant-envs`` envs, SubprocVecEnv: one process
  each).

Only the number of envs differs (the same transitions per update, ``--rollout``, over all envs).
Each training's wall clock is split into: the twin's compilation (its compiled substep loaded
from the cache on disk, :mod:`tensegrity_gym.backends.substep_cache`, or compiled and stored there
when no earlier run of the same model stored it: the table says which; with
``TENSEGRITY_TWIN_CACHE=0`` a plain ``torch.compile`` from inductor's own cache; a short warm-up
training of the twin first stores it where no earlier run did, its time printed apart, unless
``--cold-twin``), the env's steps (the twin's engine and the env around it / waiting for the plant's
worker processes), SB3's own work while collecting (policy forward pass, action sampling, rollout
buffer, VecNormalize, VecMonitor, callbacks: the rest of ``collect_rollouts``) and PPO's updates
(``PPO.train``: the gradient epochs). CPU time counts this process, its children and the
SubprocVecEnv workers (read from /proc before they close). The table prints both conditions side by
side with the ratio plant / twin of wall clocks; results go to ``OUT/bench_train.json``.

``--curve`` (quiet run only) adds what the plant steps buy: the twin policy on the plant
(``tensegrity gap``'s evaluation, ``--episodes`` episodes from reset seeds 0..), and the learning
curve of direct training on the plant (the policy after every update kept, ``--points`` of them
evaluated), the first plant step count at which it reaches the twin policy's plant progress (and
``--target``), against the plant data of the twin pipeline: the collection of
``scripts/make_shipped_model.sh`` (10 episodes x 3000 physics steps of 1 ms = 30 s of robot time).

``--updates`` times PPO's update alone (``PPO.train`` on a buffer of random transitions of the
env's shapes) per mini-batch size and with Adam's fused CPU kernel, and splits its time into a
fixed cost per mini-batch (SB3's Python, autograd and optimizer calls) and a cost per transition.

The load average is printed before and after every training: timings beside other jobs are not a
quiet machine's; read the ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from typing import Self

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

#: The plant data behind the shipped model (scripts/make_shipped_model.sh): episodes x physics steps.
COLLECTION = {"episodes": 10, "physics_steps": 3000, "physics_dt_s": 0.001}


#: CPU seconds of SubprocVecEnv workers, read just before they close: SB3 starts them through a
#: forkserver, so they are not this process's children and RUSAGE_CHILDREN misses them.
WORKER_CPU = [0.0]
#: Seconds spent in each part of the current training (see :func:`instrument`).
PARTS: dict[str, float] = {}
#: Where the twin's compiled substep came from in the current training (``TwinPhysics.cache_status``).
CACHE_STATUS: list[str | None] = []


def _proc_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _timed(cls: type, name: str, part: str) -> None:
    """Add the seconds spent in ``cls.name`` to :data:`PARTS` ``[part]``."""
    orig = getattr(cls, name)

    def wrapper(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return orig(self, *args, **kwargs)
        finally:
            PARTS[part] = PARTS.get(part, 0.0) + time.perf_counter() - t0

    setattr(cls, name, wrapper)


def instrument() -> None:
    """Time the parts of a training (:data:`PARTS`): PPO's collection and updates, the env's steps
    (the twin's adapter, the plant's SubprocVecEnv), the twin's compilation; count the SubprocVecEnv
    workers' CPU time as they close (Linux /proc)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from tensegrity_gym.backends import twin_physics
    from tensegrity_gym.backends.twin_physics import TwinPhysics
    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    _timed(PPO, "collect_rollouts", "collect")
    _timed(PPO, "train", "updates")
    _timed(SB3VecEnvAdapter, "step_wait", "env")
    _timed(SubprocVecEnv, "step_wait", "env")
    _timed(SubprocVecEnv, "step_async", "env")
    _timed(TwinPhysics, "_compile_and_advance", "compile")
    compile_and_advance = TwinPhysics._compile_and_advance

    def recorded(self, *args, **kwargs):
        try:
            return compile_and_advance(self, *args, **kwargs)
        finally:
            CACHE_STATUS.append(self.cache_status)

    TwinPhysics._compile_and_advance = recorded  # type: ignore[method-assign]
    prefetch = twin_physics.prefetch

    def timed_prefetch() -> None:  # the start of the twin's compilation, while its env is built
        t0 = time.perf_counter()
        try:
            prefetch()
        finally:
            PARTS["prefetch"] = PARTS.get("prefetch", 0.0) + time.perf_counter() - t0

    twin_physics.prefetch = timed_prefetch
    close = SubprocVecEnv.close

    def counted(self) -> None:
        if sys.platform.startswith("linux"):
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


def train_timed(cfg, out: str) -> dict:
    """Train ``cfg`` into ``out``; its wall clock, CPU time and parts (:func:`instrument`)."""
    from tensegrity_gym.training import train

    PARTS.clear()
    load0 = os.getloadavg()[0]
    c0, t0 = cpu_s(), time.perf_counter()
    r = train(cfg, out, progress=False)
    wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    parts = dict(PARTS)
    first_step = parts.get("compile", 0.0)  # the first step: load or compile, inside an env step
    prefetch = parts.get("prefetch", 0.0)  # its start, while the env is built
    env = parts.get("env", 0.0) - first_step
    collect = parts.get("collect", 0.0)
    updates = parts.get("updates", 0.0)
    return {"wall_s": wall, "cpu_s": cpu, "timesteps": int(r.timesteps), "envs": cfg.n_envs,
            "steps_per_s": r.timesteps / wall, "policy": out, "load_before": load0, "load_after": os.getloadavg()[0],
            "compile_s": first_step + prefetch, "compile_cache": CACHE_STATUS[0] if CACHE_STATUS else None,
            "env_s": env, "sb3_collect_s": collect - env - first_step, "updates_s": updates,
            "other_s": wall - collect - updates - prefetch, "hyperparameters": cfg.algo_kwargs()}


class Busy:
    """One more process busy on one core (a Python loop) while the block runs."""

    def __enter__(self) -> Self:
        self.proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        return self

    def __exit__(self, *exc) -> None:
        self.proc.kill()
        self.proc.wait()


ROWS = (("wall clock (s)", "wall_s"), ("  twin compilation", "compile_s"),
        ("  env steps (twin engine / plant workers)", "env_s"),
        ("  SB3 while collecting (policy, buffer, VecNormalize)", "sb3_collect_s"),
        ("  PPO updates (gradient epochs)", "updates_s"), ("  other (setup, saving)", "other_s"),
        ("CPU time (s)", "cpu_s"), ("process wall clock (s): imports, training, exit", "process_wall_s"),
        ("env steps per second", "steps_per_s"), ("load average after", "load_after"))


def print_table(runs: dict) -> None:
    """Both conditions side by side: twin, plant, plant / twin."""
    conds = list(runs)
    head = f"{'':54s}" + "".join(f"{c + ': twin':>14s}{'plant':>10s}{'plant/twin':>12s}" for c in conds)
    print(head)
    for label, key in ROWS:
        line = f"{label:54s}"
        for c in conds:
            tw, pl = runs[c]["twin"][key], runs[c]["plant"][key]
            ratio = f"{pl / tw:.2f}x" if key in ("wall_s", "cpu_s", "process_wall_s") and tw > 0 else ""
            fmt = "{:14.0f}{:10.0f}" if key == "steps_per_s" else "{:14.1f}{:10.1f}"
            line += fmt.format(tw, pl) + f"{ratio:>12s}"
        print(line)
    for c in conds:
        r = runs[c]
        share = r["twin"]["updates_s"] + r["twin"]["sb3_collect_s"]
        print(f"{c}: the twin's compiled substep: {r['twin'].get('compile_cache')} "
              f"({r['twin']['compile_s']:.1f} s; 'hit': loaded from the cache on disk, 'stored': compiled "
              "now, the first run of this model)")
        print(f"{c}: the twin trains {r['plant']['wall_s'] / r['twin']['wall_s']:.2f}x faster than the plant "
              f"(wall clock); SB3's own work (updates + collection overhead) is {100 * share / r['twin']['wall_s']:.0f} % "
              f"of the twin's wall clock, the twin's engine and env {100 * r['twin']['env_s'] / r['twin']['wall_s']:.0f} %")


def updates_table(rollout: int, repeats: int = 3) -> dict:
    """PPO's update alone (``PPO.train`` on a full rollout buffer of random transitions of the
    env's shapes: 133 observations, 24 actions), per mini-batch size and with Adam's fused kernel:
    what SB3's per-mini-batch overhead costs. Same process, one torch thread, best of ``repeats``."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from tensegrity_gym.training import PPO_HYPERPARAMETERS

    torch.set_num_threads(1)

    class Shapes(gym.Env):
        observation_space = gym.spaces.Box(-10, 10, (133,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (24,), np.float32)

        def reset(self, seed=None, options=None):
            return self.observation_space.sample(), {}

        def step(self, action):
            return self.observation_space.sample(), 0.0, False, False, {}

    venv = DummyVecEnv([Shapes for _ in range(64)])
    fused = {"policy_kwargs": {"optimizer_kwargs": {"fused": True}}}
    plain = {"policy_kwargs": {}}  # torch's default Adam (the defaults hold the fused one)
    settings = [("128", {"batch_size": 128, **plain}), ("128, fused Adam", {"batch_size": 128, **fused}),
                ("256", {"batch_size": 256, **plain}), ("512", {"batch_size": 512, **plain}),
                ("1024", {"batch_size": 1024, **plain}), ("1024, fused Adam (the default)", {"batch_size": 1024, **fused}),
                (str(rollout), {"batch_size": rollout, **plain})]
    epochs = PPO_HYPERPARAMETERS["n_epochs"]
    rows = {}
    print(f"PPO update alone: {rollout} transitions x {epochs} epochs, random data of the env's shapes")
    for name, kw in settings:
        hp = {**PPO_HYPERPARAMETERS, **kw}
        model = PPO("MlpPolicy", venv, n_steps=rollout // 64, device="cpu", seed=0, **hp)
        model.learn(rollout)  # fills the buffer (and makes one update: warm)
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            model.train()
            best = min(best, time.perf_counter() - t0)
        minibatches = epochs * -(-rollout // hp["batch_size"])
        rows[name] = {"update_s": best, "minibatches": minibatches, "per_minibatch_ms": 1e3 * best / minibatches}
        print(f"  mini-batch {name:18s} {1e3 * best:7.0f} ms per update ({minibatches:4d} mini-batches, "
              f"{1e3 * best / minibatches:5.2f} ms each)", flush=True)
    # time = a * mini-batches + b * transitions x epochs, from the smallest and the largest batch
    lo, hi = rows["128"], rows[str(rollout)]
    a = (lo["update_s"] - hi["update_s"]) / (lo["minibatches"] - hi["minibatches"])
    b = (hi["update_s"] - a * hi["minibatches"]) / (rollout * epochs)
    share = a * lo["minibatches"] / lo["update_s"]
    print(f"  fixed cost per mini-batch {1e3 * a:.2f} ms, per transition and epoch {1e6 * b:.1f} us: at mini-batches "
          f"of 128, {100 * share:.0f} % of an update is SB3's per-mini-batch overhead (Python, autograd, optimizer "
          "calls), not arithmetic")
    return {"rows": rows, "per_minibatch_s": a, "per_sample_epoch_s": b, "overhead_share_at_128": share}


def _physics_dt(text: str) -> float | str | None:
    """``--physics-dt``: ``"auto"``, ``None`` for ``model`` (the model's own dt) or seconds."""
    return text if text == "auto" else None if text == "model" else float(text)


def _step_line(args: argparse.Namespace) -> str:
    """The twin's step as the trainings will take it, and why (the choice takes ~2 s, inside the
    twin's wall clock below as it is inside ``tensegrity train``'s)."""
    from tensegrity_gym.training import TrainConfig, resolve_physics_dt

    return resolve_physics_dt(TrainConfig(timesteps=1, identified=args.identified,
                                          physics_dt=_physics_dt(args.physics_dt)))[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--identified", default=os.path.join(ROOT, "identified", "data", "robot.json"))
    ap.add_argument("--timesteps", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--busy", choices=("both", "none", "only"), default="both",
                    help="run quiet and with one busy process (both, default), quiet only, or busy only")
    ap.add_argument("--twin-envs", type=int, default=None, help="twin envs (default: tensegrity train's, 64)")
    ap.add_argument("--plant-envs", type=int, default=8, help="plant envs, one process each (default 8)")
    ap.add_argument("--batch-size", type=int, default=None, help="PPO mini-batch (default: tensegrity train's)")
    ap.add_argument("--n-epochs", type=int, default=None, help="PPO epochs per update (default: tensegrity train's)")
    ap.add_argument("--rollout", type=int, default=None, help="PPO transitions per update (default 4096)")
    ap.add_argument("--fused-adam", action="store_true",
                    help="Adam's fused CPU kernel (the same update rule; tensegrity train's default already)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of both trainings (default 1)")
    ap.add_argument("--physics-dt", default="auto",
                    help="the twin's integration step: 'auto' (tensegrity train's default: the coarsest stable "
                    "step, 4 ms for the robot preset), 'model' (the model's own dt, 1 ms) or seconds")
    ap.add_argument("--curve", action="store_true",
                    help="also evaluate on the plant: the twin policy and the learning curve of the plant run")
    ap.add_argument("--no-curve", action="store_true", help=argparse.SUPPRESS)  # the default now
    ap.add_argument("--episodes", type=int, default=10, help="evaluation episodes on the plant (--curve)")
    ap.add_argument("--target", type=float, default=0.5, help="a progress (m) to report the plant steps of (--curve)")
    ap.add_argument("--points", type=int, default=8,
                    help="snapshots of the plant run evaluated (--curve; evenly spaced, plus the final policy)")
    ap.add_argument("--out", default=os.path.join(ROOT, "runs", "bench_train"))
    ap.add_argument("--updates", action="store_true",
                    help="only time PPO's update alone per mini-batch size (seconds; no training)")
    ap.add_argument("--cold-twin", action="store_true",
                    help="no warm-up training of the twin first: the first twin training may compile its substep "
                         "(a model's first training; by default a short warm-up training compiles and stores it)")
    ap.add_argument("--one", choices=("twin", "plant"), default=None, help=argparse.SUPPRESS)  # a child: one training
    ap.add_argument("--policy-out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()

    import tensegrity_gym  # noqa: F401
    from tensegrity_gym.training import DEFAULT_ROLLOUT, TrainConfig

    os.makedirs(args.out, exist_ok=True)
    hp: dict = {}
    if args.batch_size is not None:
        hp["batch_size"] = args.batch_size
    if args.n_epochs is not None:
        hp["n_epochs"] = args.n_epochs
    if args.fused_adam:
        hp["policy_kwargs"] = {"optimizer_kwargs": {"fused": True}}
    rollout = args.rollout or DEFAULT_ROLLOUT
    if args.updates:
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        with open(os.path.join(args.out, "bench_train_updates.json"), "w") as fh:
            json.dump(updates_table(rollout), fh, indent=1)
        return
    if args.one is not None:  # the child: train, print the row as the last line of stdout
        instrument()
        plant = args.one == "plant"
        cfg = TrainConfig(timesteps=args.timesteps, seed=args.seed, identified=args.identified, plant=plant,
                          envs=args.plant_envs if plant else args.twin_envs, rollout=rollout, threads=args.threads,
                          hyperparameters=dict(hp), snapshots=args.curve and plant and os.path.basename(args.policy_out) == "plant-quiet.zip",
                          physics_dt=_physics_dt(args.physics_dt))
        print(json.dumps(train_timed(cfg, args.policy_out), default=str))
        return
    conds = {"both": ("quiet", "busy"), "none": ("quiet",), "only": ("busy",)}[args.busy]
    if not args.cold_twin:
        # the twin's compiled substep, from the cache on disk or compiled and stored now: a model's
        # first training pays this once; the timed trainings below then load it (a short twin
        # training, its own process; its figures are printed, not part of the table)
        warm = [sys.executable, os.path.abspath(__file__), "--one", "twin", "--policy-out",
                os.path.join(args.out, "twin-warmup.zip"), *sys.argv[1:], "--timesteps", str(2 * rollout)]
        proc = subprocess.run(warm, check=False, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(f"bench_train: the twin's warm-up failed:\n{proc.stderr[-3000:]}")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        print(f"twin warm-up ({2 * rollout} steps): compiled substep {row['compile_cache']} in {row['compile_s']:.1f} s "
              "('stored': compiled now, a model structure's first training; 'hit': from the cache on disk)", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {args.timesteps} steps, seed {args.seed}, "
          f"{args.threads} torch thread(s); overrides {hp or 'none'}, rollout {rollout}; {_step_line(args)}", flush=True)
    runs: dict = {}
    for cond in conds:
        runs[cond] = {}
        for where in ("twin", "plant"):
            # each training in a fresh process, as 'tensegrity train' runs: the twin loads its compiled
            # substep from the cache on disk (or compiles and stores it), nothing else carries over
            out = os.path.join(args.out, f"{where}-{cond}.zip")
            child = [sys.executable, os.path.abspath(__file__), "--one", where, "--policy-out", out,
                     *sys.argv[1:]]
            t0 = time.perf_counter()
            if cond == "busy":
                with Busy():
                    proc = subprocess.run(child, check=False, capture_output=True, text=True)
            else:
                proc = subprocess.run(child, check=False, capture_output=True, text=True)
            if proc.returncode != 0:
                sys.exit(f"bench_train: the {where} training failed:\n{proc.stderr[-3000:]}")
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["process_wall_s"] = time.perf_counter() - t0
            runs[cond][where] = row
            print(f"{cond:5s} {where:5s}: {row['timesteps']} steps, {row['envs']} envs: {row['wall_s']:.1f} s wall "
                  f"({row['steps_per_s']:.0f} steps/s; compile {row['compile_s']:.1f}"
                  f"{' (' + row['compile_cache'] + ')' if row.get('compile_cache') else ''}, env {row['env_s']:.1f}, SB3 "
                  f"collecting {row['sb3_collect_s']:.1f}, updates {row['updates_s']:.1f} s), {row['cpu_s']:.0f} s CPU; "
                  f"process {row['process_wall_s']:.1f} s; load {row['load_before']:.1f} -> {row['load_after']:.1f}",
                  flush=True)
    print()
    print_table(runs)
    result: dict = {"runs": runs, "overrides": {k: v for k, v in hp.items() if k != "policy_kwargs"},
                    "fused_adam": args.fused_adam, "rollout": rollout,
                    "plant_over_twin_wall": {c: runs[c]["plant"]["wall_s"] / runs[c]["twin"]["wall_s"] for c in runs}}
    if args.curve and "quiet" in runs:
        result.update(learning_curve(args, runs["quiet"]))
    with open(os.path.join(args.out, "bench_train.json"), "w") as fh:
        json.dump(result, fh, indent=1, default=str)


def learning_curve(args: argparse.Namespace, rows: dict) -> dict:
    """The twin policy on the plant, the plant run's learning curve and the plant-data anchors."""
    from tensegrity_gym.gap import measure_gap
    from tensegrity_gym.training import snapshot_path

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
    return {"gap": {k: gap[k] for k in ("twin", "plant", "random_plant")}, "plant_curve": curve, "anchors": anchors,
            "collection": {**COLLECTION, "robot_s": coll_robot_s, "control_steps": coll_robot_s / dt}}


if __name__ == "__main__":
    main()
