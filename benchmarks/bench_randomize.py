"""Speed of the batched twin with and without domain randomization (``randomize="auto"``).

Prints env steps/s of ``gym.make_vec("TensegrityIco-v0", backend="identified")`` (float32, the
default compiled substep) stepped with random actions, alternating plain and randomized twins in
one process so that both see the same machine load:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_randomize.py [--envs 64] [--steps 200]
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.model import load_model
from tensegrity_gym.backends.identified_backend import default_model_path
from tensegrity_gym.randomize import auto_randomization


def steps_per_s(envs: int, steps: int, randomize) -> float:
    v = gym.make_vec("TensegrityIco-v0", num_envs=envs, vectorization_mode="vector_entry_point", backend="identified",
                     randomize=randomize)
    v.reset(seed=0)
    rng = np.random.default_rng(0)
    A = v.single_action_space.shape[0]
    for _ in range(5):  # compilation and warm-up
        v.step(rng.uniform(-1, 1, (envs, A)))
    t0 = time.perf_counter()
    for _ in range(steps):
        v.step(rng.uniform(-1, 1, (envs, A)))
    v.close()
    return envs * steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    auto = auto_randomization(load_model(default_model_path()))
    print(f"load average {os.getloadavg()[0]:.2f}")
    for _ in range(a.repeats):
        for name, r in (("none", None), ("auto", auto)):
            print(f"{name:5s} {a.envs} envs: {steps_per_s(a.envs, a.steps, r):,.0f} env steps/s", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
