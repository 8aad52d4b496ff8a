"""Plants on MuJoCo's other integrators: identification accuracy, the choice of integrator, cost.

    python benchmarks/bench_integrators.py [--episodes 20] [--steps 2000] [--refine-windows 16]

For each MuJoCo integrator of the plant (Euler, implicitfast, implicit, RK4) the paper's
non-uniform icosahedron (``build_model("ico", "paper-nonuniform", seed=0, integrator=...)``) is
rolled with 50 N surface pushes every 100 steps; one table, side by side:

* ``fit --integrator auto``: which integrator the equation residuals pick, the fit time, and the
  maximum relative error of K, c, M, the transverse and the axial inertias against the truth;
* the same data fitted with the Euler equations (what a fit that ignores the plant's integrator
  gets);
* for RK4, ``--refine`` from the regression through the RK4 engine (``--refine-windows`` windows of
  50 steps, 30 L-BFGS iterations), with its time;
* the engine's cost per step of each integrator (6 rods, batch of 1 and of 1024 states).

Figures, not assertions: the machine's other load shows in the times.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from identified import Topology
from identified.engine import SpringRodEngine, SpringRodParams
from identified.fit.identify import identify
from identified.fit.refine import refine
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters

PLANTS = ("euler", "implicitfast", "implicit", "rk4")


def truth(seed: int) -> dict[str, np.ndarray]:
    p = preset_parameters("ico", "paper-nonuniform", seed)
    inertia = np.array([r["inertia"] for r in p["rods"]])
    return {"K": np.array([s["stiffness"] for s in p["springs"]]), "c": np.array([s["damping"] for s in p["springs"]]),
            "M": np.array([r["mass"] for r in p["rods"]]), "I_t": inertia[:, :2], "I_a": inertia[:, 2]}


def errors(model, want: dict[str, np.ndarray]) -> dict[str, float]:
    got = {"K": model.stiffness, "c": model.damping, "M": model.mass, "I_t": model.inertia[:, :2],
           "I_a": model.inertia[:, 2]}
    return {k: float(np.max(np.abs(got[k] / want[k] - 1))) for k in want}


def row(label: str, err: dict[str, float], seconds: float, extra: str = "") -> str:
    cols = " ".join(f"{err[k]:9.1e}" for k in ("K", "c", "M", "I_t", "I_a"))
    return f"  {label:<34} {cols} {seconds:8.2f}  {extra}"


def engine_cost(integrator: str, batch: int, steps: int = 200) -> float:
    """Microseconds per engine step of the 6-rod icosahedron, ``batch`` states at once."""
    xml = build_model("ico", "paper-uniform")
    topo = Topology.from_mjcf(xml)
    params = SpringRodParams.from_values(100.0, 10.0, 10.0, [0.9, 0.9, 0.0125], n_rods=6, n_springs=24)
    eng = SpringRodEngine(topo, params, 1e-3, integrator=integrator)
    rng = np.random.default_rng(0)
    quat = rng.normal(size=(batch, 6, 4))
    state = eng.state(rng.normal(size=(batch, 6, 3)), quat / np.linalg.norm(quat, axis=-1, keepdims=True),
                      rng.normal(size=(batch, 6, 3)), rng.normal(size=(batch, 6, 3)))
    rest = torch.full((batch, 24), 0.637, dtype=torch.float64)
    with torch.inference_mode():
        for _ in range(3):
            eng.step(state, rest)
        t0 = time.perf_counter()
        for _ in range(steps):
            eng.step(state, rest)
    return (time.perf_counter() - t0) / steps * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--refine-windows", type=int, default=16)
    args = ap.parse_args()
    want = truth(0)
    print(f"paper-nonuniform seed 0, {args.episodes} x {args.steps} steps, 50 N pushes every 100 steps; "
          "max relative error against the truth")
    print(f"  {'plant / fit':<34} {'K':>9} {'c':>9} {'M':>9} {'I_trans':>9} {'I_axial':>9} {'time s':>8}")
    for plant in PLANTS:
        xml = build_model("ico", "paper-nonuniform", seed=0, integrator=plant)
        data = collect(xml, CollectConfig(episodes=args.episodes, steps=args.steps, seed=1, push_every=100))
        topo = Topology.from_mjcf(xml)
        t0 = time.perf_counter()
        auto = identify(data, topo, integrator="auto")
        t_auto = time.perf_counter() - t0
        sel = auto.metrics["integrator_selection"]
        picked = ", ".join(f"{k} {v:.3g}" for k, v in sorted(sel.items(), key=lambda kv: kv[1]))
        print(row(f"{plant}: auto -> {auto.integrator}", errors(auto, want), t_auto, f"scores: {picked}"))
        if auto.integrator != "euler":
            t0 = time.perf_counter()
            euler = identify(data, topo)
            print(row(f"{plant}: euler equations", errors(euler, want), time.perf_counter() - t0))
        if auto.integrator == "rk4":
            t0 = time.perf_counter()
            ref = refine(auto, data, horizon=50, max_windows=args.refine_windows, iterations=30)
            info = ref.metrics["refine"]
            print(row(f"{plant}: auto + refine ({args.refine_windows}x50)", errors(ref, want),
                      time.perf_counter() - t0, f"loss {info['loss_before']:.2g} -> {info['loss_after']:.2g}"))
    print("engine step, 6 rods (us):")
    for integrator in ("euler", "implicit", "rk4"):
        print(f"  {integrator:<9} batch 1: {engine_cost(integrator, 1):8.0f}   batch 1024: "
              f"{engine_cost(integrator, 1024, steps=50):8.0f}")


if __name__ == "__main__":
    main()
