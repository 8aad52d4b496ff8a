"""Bring your own robot: the three lab-style models of ``examples/`` through collect and fit, against
the truth the plant holds.

    python benchmarks/bench_byor.py [--episodes 10] [--steps 1000] [--effects ground_contact]

For each model (a 3-bar prism with motor actuators; a 6-bar of composite rods with an electronics
box 6 cm off the axis; a 6-bar of nested bodies with filtered general actuators): collect
``episodes x steps`` with pushes of 5 N every 50 steps, fit with the total mass given
(``--total-mass``, the truth's), and print the largest relative error of K, c and M against the
plant's own values (read here from the compiled MuJoCo model: the benchmark knows the truth, the
fit never sees it) with the fit's own verdict, ``metrics.residual`` (the one-step residual wrench
relative to the recorded one; above 1 % the fit says it does not describe its data).

What the identification does not model yet (a rod's centre of mass off its frame's origin,
products of inertia, MuJoCo actuator forces) shows here as large errors *and* a large residual:
the point of the table is that the two go together. Figures, not assertions.
"""

from __future__ import annotations

import argparse
import os
import time

import mujoco
import numpy as np

from identified.fit.identify import ScaleSpec
from identified.fit.pipeline import fit_model
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, collect

EXAMPLES = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "examples")
MODELS = ("prism3", "six_bar_composite", "six_bar_nested")


def truth(path: str) -> dict[str, np.ndarray]:
    """K, c per tendon and M per rod (its bodies together) of the compiled model, in topology order."""
    m = mujoco.MjModel.from_xml_path(path)
    topo = Topology.from_mjcf(path)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    bid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in topo.rod_names]
    return {"K": m.tendon_stiffness[tid].copy(), "c": m.tendon_damping[tid].copy(),
            "M": m.body_subtreemass[bid].copy()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--effects", default="ground_contact")
    args = ap.parse_args()
    print(f"{'model':20s}{'collect s':>10s}{'fit s':>8s}{'max |dK|/K':>12s}{'max |dc|/c':>12s}"
          f"{'max |dM|/M':>12s}{'residual':>10s}  verdict")
    for name in MODELS:
        path = os.path.join(EXAMPLES, f"{name}.xml")
        t = truth(path)
        t0 = time.perf_counter()
        data = collect(path, CollectConfig(episodes=args.episodes, steps=args.steps, seed=1, push_every=50,
                                           push_magnitude=5.0))
        t1 = time.perf_counter()
        try:
            model = fit_model(data, path, effects=args.effects, scale=ScaleSpec(total_mass=float(t["M"].sum())),
                              jobs=1)
        except ValueError as exc:
            print(f"{name:20s}{t1 - t0:10.1f}{'':8s}  fit refused: {exc}")
            continue
        t2 = time.perf_counter()
        rel = lambda est, true: float(np.max(np.abs(est - true) / np.abs(true)))
        res = model.metrics["residual"]
        verdict = "says it does not describe its data" if res["large"] else "describes its data"
        print(f"{name:20s}{t1 - t0:10.1f}{t2 - t1:8.1f}{rel(model.stiffness, t['K']):12.3g}"
              f"{rel(model.damping, t['c']):12.3g}{rel(model.mass, t['M']):12.3g}"
              f"{res['relative_one_step']:10.3g}  {verdict}")


if __name__ == "__main__":
    main()
