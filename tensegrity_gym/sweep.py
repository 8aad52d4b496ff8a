"""Several training seeds at once: ``tensegrity train --seeds 0-4 --out DIR``.

:func:`run_sweep` trains one policy per seed with the same :class:`~tensegrity_gym.training.TrainConfig`
(only ``seed`` differs), in parallel local processes (``jobs`` at a time, one torch thread each) or,
given ``ray_address``, as Ray tasks (one CPU each) on a Ray cluster (``pip install
'tensegrity-gym[ray]'``; every node needs this package installed). A task gets the identified
model's JSON and its plant MJCF as text and returns the files it wrote as bytes, so the nodes
need no shared file system; the driver writes every file, atomically.

The output follows rl_zoo3's layout, one folder per run::

    DIR/
      summary.json                  every seed: timesteps, wall clock, last episodes' figures;
                                    mean and spread over seeds; the configuration
      learning_curves.png           the seeds' learning curves on one plot
      seed_<S>/
        policy.zip                  the policy (``tensegrity gap``/``load_policy`` read it; it
                                    carries its observation normalisation)
        vecnormalize.pkl            SB3's VecNormalize statistics (``VecNormalize.load``)
        config.json                 the TrainConfig and the algorithm's effective hyperparameters
        progress.csv                the learning curve: one row per rollout (update): the mean
                                    reward per step and forward velocity over all envs
        episodes.csv                one row per finished training episode (return, progress)
        learning_curve.png          the learning curve, plotted
        result.json                 what the run did (steps, wall clock, last episodes' figures)

The figures in ``summary.json`` are those of training (the last :data:`LAST_EPISODES` training
episodes, with the policy's exploration noise, on the env it trained on). How the policies do on
the plant is ``tensegrity gap --policy DIR``.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import os
import pathlib
import re
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from tensegrity_gym.training import TrainConfig

__all__ = ["CURVE_COLUMNS", "EPISODE_COLUMNS", "LAST_EPISODES", "SUMMARY_FORMAT", "curve_csv", "parse_seeds", "plot_curves",
           "policies_in", "run_sweep", "spread"]

SUMMARY_FORMAT = "tensegrity-sweep/1"
#: Columns of ``progress.csv`` (one row per rollout: the learning curve).
CURVE_COLUMNS = ("timesteps", "wall_s", "reward_per_step", "velocity_m_s")
#: Columns of ``episodes.csv`` (one row per finished training episode).
EPISODE_COLUMNS = ("timesteps", "wall_s", "return", "progress_m", "length")
#: Training episodes the summary's "last" figures average over (the progress bar's window).
LAST_EPISODES = 20
RUN_FILES = ("policy.zip", "vecnormalize.pkl", "config.json", "progress.csv", "episodes.csv",
             "learning_curve.png", "result.json")


# ---------------------------------------------------------------------- seeds
def parse_seeds(text: str) -> list[int]:
    """``"0-4"`` -> [0, 1, 2, 3, 4]; ``"0,3,7"``, ``"0-2,9"`` likewise (ValueError naming ``--seeds``
    for anything else, a repeated seed, or a descending range)."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not m:
            raise ValueError(f"--seeds '{text}': '{part}' is not a seed or a range A-B of seeds "
                             "(non-negative integers, e.g. 0-4 or 0,3,7)")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        if b < a:
            raise ValueError(f"--seeds '{text}': the range {part} runs backwards")
        seeds.extend(range(a, b + 1))
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds '{text}' names a seed twice")
    return seeds


