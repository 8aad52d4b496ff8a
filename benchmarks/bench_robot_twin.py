"""The robot's twin against its plant: standing, rolling on every cable, free-run error.

The robot's figures, for any identified model of the robot (default: the shipped one,
``identified/data/robot.json``, from ``scripts/make_shipped_model.sh``):

* **standing**: plant and twin from the same reset (seed), neutral commands for 5 s; the centre of
  mass's height and its (x, y) apart at the end;
* **rolling**: for every actuated cable, contracted fully for 2 s, then neutral for 2.5 s (the
  procedure of ``tests/test_effects.py::test_shipped_twin_rolls_like_the_plant``): the centre of
  mass's (x, y) displacement in plant and twin; a cable whose plant displacement exceeds
  ``--roll`` m rolls the robot onto a neighbouring face (an edge of the base triangle), and the twin
  must land where the plant does (distance between the two displacements relative to the plant's);
  every other cable must roll neither;
* **free run**: on fresh plant episodes of random cable commands (``collect``), the position error
  over 1 s of the model with its effects and without them (no ground: it falls through the floor).

    python benchmarks/bench_robot_twin.py                       # the shipped model, ~2 min
    python benchmarks/bench_robot_twin.py --model F.json --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.model import load_model
from identified.predict import rollout_errors
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.envs.tensegrity_ico_v0 import rest_to_action
from tensegrity_gym.models import write_model


def _neutral(env: gym.Env) -> np.ndarray:
    u = env.unwrapped
    return rest_to_action(u.backend.nominal_rest_lengths(), u.rest_min, u.rest_max)


def stand(env: gym.Env, seed: int, steps: int = 250) -> tuple[float, np.ndarray, bool]:
    """Neutral commands for ``steps`` control steps: final (height, (x, y)), whether it terminated."""
    _, info = env.reset(seed=seed)
    a = _neutral(env)
    for _ in range(steps):
        _, _, term, _, info = env.step(a)
        if term:
            return float(info["com_height"]), np.asarray(info["com"][:2]), True
    return float(info["com_height"]), np.asarray(info["com"][:2]), False


def roll(env: gym.Env, cable: str, seed: int = 0) -> np.ndarray:
    """Contract ``cable`` fully for 2 s, then neutral for 2.5 s: the centre of mass's (x, y) move."""
    _, info = env.reset(seed=seed)
    names = list(env.unwrapped.backend.actuated_names)
    neutral = _neutral(env)
    start = np.asarray(info["com"][:2]).copy()
    for k in range(225):
        a = neutral.copy()
        if k < 100:
            a[names.index(cable)] = -1.0
        _, _, term, _, info = env.step(a)
        if term:
            break
    return np.asarray(info["com"][:2]) - start


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="identified model JSON (default: the shipped robot model)")
    p.add_argument("--seeds", default="0,1,2,3,4", help="reset seeds of the standing test")
    p.add_argument("--roll", type=float, default=0.3, help="plant displacement (m) that counts as a roll")
    p.add_argument("--episodes", type=int, default=4, help="fresh plant episodes of the free-run error")
    args = p.parse_args()
    torch.set_num_threads(1)
    kw = {} if args.model is None else {"model": args.model}
    plant = gym.make("TensegrityIco-v0", max_episode_steps=1000)
    twin = gym.make("TensegrityIco-v0", backend="identified", max_episode_steps=1000, **kw)
    model = load_model(args.model) if args.model else twin.unwrapped.backend.model
    print(f"model: {args.model or 'shipped'}; effects {[e['name'] for e in model.effects]}")

    print("\nstanding, 5 s of neutral commands (centre of mass):")
    print(f"{'seed':>4} {'plant height':>12} {'twin height':>11} {'|dh| (mm)':>9} {'|dxy| (mm)':>10}")
    worst = 0.0
    for seed in (int(s) for s in args.seeds.split(",")):
        (hp, xyp, tp), (ht, xyt, tt) = stand(plant, seed), stand(twin, seed)
        worst = max(worst, abs(hp - ht))
        flag = "  (terminated: " + ("plant " if tp else "") + ("twin" if tt else "") + ")" if tp or tt else ""
        print(f"{seed:>4} {hp:12.4f} {ht:11.4f} {1e3 * abs(hp - ht):9.2f} {1e3 * np.linalg.norm(xyp - xyt):10.2f}{flag}")
    print(f"largest height difference: {1e3 * worst:.2f} mm (target: within 50 mm)")

    print(f"\nrolling: each cable contracted 2 s, then neutral 2.5 s (a roll: plant moves > {args.roll} m):")
    print(f"{'cable':<8} {'plant dx, dy (m)':>18} {'twin dx, dy (m)':>18} {'|plant|':>8} {'|twin|':>7} "
          f"{'|twin-plant|/|plant|':>20}")
    rolls, still = [], []
    for cable in plant.unwrapped.backend.actuated_names:
        dp, dt = roll(plant, cable), roll(twin, cable)
        rel = np.linalg.norm(dt - dp) / max(np.linalg.norm(dp), 1e-12)
        is_roll = np.linalg.norm(dp) > args.roll
        (rolls if is_roll else still).append((cable, rel, float(np.linalg.norm(dt))))
        print(f"{cable:<8} {dp[0]:8.3f} {dp[1]:8.3f}  {dt[0]:8.3f} {dt[1]:8.3f}  {np.linalg.norm(dp):8.3f} "
              f"{np.linalg.norm(dt):7.3f} {(f'{100 * rel:.1f} %' if is_roll else '-'):>20}")
    if rolls:
        print(f"{len(rolls)} cables roll the plant ({', '.join(c for c, _, _ in rolls)}); the twin lands within "
              f"{100 * max(r for _, r, _ in rolls):.1f} % of the plant's displacement (target: 30 %, aim 10 %)")
    if still:
        print(f"{len(still)} cables roll neither: the twin moves at most {max(d for _, _, d in still):.3f} m "
              f"({max(still, key=lambda x: x[2])[0]})")

    with tempfile.TemporaryDirectory() as d:
        mjcf = Path(d) / "robot.xml"
        write_model(mjcf, "ico", preset="robot", seed=0)
        test = collect(mjcf, CollectConfig(episodes=args.episodes, steps=1000, seed=4242, push_every=200))
    H = min(test.n_steps, round(1.0 / test.dt))
    bare = copy.deepcopy(model)
    bare.effects = []
    before = rollout_errors(bare, test, horizon=H)["pos_mean"]
    after = rollout_errors(model, test, horizon=H)["pos_mean"]
    print(f"\nfree run over 1 s, {args.episodes} fresh plant episodes (seed 4242), mean rod position error: "
          f"without the model's effects {before:.3f} m, with them {after:.4f} m ({before / after:.0f}x; "
          "target: at least 10x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
