"""The twin at a coarser integration step: where it stops being stable, and what each step costs
in accuracy against the model's own step.

    python benchmarks/bench_physics_dt.py [--identified identified/data/robot.json]
                                          [--steps-ms 1,2,4,5,10] [--episodes 3] [--seconds 1,5]

Prints, for the model: the spectral radius of its engine's step linearised at the standing pose
for each tested step (:mod:`identified.engine.stability`), the step ``physics_dt="auto"`` picks
(``tensegrity train``'s default) and its bisected stability limit; then for each step of
``--steps-ms`` the centre of mass of the robot against the twin at the model's own step after each
of ``--seconds`` under the same seeded random commands (float64, eager, ``--episodes`` episodes:
mean and largest distance, and whether any episode diverged).  The speed each step buys in
training is ``bench_train.py --physics-dt``'s.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.engine.stability import is_stable, spectral_radius
from identified.model import load_model
from identified.twin import engine_from_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend, default_model_path
from tensegrity_gym.backends.step_size import stable_physics_dt
from tensegrity_gym.envs.tensegrity_ico_v0 import FRAME_SKIP


def stability_limit(model, state, rest, lo: float, hi: float, own: float, tol: float = 1e-4) -> tuple[float, float]:
    """Bisect the step (s) between a stable ``lo`` and an unstable ``hi`` to ``tol`` (stable: no
    faster growth than the model's own, ``own`` 1/s)."""
    while hi - lo > tol:
        h = 0.5 * (lo + hi)
        rho = spectral_radius(engine_from_model(dataclasses.replace(model, dt=h)), state, rest)
        lo, hi = (h, hi) if is_stable(rho, h, own) else (lo, h)
    return lo, hi


def com_track(identified: str, physics_dt: float, seconds: float, seed: int) -> np.ndarray:
    """The robot's centre of mass (T, 3) at every control step of ``seconds`` under seeded random
    commands, the twin integrating at ``physics_dt``."""
    env = gym.make("TensegrityIco-v0", backend="identified", model=identified, max_episode_steps=100_000,
                   backend_kwargs={"compile": False, "dtype": "float64", "physics_dt": physics_dt})
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    b = env.unwrapped.backend
    mass = np.asarray(b.model.mass)
    out = []
    for _ in range(round(seconds / env.unwrapped.dt)):
        env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        pos = b.states().pos
        out.append((mass[:, None] * pos).sum(0) / mass.sum())
    env.close()
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--identified", default=default_model_path())
    ap.add_argument("--steps-ms", default="1,2,4,5,10")
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--seconds", default="1,5")
    args = ap.parse_args()
    m = load_model(args.identified)
    t0 = time.perf_counter()
    choice = stable_physics_dt(args.identified, FRAME_SKIP)
    print(f"auto step ({time.perf_counter() - t0:.1f} s): {choice.describe()}")
    b = IdentifiedBackend(m, dtype="float64", compile=False)
    state, rest = b.nominal_states(), b.nominal_rest_lengths()
    steps = [float(s) / 1e3 for s in args.steps_ms.split(",")]
    for h in sorted({*steps, 2 * choice.step}):
        rho = spectral_radius(engine_from_model(dataclasses.replace(m, dt=h)), state, rest)
        print(f"  step {1e3 * h:5g} ms: |λ| {rho:.6f} a step, "
              f"{'stable' if is_stable(rho, h, choice.own_rate) else 'UNSTABLE'}")
    unstable = [h for h in (0.01, 0.02, 0.04, 0.08) if not is_stable(
        spectral_radius(engine_from_model(dataclasses.replace(m, dt=h)), state, rest), h, choice.own_rate)]
    if unstable:
        lo, hi = stability_limit(m, state, rest, unstable[0] / 2, unstable[0], choice.own_rate)
        print(f"stability limit at the standing pose: between {1e3 * lo:.2f} and {1e3 * hi:.2f} ms")
    marks = [float(s) for s in args.seconds.split(",")]
    T = max(marks)
    ref = {e: com_track(args.identified, m.dt, T, seed=e) for e in range(args.episodes)}
    print(f"centre of mass against the twin at {1e3 * m.dt:g} ms (mean / largest over {args.episodes} episodes of "
          "random commands, mm):")
    for h in steps:
        if abs(h - m.dt) < 1e-12:
            continue
        tracks = {e: com_track(args.identified, h, T, seed=e) for e in ref}
        row = []
        for t in marks:
            k = round(t / (FRAME_SKIP * m.dt)) - 1  # the control step ending at t
            d = np.array([np.linalg.norm(tracks[e][k] - ref[e][k]) for e in ref])
            row.append(f"after {t:g} s {1e3 * np.nanmean(d):.2f} / {1e3 * np.nanmax(d):.2f}"
                       + ("" if np.isfinite(d).all() else " (diverged)"))
        print(f"  {1e3 * h:5g} ms: " + "; ".join(row))


if __name__ == "__main__":
    main()
