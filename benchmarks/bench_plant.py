"""Physics steps per second of the MuJoCo plant (robot and paper icosahedron).

Three loops per model:

* ``mj_step``: MuJoCo alone (the floor of what the plant can cost);
* ``plant.step``: motors + ``mj_step`` (what an env pays per physics step);
* ``record``: what ``tensegrity collect`` does per step: ``states()``, ``set_targets``, ``step``
  with a push, ``rest_lengths()``.

and the projected wall time of the paper's data scale (1000 trajectories x 2000 steps) for the
``record`` loop on one core. Figures, not assertions: run ``python benchmarks/bench_plant.py``.
"""

from __future__ import annotations

import argparse
import platform
import time

import mujoco
import numpy as np

from tensegrity_gym.models import build_model
from tensegrity_gym.plant import MujocoPlant

PAPER_STEPS = 1000 * 2000  # paper, Sec. Experiments: 1000 training trajectories, 2000 steps each


def _rate(fn, steps: int, repeats: int = 3) -> float:
    """Best of ``repeats`` runs of ``fn(steps)``, in steps per second."""
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(steps)
        best = max(best, steps / (time.perf_counter() - t0))
    return best


def bench(preset: str, steps: int) -> dict[str, float]:
    plant = MujocoPlant(build_model("ico", preset))
    m, d = plant.model, plant.data
    R, A = plant.n_rods, len(plant.actuated_names)
    rng = np.random.default_rng(0)
    lo, hi = plant.rest_bounds()
    targets = lo + (hi - lo) * rng.uniform(size=(steps, A)) if A else np.zeros((steps, 0))
    force = np.zeros((R, 3))
    force[0] = (20.0, 0.0, 0.0)
    point = np.zeros((R, 3))
    point[0] = (0.0, 0.0, 0.3)

    def raw(n: int) -> None:
        plant.reset()
        for _ in range(n):
            mujoco.mj_step(m, d)

    def step(n: int) -> None:
        plant.reset()
        for _ in range(n):
            plant.step()

    def record(n: int) -> None:
        plant.reset()
        for t in range(n):
            plant.states()
            if A:
                plant.set_targets(targets[t])
            plant.step(force, point)
            plant.rest_lengths()

    return {"mj_step": _rate(raw, steps), "plant.step": _rate(step, steps), "record": _rate(record, steps)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=5000, help="physics steps per timed run (default 5000)")
    args = ap.parse_args()
    print(f"MuJoCo {mujoco.__version__}, numpy {np.__version__}, {platform.processor() or platform.machine()}, "
          f"one thread; best of 3 runs of {args.steps} steps")
    for preset in ("robot", "paper-uniform"):
        r = bench(preset, args.steps)
        line = ", ".join(f"{k} {v:,.0f} steps/s" for k, v in r.items())
        print(f"ico/{preset:14s} {line}")
        print(f"{'':19s} paper scale (1000 x 2000 steps) recorded: {PAPER_STEPS / r['record']:,.0f} s "
              f"({PAPER_STEPS / r['record'] / 60:.1f} min) on one core")


if __name__ == "__main__":
    main()
