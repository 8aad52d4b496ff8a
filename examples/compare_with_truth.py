"""Compare an identified model with the ground truth of the preset that generated its data.

    python examples/compare_with_truth.py runs/demo/ico.json --preset paper-nonuniform --seed 3

Prints, per parameter kind, the largest and the median relative error.  When the model is
normalised (no mass or push fixed the scale), the truth is rescaled by the mean rod mass first.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from identified.model import load_model
from tensegrity_gym.models import preset_parameters


def relative_errors(model_path: str, system: str, preset: str, seed: int | None) -> dict[str, np.ndarray]:
    """Relative error of every K, c, M and I against the preset's truth, matched by name."""
    model = load_model(model_path)
    truth = preset_parameters(system, preset, seed)
    rods = {r["name"]: r for r in truth["rods"]}
    springs = {s["name"]: s for s in truth["springs"]}
    scale = 1.0
    if model.scale.get("anchor") == "normalised":
        scale = 1.0 / np.mean([r["mass"] for r in truth["rods"]])
    names_r, names_s = model.topology.rod_names, model.topology.spring_names
    true_m = np.array([rods[n]["mass"] for n in names_r]) * scale
    true_i = np.array([rods[n]["inertia"] for n in names_r]) * scale
    true_k = np.array([springs[n]["stiffness"] for n in names_s]) * scale
    true_c = np.array([springs[n]["damping"] for n in names_s]) * scale
    return {
        "stiffness K": model.stiffness / true_k - 1,
        "damping c": model.damping / true_c - 1,
        "mass M": model.mass / true_m - 1,
        "inertia I (transverse)": model.inertia[:, :2] / true_i[:, :2] - 1,
        "inertia I (axial)": model.inertia[:, 2] / true_i[:, 2] - 1,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("identified", help="identified-model .json")
    p.add_argument("--system", default="ico")
    p.add_argument("--preset", default="paper-nonuniform")
    p.add_argument("--seed", type=int, default=None)
    a = p.parse_args(argv)
    errs = relative_errors(a.identified, a.system, a.preset, a.seed)
    print(f"{'parameter':<24}{'max |rel. error|':>18}{'median':>12}")
    for name, e in errs.items():
        e = np.abs(np.ravel(e))
        print(f"{name:<24}{e.max():>18.2e}{np.median(e):>12.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
