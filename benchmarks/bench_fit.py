"""Identification time and accuracy: the closed form against the paper's Adam, by data size.

    python benchmarks/bench_fit.py [--quick] [--adam-budget 600] [--repeats 3] [--threads N]

The plant is the paper's icosahedron with non-uniform parameters
(``build_model("ico", "paper-nonuniform", seed=0)``: 54 parameters K, c per spring and M per rod,
plus the inertias and the push scale h), rolled with random initial states and 50 N pushes every
100 steps.  One table, side by side:

(a) the 54-parameter fit from 20 trajectories x 2000 steps, closed form (``solver="lstsq"``),
    features included (best of ``--repeats``), with the time split into features (states ->
    equation rows), reduction (streamed QR of the rows) and solve (anchored least squares);
(b) 1e5 and 1e6 recorded steps, closed form against the paper's Adam (``solver="adam"``: 30
    epochs, lr 0.1 halved every 3 epochs, mini-batches of 32 steps), with the maximum relative
    error of each against the truth (``preset_parameters``).  Adam runs on 1e6 steps only when
    its projected time (seconds per epoch measured on 1e5, x 10, x 30 epochs) fits in
    ``--adam-budget``; otherwise the row says why and gives the projection.

The 1e6-step dataset (500 x 2000 steps, about 1 GB in memory) is collected once and cached under
``benchmarks/.cache/`` (git-ignored; delete it to re-collect); the table notes the collection
time.  ``--quick`` runs a small version in memory (seconds).
Figures, not assertions: the machine's other load shows in them.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import json
import os
import platform
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from identified import Topology
from identified.dataset import Dataset, load_dataset, save_dataset
from identified.fit.identify import identify
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters

CACHE = Path(__file__).resolve().parent / ".cache"
STEPS = 2000  # per trajectory, as in the paper
PUSH_EVERY = 100
ADAM_EPOCHS = 30  # identified.fit.adam default (the paper's schedule)


# ---------------------------------------------------------------------- data
def get_dataset(xml: str, episodes: int, steps: int, seed: int, cache: Path | None) -> tuple[Dataset, str]:
    """Collect (or load from the cache) ``episodes`` x ``steps`` with pushes; returns (data, note)."""
    cfg = CollectConfig(episodes=episodes, steps=steps, seed=seed, push_every=PUSH_EVERY)
    if cache is None:
        t0 = time.perf_counter()
        data = collect(xml, cfg)
        return data, f"collected in {time.perf_counter() - t0:.1f} s"
    tag = hashlib.sha1(xml.encode()).hexdigest()[:10]
    stem = f"ico-nonuniform-s0-{tag}_E{{}}_T{steps}_seed{seed}_push{PUSH_EVERY}"
    name = stem.format(episodes)
    npz, meta = cache / f"{name}.npz", cache / f"{name}.json"
    # a cached run with at least as many episodes will do: episodes draw from one seeded stream in order
    have = sorted((int(p.stem.split("_E")[1].split("_")[0]), p) for p in cache.glob(stem.format("*") + ".npz")
                  if p.with_suffix(".json").exists()) if cache.is_dir() else []
    have = [(e, p) for e, p in have if e >= episodes]
    if have:
        e, found = have[0]
        t0 = time.perf_counter()
        data = load_dataset(found)
        if e > episodes:
            data = data.select(episodes=slice(0, episodes))
        info = json.loads(found.with_suffix(".json").read_text())
        return data, (f"cached {found.relative_to(CACHE.parent.parent)} ({e} episodes collected in "
                      f"{info['collect_s']:.0f} s = {info['steps_per_s']:.0f} steps/s; loaded in "
                      f"{time.perf_counter() - t0:.1f} s)")
    cache.mkdir(parents=True, exist_ok=True)
    print(f"collecting {episodes} x {steps} steps (once; cached in {cache}) ...", flush=True)
    t0 = time.perf_counter()
    data = collect(xml, cfg, progress=True)
    collect_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    save_dataset(npz, data)
    save_s = time.perf_counter() - t1
    meta.write_text(json.dumps({"collect_s": collect_s, "steps_per_s": episodes * steps / collect_s,
                                "save_s": save_s, "episodes": episodes, "steps": steps, "seed": seed}))
    return data, (f"collected in {collect_s:.0f} s ({episodes * steps / collect_s:.0f} steps/s), "
                  f"saved to {npz.relative_to(CACHE.parent.parent)} in {save_s:.0f} s")


# ---------------------------------------------------------------------- timing
@contextlib.contextmanager
def stage_timer() -> Iterator[dict[str, float]]:
    """Time the stages inside ``identify`` by wrapping the functions it looks up at call time.

    ``features``: ``iter_chunks`` (states to tensors, accelerations), ``equation_rows`` and
    ``weak_form``; ``accumulate``: the streamed QR *including* the features it pulls (the
    reduction alone is ``accumulate - features``); ``solve``: the anchored least squares.
    Yields an empty dict when the pipeline's names are not found (the breakdown is then n/a).
    """
    import identified.fit.identify as idm

    t: dict[str, float] = {"features": 0.0, "accumulate": 0.0, "solve": 0.0}
    names = {"iter_chunks": "gen", "equation_rows": "features", "weak_form": "features",
             "accumulate": "accumulate", "solve": "solve"}
    if not all(hasattr(idm, n) for n in ("iter_chunks", "equation_rows", "accumulate", "solve")):
        yield {}
        return
    saved = {n: getattr(idm, n) for n in names if hasattr(idm, n)}

    def timed(fn, key):
        @functools.wraps(fn)
        def f(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                t[key] += time.perf_counter() - t0
        return f

    def timed_gen(fn):
        @functools.wraps(fn)
        def g(*a, **k):
            it = iter(fn(*a, **k))
            while True:
                t0 = time.perf_counter()
                try:
                    x = next(it)
                except StopIteration:
                    t["features"] += time.perf_counter() - t0
                    return
                t["features"] += time.perf_counter() - t0
                yield x
        return g

    for n, fn in saved.items():
        setattr(idm, n, timed_gen(fn) if names[n] == "gen" else timed(fn, names[n]))
    try:
        yield t
    finally:
        for n, fn in saved.items():
            setattr(idm, n, fn)


def errors(model, truth: dict) -> tuple[float, float]:
    """Max relative error over the 54 parameters (K, c, M), and over the 18 inertias."""
    K = np.array([s["stiffness"] for s in truth["springs"]])
    c = np.array([s["damping"] for s in truth["springs"]])
    M = np.array([r["mass"] for r in truth["rods"]])
    Inert = np.array([r["inertia"] for r in truth["rods"]])
    est = np.concatenate([model.stiffness, model.damping, model.mass])
    ref = np.concatenate([K, c, M])
    return float(np.max(np.abs(est / ref - 1))), float(np.max(np.abs(model.inertia / Inert - 1)))


def fit(data: Dataset, topo: Topology, truth: dict, solver: str, repeats: int = 1) -> dict:
    best: dict | None = None
    for _ in range(repeats):
        with stage_timer() as st:
            t0, c0 = time.perf_counter(), time.process_time()
            model = identify(data, topo, solver=solver)
            total, cpu = time.perf_counter() - t0, time.process_time() - c0
        row = {"total": total, "cpu": cpu, **st}
        if best is None or total < best["total"]:
            best = row
    best["err"], best["err_I"] = errors(model, truth)
    best["h"] = model.control_scale
    return best


# ---------------------------------------------------------------------- table
HEAD = (f"{'case':<24} {'steps':>9} {'solver':<6} {'fit s':>9} {'cpu s':>9} {'features':>9} {'reduce':>8} {'solve':>7} "
        f"{'max rel err K,c,M':>18} {'max rel err I':>14}  note")


def line(case: str, steps: int, solver: str, r: dict | None, note: str = "") -> str:
    if r is None:
        return f"{case:<24} {steps:>9,d} {solver:<6} {'-':>9} {'':>9} {'':>9} {'':>8} {'':>7} {'-':>18} {'-':>14}  {note}"
    if r.get("features") is not None and r.get("accumulate"):
        feat = f"{r['features']:.3f}"
        red = f"{r['accumulate'] - r['features']:.3f}"
        sol = f"{r['solve']:.3f}"
    else:
        feat = red = sol = "n/a" if solver == "lstsq" else ""
    return (f"{case:<24} {steps:>9,d} {solver:<6} {r['total']:>9.3f} {r['cpu']:>9.3f} {feat:>9} {red:>8} {sol:>7} "
            f"{r['err']:>18.2e} {r['err_I']:>14.2e}  {note}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, in memory (seconds)")
    ap.add_argument("--adam-budget", type=float, default=None,
                    help="run Adam on the larger size only if its projection is below this many seconds "
                    "(default 600; 15 with --quick)")
    ap.add_argument("--repeats", type=int, default=3, help="best of N for case (a) (default 3)")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's choice)")
    ap.add_argument("--sizes", default=None,
                    help="comma-separated step counts for (b), multiples of 2000 (default 100000,1000000)")
    ap.add_argument("--no-adam", action="store_true", help="closed form only")
    ap.add_argument("--no-cache", action="store_true", help="collect in memory, do not read/write the cache")
    args = ap.parse_args(argv)
    if args.adam_budget is None:
        args.adam_budget = 15.0 if args.quick else 600.0
    if args.threads:
        torch.set_num_threads(args.threads)

    xml = build_model("ico", "paper-nonuniform", seed=0)
    topo = Topology.from_mjcf(xml)
    truth = preset_parameters("ico", "paper-nonuniform", 0)
    if args.quick:
        a_eps, a_steps, sizes, big_eps, big_steps = 4, 500, (500, 5_000), 10, 500
        cache = None
    else:
        a_eps, a_steps, sizes, big_eps, big_steps = 20, STEPS, (100_000, 1_000_000), 500, STEPS
        cache = None if args.no_cache else CACHE
    if args.sizes is not None:
        sizes = tuple(int(float(x)) for x in args.sizes.split(",") if x.strip())
        big_eps = max([a_eps, *(n // big_steps for n in sizes)])

    print(f"bench_fit: ico/paper-nonuniform seed 0 ({topo.n_rods} rods, {topo.n_springs} springs: "
          f"{2 * topo.n_springs + topo.n_rods} parameters K, c, M + {3 * topo.n_rods} inertias + h); "
          f"pushes 50 N every {PUSH_EVERY} steps")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"torch {torch.__version__} with {torch.get_num_threads()} threads, python {sys.version.split()[0]}"
          f"{'  [QUICK]' if args.quick else ''}")
    big, note = get_dataset(xml, big_eps, big_steps, seed=1, cache=cache)
    print(f"data: {big.n_episodes} x {big.n_steps} steps: {note}")
    print()
    print(HEAD)
    print("-" * len(HEAD))

    sub = big.select(episodes=slice(0, a_eps), steps=a_steps)
    r = fit(sub, topo, truth, "lstsq", repeats=args.repeats)
    print(line(f"(a) {a_eps} x {a_steps}", a_eps * a_steps, "lstsq", r,
               f"best of {args.repeats}; target < 2 s"), flush=True)

    adam_per_step_epoch: float | None = None
    for n in sizes:
        eps = n // big_steps
        d = big.select(episodes=slice(0, eps))
        case = f"(b) {eps} x {big_steps}"
        r = fit(d, topo, truth, "lstsq")
        print(line(case, n, "lstsq", r), flush=True)
        if args.no_adam:
            continue
        if adam_per_step_epoch is not None:
            projected = adam_per_step_epoch * n * ADAM_EPOCHS
            if projected > args.adam_budget:
                print(line(case, n, "adam", None,
                           f"not run: projected {projected:,.0f} s = {adam_per_step_epoch * n:.1f} s/epoch "
                           f"(measured on {sizes[0]:,} steps, scaled) x {ADAM_EPOCHS} epochs "
                           f"> budget {args.adam_budget:.0f} s"), flush=True)
                continue
        r = fit(d, topo, truth, "adam")
        per_epoch = r["total"] / ADAM_EPOCHS
        adam_per_step_epoch = per_epoch / n
        print(line(case, n, "adam", r, f"{per_epoch:.2f} s/epoch x {ADAM_EPOCHS}; h = {r['h']:.4f}"), flush=True)
    print()
    print("fit s: wall time of identify(); cpu s: CPU time of this process (all threads) over the same span; "
          "features/reduce/solve: wall time of each stage (lstsq).")
    print("features: states -> equation rows (accelerations, 1D spring reduction, torques); reduce: streamed QR "
          "of the rows into per-rod triangular factors;\nsolve: anchored least squares with error bars. Adam "
          "recomputes the features every epoch (they are streamed, not stored). Errors are max |est/true - 1|.")


if __name__ == "__main__":
    main()