def spread(values: Iterable[float | None]) -> dict[str, Any]:
    """Mean, standard deviation (population), minimum and maximum of the finite values, and
    how many there were (``None`` figures when there are none)."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "min": float(v.min()), "max": float(v.max()),
            "n": int(v.size)}


# ---------------------------------------------------------------------- one seed (runs in a worker)
def _materialize_model(folder: str, identified: str | None, model_text: str | None, model_sha: str | None,
                       mjcf_text: str | None) -> str | None:
    """The identified model as a path the worker can read: the driver's path when it holds the
    same file here, else the shipped text written into ``folder`` with its source MJCF beside it."""
    if identified is None:
        return None
    if os.path.isfile(identified):
        with open(identified, "rb") as fh:
            if hashlib.sha256(fh.read()).hexdigest() == model_sha:
                return identified
    obj = json.loads(model_text or "{}")
    if mjcf_text is not None:
        src = os.path.join(folder, "source.xml")
        with open(src, "w", encoding="utf-8") as fh:
            fh.write(mjcf_text)
        obj["source_model"] = src
    path = os.path.join(folder, "identified.json")
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh)
    return path


def train_one(task: dict[str, Any]) -> dict[str, Any]:
    """Train one seed of a sweep (in a worker process or a Ray task) and return its files as bytes.

    ``task``: ``config`` (TrainConfig fields), ``identified`` (the driver's path), ``model_text``,
    ``model_sha``, ``mjcf_text``. Returns ``{"seed", "files": {name: bytes}, "result": {...}}``.
    """
    import tensegrity_gym  # noqa: F401  (registers the env in a fresh worker)
    from tensegrity_gym.training import train

    fields = dict(task["config"])
    with tempfile.TemporaryDirectory(prefix="tensegrity-seed-") as tmp:
        fields["identified"] = _materialize_model(tmp, task.get("identified"), task.get("model_text"),
                                                  task.get("model_sha"), task.get("mjcf_text"))
        cfg = TrainConfig(**fields)
        policy = os.path.join(tmp, "policy.zip")
        r = train(cfg, policy, progress=False)
        r.vecnormalize.save(os.path.join(tmp, "vecnormalize.pkl"))
        files = {name: pathlib.Path(tmp, name).read_bytes() for name in ("policy.zip", "vecnormalize.pkl")}
    log, curve = r.episode_log, r.rollout_log
    last = log[-LAST_EPISODES:]
    result = {
        "seed": int(cfg.seed),
        "timesteps": int(r.timesteps),
        "wall_s": float(r.wall_s),
        "env_steps_per_s": float(r.env_steps_per_s),
        "episodes": int(r.episodes),
        "diverged_episodes": int(r.diverged_episodes),
        "last_episodes": len(last),
        "last_return": float(np.mean([e["return"] for e in last])) if last else None,
        "last_progress_m": float(np.mean([e["progress_m"] for e in last])) if last else None,
        "last_velocity_m_s": float(curve[-1]["velocity_m_s"]) if curve else None,
        "last_reward_per_step": float(curve[-1]["reward_per_step"]) if curve else None,
        "trained_on": "plant" if cfg.plant else "twin",
    }
    config = {**{k: v for k, v in task["config"].items()}, "identified": task.get("identified"),
              "algorithm_kwargs": {k: v for k, v in cfg.algo_kwargs().items() if isinstance(v, (int, float, str))},
              "envs_resolved": cfg.n_envs}
    files["config.json"] = json.dumps(config, indent=1).encode()
    files["progress.csv"] = curve_csv(curve).encode()
    files["episodes.csv"] = curve_csv(log, EPISODE_COLUMNS).encode()
    files["result.json"] = json.dumps(result, indent=1).encode()
    png = io.BytesIO()
    plot_curves({int(cfg.seed): curve}, png, title=f"{cfg.algo} on the {result['trained_on']}, seed {cfg.seed}")
    files["learning_curve.png"] = png.getvalue()
    return {"seed": int(cfg.seed), "files": files, "result": result}


# ---------------------------------------------------------------------- learning curves
def curve_csv(rows: list[dict[str, float]], columns: tuple[str, ...] = CURVE_COLUMNS) -> str:
    """Rows of a training log (:attr:`TrainResult.rollout_log`, or ``episode_log`` with
    :data:`EPISODE_COLUMNS`) as CSV text (floats written exactly)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for e in rows:
        w.writerow([int(e[c]) if c in ("timesteps", "length") else repr(float(e[c])) for c in columns])
    return buf.getvalue()


def read_curve(path: str) -> list[dict[str, float]]:
    """A ``progress.csv`` back as episode rows."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def plot_curves(logs: dict[int, list[dict[str, float]]], out: Any, title: str) -> None:
    """The learning curves (:data:`CURVE_COLUMNS` rows per seed): mean forward velocity and reward per
    step over each rollout versus training steps; PNG to ``out`` (a path or a binary file)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    for seed, log in sorted(logs.items()):
        if not log:
            continue
        t = np.array([e["timesteps"] for e in log], dtype=float)
        for ax, key in zip(axes, ("velocity_m_s", "reward_per_step"), strict=True):
            ax.plot(t, [e[key] for e in log], ".-", ms=3, label=f"seed {seed}")
    axes[0].set_ylabel("forward velocity of the centre of mass (m/s)")
    axes[1].set_ylabel("reward per step")
    for ax in axes:
        ax.set_xlabel("training steps")
        ax.grid(alpha=0.3)
    if any(logs.values()):
        axes[0].legend(fontsize=8)
    fig.suptitle(f"{title}: mean over every env and step of each rollout", fontsize=10)
    fig.savefig(out, format="png", dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------- the sweep
def _write_run(folder: str, files: dict[str, bytes]) -> None:
    from identified.dataset import atomic_write

    os.makedirs(folder, exist_ok=True)
    for name, data in files.items():
        atomic_write(os.path.join(folder, name), lambda fh, d=data: fh.write(d), binary=True)


def _task(cfg: TrainConfig, seed: int) -> dict[str, Any]:
    from tensegrity_gym.training import plant_mjcf

    fields = dataclasses.asdict(cfg)
    fields.update(seed=int(seed), identified=None, tensorboard=None)
    task: dict[str, Any] = {"config": fields, "identified": None}
    if cfg.identified is not None:
        path = os.path.abspath(cfg.identified)
        with open(path, "rb") as fh:
            raw = fh.read()
        task.update(identified=path, model_text=raw.decode("utf-8"), model_sha=hashlib.sha256(raw).hexdigest(),
                    mjcf_text=plant_mjcf(path))
    return task


def run_sweep(cfg: TrainConfig, seeds: list[int], out: str | os.PathLike, jobs: int | None = None,
              ray_address: str | None = None, progress: bool = True,
              log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Train ``cfg`` once per seed into ``out/seed_<S>/`` and write ``out/summary.json`` (module
    docstring); returns the summary.

    Args:
        cfg: the configuration every seed shares (its ``seed`` is replaced).
        seeds: the seeds (distinct).
        out: the sweep's folder (created; existing seed folders are replaced file by file).
        jobs: local processes at a time (``None``: one per seed, at most the machine's cores).
        ray_address: run the seeds as Ray tasks: ``"local"`` (a Ray instance on this machine, or
            the one ``ray.init`` already started in this process), ``"auto"`` or ``HOST:PORT`` of a
            cluster. ``None``: local processes.
        progress: a progress bar over seeds (stderr).
        log: where a line per finished seed goes (default: stderr when ``progress``).
    """
    cfg.validate()
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("--seeds names no seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError("--seeds names a seed twice")
    if jobs is not None and (int(jobs) != jobs or jobs < 1):
        raise ValueError(f"--jobs must be an integer >= 1, got {jobs}")
    out = os.fspath(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"--out '{out}' exists and is not a folder (with --seeds, --out is a folder)")
    os.makedirs(out, exist_ok=True)
    if log is None:
        def log(line: str) -> None:
            if progress:
                print(line, file=sys.stderr, flush=True)
    tasks = [_task(cfg, s) for s in seeds]
    n_jobs = min(len(seeds), int(jobs) if jobs is not None else max(1, os.cpu_count() or 1))
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(seeds), unit="seed", desc=f"train {len(seeds)} seeds", dynamic_ncols=True,
                   file=sys.stderr)
    results: dict[int, dict[str, Any]] = {}

    def done(r: dict[str, Any]) -> None:
        _write_run(os.path.join(out, f"seed_{r['seed']}"), r["files"])
        results[r["seed"]] = r["result"]
        res = r["result"]
        last = ("" if res["last_progress_m"] is None else
                f", last {res['last_episodes']} episodes {res['last_progress_m']:.3f} m")
        vel = "" if res["last_velocity_m_s"] is None else f", last rollout {res['last_velocity_m_s']:.4f} m/s"
        log(f"seed {r['seed']}: {res['timesteps']} steps in {res['wall_s']:.1f} s{vel}{last}")
        if bar is not None:
            bar.update(1)

    try:
        if ray_address is not None:
            executor = "ray"
            _run_ray(tasks, ray_address, done)
        else:
            executor = "processes"
            _run_processes(tasks, n_jobs, done)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    runs = [{**results[s], "folder": f"seed_{s}", "policy": os.path.join(f"seed_{s}", "policy.zip")} for s in seeds]
    summary = {
        "format": SUMMARY_FORMAT,
        "seeds": seeds,
        "executor": executor,
        "jobs": n_jobs if executor == "processes" else None,
        "ray_address": ray_address,
        "wall_s": wall,
        "runs": runs,
        "over_seeds": {
            "last_progress_m": spread(r["last_progress_m"] for r in runs),
            "last_return": spread(r["last_return"] for r in runs),
            "last_velocity_m_s": spread(r["last_velocity_m_s"] for r in runs),
            "wall_s": spread(r["wall_s"] for r in runs),
        },
        "what": f"training figures: the last {LAST_EPISODES} training episodes and the last rollout of each seed "
                "(exploration noise on, on the env it trained on); the plant: tensegrity gap --policy THIS_FOLDER",
        "config": {**{k: v for k, v in dataclasses.asdict(cfg).items() if k != "seed"},
                   "identified": None if cfg.identified is None else os.path.abspath(cfg.identified)},
    }
    from identified.dataset import atomic_write
    from identified.jsonsafe import json_safe

    logs = {s: read_curve(os.path.join(out, f"seed_{s}", "progress.csv")) for s in seeds}
    atomic_write(os.path.join(out, "learning_curves.png"),
                 lambda fh: plot_curves(logs, fh, title=f"{cfg.algo}, {len(seeds)} seeds"), binary=True)
    atomic_write(os.path.join(out, "summary.json"),
                 lambda fh: json.dump(json_safe(summary), fh, indent=1, allow_nan=False))
    return summary


def _run_processes(tasks: list[dict[str, Any]], jobs: int, done: Callable[[dict[str, Any]], None]) -> None:
    """The tasks in ``jobs`` local worker processes (started fresh: no forked torch state)."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = multiprocessing.get_context("forkserver" if sys.platform.startswith("linux") else "spawn")
    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=ctx)
    try:
        pending = {pool.submit(train_one, t) for t in tasks}
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                done(f.result())
    except BaseException:
        # running seeds: stop them now (the pool forgets its processes when it shuts down)
        running = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in running:
            if p.is_alive():
                p.terminate()
        raise
    pool.shutdown(wait=True)


def _run_ray(tasks: list[dict[str, Any]], address: str, done: Callable[[dict[str, Any]], None]) -> None:
    """The tasks as Ray tasks of one CPU each."""
    try:
        import ray
    except ImportError:
        raise ValueError("--ray needs the ray package (pip install 'tensegrity-gym[ray]')") from None
    if not ray.is_initialized():
        ray.init(address=None if address == "local" else address, log_to_driver=False,
                 include_dashboard=False)
    remote = ray.remote(num_cpus=1, max_retries=0)(train_one)
    pending = [remote.remote(t) for t in tasks]
    try:
        while pending:
            finished, pending = ray.wait(pending, num_returns=1)
            for ref in finished:
                done(ray.get(ref))
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise


# ---------------------------------------------------------------------- reading sweeps
def policies_in(paths: Iterable[str]) -> list[str]:
    """Policy files named by ``paths``: a file is itself; a sweep folder gives its seeds' policies
    (``summary.json``'s order, else ``*/policy.zip`` by name). ValueError for a path that is
    neither, or a folder with no policy."""
    found: list[str] = []
    for p in paths:
        if os.path.isfile(p):
            found.append(p)
        elif os.path.isdir(p):
            summary = os.path.join(p, "summary.json")
            inside: list[str] = []
            if os.path.isfile(summary):
                try:
                    with open(summary, encoding="utf-8") as fh:
                        s = json.load(fh)
                    inside = [os.path.join(p, r["policy"]) for r in s.get("runs", [])]
                except (OSError, ValueError, KeyError, TypeError):
                    inside = []
            if not inside:
                inside = sorted((os.path.join(p, d, "policy.zip") for d in os.listdir(p)
                                 if os.path.isfile(os.path.join(p, d, "policy.zip"))), key=_natural)
            if not inside:
                raise ValueError(f"'{p}' holds no policies (no */policy.zip: a folder written by "
                                 "'tensegrity train --seeds')")
            found.extend(inside)
        else:
            raise ValueError(f"'{p}' does not exist (a policy file or a folder of seeds)")
    return found


def _natural(path: str) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path)]
