"""Identification from noisy states: accuracy against the truth and calibration of the error bars.

    python benchmarks/bench_noise.py [--model-seeds 17,3,42] [--data-seeds 1,2,3,4,5]
                                     [--episodes 20] [--steps 2000] [--no-cache] [--refine]

Plants ``build_model("ico", "paper-nonuniform", seed=S)`` for every model seed; data collected with
50 N pushes every 100 steps and the reference sensor noise: 1 mm on positions, 1 cm/s on velocities,
1 mrad on orientations, 0.01 rad/s on angular velocities (``--steps``/``--episodes`` per dataset,
one dataset per data seed ``d``, collected with seed ``100 * model seed + d``: :func:`collect`
draws initial states, pushes and noise in the same order for every model, so datasets of
different models with one seed would share them and not be independent).  Every dataset is
fitted twice:

* ``eiv``: the default fit (weak form, errors-in-variables estimator with the recorded noise,
  cluster-robust error bars; :mod:`identified.fit.regression`, :mod:`identified.fit.uncertainty`);
* ``plain``: the same weak-form rows fitted as if the states were exact (``noise_copies=0``);
* with ``--refine`` also ``refine``: the ``eiv`` result refined by :func:`identified.fit.refine.refine`
  (on noisy data the output-error maximum-likelihood fit; ~70 s per dataset, no error bars, so it
  has no z-scores).

Printed per dataset: the maximum relative error of each parameter group against
``preset_parameters`` (K, c, M, transverse inertias Ixx/Iyy, axial inertia Izz) and the fit time;
then, over all datasets, the RMS and the share beyond 3 of the z-scores
``(estimate - truth) / stderr`` per group (calibrated error bars give an RMS near 1).  Datasets are
cached under ``benchmarks/.cache/`` (git-ignored).  Figures, not assertions.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from identified import Topology
from identified.dataset import Dataset, load_dataset, save_dataset
from identified.fit.identify import identify
from identified.fit.refine import refine
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters

CACHE = Path(__file__).resolve().parent / ".cache"
NOISE = {"noise_pos": 1e-3, "noise_vel": 1e-2, "noise_quat": 1e-3, "noise_angvel": 1e-2}
GROUPS = ("K", "c", "M", "Ixy", "Izz")


def truth(seed: int) -> dict[str, np.ndarray]:
    p = preset_parameters("ico", "paper-nonuniform", seed)
    inertia = np.array([r["inertia"] for r in p["rods"]])
    springs, rods = p["springs"], p["rods"]
    return {"K": np.array([s["stiffness"] for s in springs]), "c": np.array([s["damping"] for s in springs]),
            "M": np.array([r["mass"] for r in rods]), "Ixy": inertia[:, :2], "Izz": inertia[:, 2]}


def estimates(model) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    se = model.stderr
    est = {"K": model.stiffness, "c": model.damping, "M": model.mass, "Ixy": model.inertia[:, :2],
           "Izz": model.inertia[:, 2]}
    if not se:  # a refined model has no error bars
        return est, {}
    err = {"K": se["stiffness"], "c": se["damping"], "M": se["mass"], "Ixy": se["inertia"][:, :2],
           "Izz": se["inertia"][:, 2]}
    return est, err


def dataset(xml: str, model_seed: int, data_seed: int, episodes: int, steps: int, cache: bool) -> Dataset:
    seed = 100 * model_seed + data_seed
    cfg = CollectConfig(episodes=episodes, steps=steps, seed=seed, push_every=100, **NOISE)
    path = CACHE / f"noise_ico{model_seed}_seed{seed}_{episodes}x{steps}.npz"
    if cache and path.exists():
        return load_dataset(path)
    data = collect(xml, cfg)
    if cache:
        CACHE.mkdir(exist_ok=True)
        save_dataset(path, data)
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model-seeds", default="17,3,42")
    ap.add_argument("--data-seeds", default="1,2,3,4,5")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--refine", action="store_true", help="also refine the eiv fit (slow)")
    args = ap.parse_args()
    fits = ("eiv", "plain") + (("refine",) if args.refine else ())
    z: dict[str, dict[str, list[np.ndarray]]] = {f: {g: [] for g in GROUPS} for f in fits}
    worst: dict[str, dict[str, float]] = {f: dict.fromkeys(GROUPS, 0.0) for f in fits}
    times: dict[str, list[float]] = {f: [] for f in fits}
    print("max relative error (%) per group; fit wall time (s)")
    print(f"{'model':>5} {'data':>4} {'fit':>5} " + " ".join(f"{g:>7}" for g in GROUPS) + "   time")
    for ms in (int(s) for s in args.model_seeds.split(",")):
        xml = build_model("ico", "paper-nonuniform", seed=ms)
        topo, want = Topology.from_mjcf(xml), truth(ms)
        for ds in (int(s) for s in args.data_seeds.split(",")):
            data = dataset(xml, ms, ds, args.episodes, args.steps, not args.no_cache)
            fitted = {}
            for fit in fits:
                t0 = time.perf_counter()
                if fit == "refine":
                    model = refine(fitted["eiv"], data)
                else:
                    model = identify(data, topo, noise_copies=1 if fit == "eiv" else 0)
                fitted[fit] = model
                times[fit].append(time.perf_counter() - t0)
                est, se = estimates(model)
                rel = {g: float(np.max(np.abs(est[g] / want[g] - 1))) for g in GROUPS}
                for g in GROUPS:
                    worst[fit][g] = max(worst[fit][g], rel[g])
                    if se:
                        z[fit][g].append(((est[g] - want[g]) / se[g]).ravel())
                print(f"{ms:>5} {ds:>4} {fit:>5} " + " ".join(f"{100 * rel[g]:7.3f}" for g in GROUPS)
                      + f"   {times[fit][-1]:.2f}", flush=True)
    print("\nover all datasets: worst max relative error (%), z-score RMS, share of |z| > 3, mean fit time")
    for fit in fits:
        print(f"{fit:>5}: worst " + " ".join(f"{g} {100 * worst[fit][g]:.3f}" for g in GROUPS))
        if not z[fit]["K"]:
            print(f"       (no error bars)   time {np.mean(times[fit]):.2f} s")
            continue
        zs = {g: np.concatenate(z[fit][g]) for g in GROUPS}
        print("       z RMS " + " ".join(f"{g} {np.sqrt(np.mean(zs[g] ** 2)):.2f}" for g in GROUPS))
        print("       |z|>3 " + " ".join(f"{g} {np.mean(np.abs(zs[g]) > 3):.2f}" for g in GROUPS)
              + f"   time {np.mean(times[fit]):.2f} s")


if __name__ == "__main__":
    main()
