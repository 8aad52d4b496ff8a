"""Counts over several hundred bad inputs: tracebacks, damaged files, silent NaNs,
unclear errors, and error bars that miss the truth.  All of them should be zero.

    .venv/bin/python benchmarks/fuzz_bad_input.py [--quick]

Every bad flag of ``tests/_fuzz.py``; every dataset key x corruption (each bad value, through
``summary`` and ``fit``); every identified-model field x corruption (through ``predict``); foreign
files through every command; a grid of env arguments (construction, reset, steps); and a few
noisy fits whose standard errors are compared with the known parameters (|z| > 4 counts as a
miss).  Same checks as the fuzz tests (:func:`tests._fuzz.check_outcome`).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym

import tensegrity_gym  # noqa: F401
from identified import Topology
from identified.dataset import save_dataset
from identified.fit.identify import identify
from identified.model import save_model
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import preset_parameters, write_model
from tests._fuzz import (
    BAD_FLAGS,
    BAD_FLOATS,
    DATASET_KEYS,
    DATASET_KINDS,
    FILE_KINDS,
    MODEL_FIELDS,
    MODEL_KINDS,
    check_outcome,
    corrupt_dataset,
    corrupt_file,
    corrupt_model,
    digest,
    finite,
    flag_argv,
    run_cli,
)


def classify(problems: list[str]) -> list[str]:
    kinds = []
    for p in problems:
        kinds.append("traceback" if p.startswith("traceback") else "damaged file" if p.startswith("damaged")
                     else "silent NaN" if p.startswith("silent NaN") else "temp file left" if "temporary" in p
                     else "unclear error" if p.startswith("expected one") else "other: " + p[:60])
    return kinds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer fits (datasets through summary only)")
    args = ap.parse_args()
    os.environ.pop("TENSEGRITY_DEBUG", None)
    root = Path(tempfile.mkdtemp(prefix="fuzz-"))
    files = {"ico": str(root / "ico.xml"), "data": str(root / "data.npz"), "fit": str(root / "fit.json")}
    write_model(files["ico"], "ico", preset="paper-nonuniform", seed=3)
    data = collect(files["ico"], CollectConfig(episodes=2, steps=60, seed=1, push_every=20))
    save_dataset(files["data"], data)
    save_model(files["fit"], identify(data, Topology.from_mjcf(files["ico"])))

    counts: Counter = Counter()
    examples: dict[str, str] = {}
    n = 0
    t0 = time.perf_counter()

    def run(label: str, argv: list[str], folder: Path) -> None:
        nonlocal n
        n += 1
        cwd = os.getcwd()
        os.chdir(folder)
        before = digest(folder)
        try:
            rc, out, err = run_cli(argv)
            problems = check_outcome(rc, out, err, before, folder)
        except Exception:  # noqa: BLE001 - an exception escaping main is a traceback
            problems = ["traceback: " + traceback.format_exc().strip().splitlines()[-1]]
        finally:
            os.chdir(cwd)
        for k in classify(problems):
            counts[k] += 1
            examples.setdefault(k, f"{label}: {problems}")

    for cmd, opt, value in BAD_FLAGS:
        run(f"flag {cmd} {opt} {value}", flag_argv(cmd, opt, value, files), Path(tempfile.mkdtemp(dir=root)))
    for key, kind in itertools.product(DATASET_KEYS, DATASET_KINDS):
        values = BAD_FLOATS if kind == "value" else [0.0]
        for i, v in enumerate(values):
            d = Path(tempfile.mkdtemp(dir=root))
            corrupt_dataset(Path(files["data"]), d / "d.npz", key, kind, v, 7919 * i + 13)
            run(f"dataset {key} {kind} {v} summary", ["summary", "d.npz", "--json"], d)
            if not args.quick:
                run(f"dataset {key} {kind} {v} fit", ["fit", "d.npz", "--model", files["ico"], "--out", "f.json",
                                                      "--quiet"], d)
    for field, kind in itertools.product(MODEL_FIELDS, MODEL_KINDS):
        values = BAD_FLOATS if kind == "value" else [0.0]
        for i, v in enumerate(values):
            d = Path(tempfile.mkdtemp(dir=root))
            corrupt_model(Path(files["fit"]), d / "m.json", field, kind, v, i)
            run(f"model {field} {kind} {v}", ["predict", files["data"], "--identified", "m.json", "--horizon", "20",
                                              "--json"], d)
    for kind in FILE_KINDS:
        for cmd in ("summary", "fit", "predict-model", "predict-data"):
            d = Path(tempfile.mkdtemp(dir=root))
            corrupt_file(Path(files["fit" if cmd == "predict-model" else "data"]), d / "x.bin", kind, 3)
            argv = {"summary": ["summary", "x.bin"], "fit": ["fit", "x.bin", "--model", files["ico"], "--out", "f.json"],
                    "predict-model": ["predict", files["data"], "--identified", "x.bin"],
                    "predict-data": ["predict", "x.bin", "--identified", files["fit"]]}[cmd]
            run(f"file {kind} {cmd}", argv, d)
    cli_inputs = n

    env_values = [0.0, 0.01, 1e6, *BAD_FLOATS]
    for ctrl, noise in itertools.product(env_values, env_values):
        n += 1
        try:
            env = gym.make("TensegrityIco-v0", ctrl_cost_weight=ctrl, reset_noise_scale=noise)
        except ValueError:
            continue
        try:
            obs, _ = env.reset(seed=0)
            ok = finite(obs)
            for _ in range(3):
                obs, r, _term, _trunc, _ = env.step(env.action_space.sample())
                ok = ok and finite(obs) and np.isfinite(r)
            if not ok:
                counts["silent NaN"] += 1
                examples.setdefault("silent NaN", f"env ctrl={ctrl} noise={noise}")
        except Exception as exc:  # noqa: BLE001
            counts["traceback"] += 1
            examples.setdefault("traceback", f"env ctrl={ctrl} noise={noise}: {exc!r}")

    p = preset_parameters("ico", "paper-nonuniform", 3)
    truth = {"stiffness": np.array([s["stiffness"] for s in p["springs"]]),
             "damping": np.array([s["damping"] for s in p["springs"]]),
             "mass": np.array([r["mass"] for r in p["rods"]])}
    fits, params, misses = (2, 3) if args.quick else (4, 3), 0, 0
    zs = []
    for seed in range(fits[0]):
        noisy = collect(files["ico"], CollectConfig(episodes=fits[1], steps=1500, seed=100 + seed, push_every=100,
                                                    noise_pos=1e-3, noise_vel=1e-2, noise_quat=1e-3,
                                                    noise_angvel=1e-2))
        m = identify(noisy, Topology.from_mjcf(files["ico"]))
        for k, v in truth.items():
            z = (getattr(m, k) - v) / m.stderr[k]
            zs.append(z)
            params += z.size
            misses += int(np.sum(~(np.abs(z) <= 4)))
    z = np.concatenate(zs)

    print(f"{n} bad inputs ({cli_inputs} through the command, {n - cli_inputs} through the env API) "
          f"in {time.perf_counter() - t0:.0f} s")
    for k in ("traceback", "damaged file", "temp file left", "silent NaN", "unclear error"):
        print(f"  {k:16s} {counts.get(k, 0)}")
    others = {k: v for k, v in counts.items() if k.startswith("other")}
    for k, v in others.items():
        print(f"  {k} {v}")
    print(f"  error bars missing the truth (|z| > 4): {misses} of {params} parameters in {fits[0]} noisy fits "
          f"of {fits[1]} episodes (z RMS {np.sqrt(np.mean(z**2)):.2f})")
    for k, v in examples.items():
        print(f"  e.g. {k}: {v}")


if __name__ == "__main__":
    main()
