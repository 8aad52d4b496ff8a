"""The story end to end: identify the robot from plant data, train on the twin, evaluate on the plant.

    python examples/train_on_twin.py                       # full budget: 100k training steps
    python examples/train_on_twin.py --quick               # small budget (minutes on 2 cores)
    python examples/train_on_twin.py --wrong-twin          # also train on twins with parameters 30 % off

1. build the robot (the MuJoCo plant, ``ico``/``robot`` preset) and write its MJCF;
2. collect rollouts of the plant with exciting cable commands and pushes;
3. fit the twin (with the search for missing effects, ``effects="auto"``, where the fit has it);
4. train a PPO policy on the natively batched twin (MuJoCo is never stepped);
5. run the policy on the twin and on the plant from the same seeds, beside a random policy, and
   print the gap (:func:`tensegrity_gym.gap.measure_gap`, what ``tensegrity gap`` prints).

``--wrong-twin`` repeats 4-5 on two wrong twins, built from the robot's nominal parameters with
every K, c, M and I off by +30 % or -30 % (random signs), and prints the gaps side by side:

* ``wrong twin (+-30 %, no effects)``: without the identified effects the
  twin has no ground (ground contact is an identified effect; the spring-rod model alone has
  none), so the robot falls from its 0.71 m stance below the healthy height (0.4 m) and every
  episode ends after ~13 control steps ("collapsed"): PPO learns nothing about rolling there;
* ``wrong twin (+-30 %, identified contact)``: the same wrong spring-rod parameters with the
  identified ground contact kept, which isolates the cost of wrong K, c, M, I.
Outputs (MJCF, dataset, models, policies, gap JSON) go to ``--out``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import time

import numpy as np

from identified import Topology
from identified.dataset import atomic_write, save_dataset
from identified.fit.identify import ScaleSpec, identify
from identified.model import IdentifiedModel, save_model
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.gap import measure_gap
from tensegrity_gym.models import preset_parameters, write_model
from tensegrity_gym.training import DEFAULT_ROLLOUT, TrainConfig, train


def fit_twin(data, mjcf: str) -> IdentifiedModel:
    """The identified twin with the effect search (``tensegrity fit --effects auto``), as
    ``scripts/make_shipped_model.sh`` fits the shipped model; the pushes in newtons fix the scale."""
    try:
        from identified.fit.pipeline import fit_model
    except ImportError:  # a fit without the effect search: the spring-rod model alone
        print("   (this version of the fit has no effect search: spring-rod parameters only)")
        model = identify(data, Topology.from_mjcf(mjcf), scale=ScaleSpec())
    else:
        model = fit_model(data, mjcf, effects="auto", progress=True)
    model.source_model = os.path.abspath(mjcf)
    return model


def wrong_twin(model: IdentifiedModel, seed: int, off: float = 0.3, keep_effects: bool = False) -> IdentifiedModel:
    """The robot's nominal parameters with every K, c, M, I off by +off or -off (signs drawn with
    ``seed``), without effects (``keep_effects``: with ``model``'s identified effects)."""
    truth = preset_parameters("ico", "robot")
    rods = {r["name"]: r for r in truth["rods"]}
    springs = {s["name"]: s for s in truth["springs"]}
    topo = model.topology
    rng = np.random.default_rng(seed)

    def skew(x: np.ndarray) -> np.ndarray:
        return x * (1.0 + off * rng.choice([-1.0, 1.0], size=x.shape))

    wrong = copy.deepcopy(model)
    wrong.stiffness = skew(np.array([springs[n]["stiffness"] for n in topo.spring_names]))
    wrong.damping = skew(np.array([springs[n]["damping"] for n in topo.spring_names]))
    wrong.mass = skew(np.array([rods[n]["mass"] for n in topo.rod_names]))
    wrong.inertia = skew(np.array([rods[n]["inertia"] for n in topo.rod_names], dtype=float))
    wrong.control_scale = 1.0
    wrong.effects = copy.deepcopy(model.effects) if keep_effects else []
    wrong.stderr = {}
    kept = "the identified effects kept" if keep_effects else "no effects"
    wrong.metrics = {"note": f"nominal parameters off by +-{off:.0%}, {kept} (examples/train_on_twin.py)"}
    return wrong


def print_gap(name: str, r: dict) -> None:
    print(f"   {name}:")
    for key, label in (("twin", "policy on the twin"), ("plant", "policy on the plant"),
                       ("random_plant", "random on the plant")):
        print(f"     {label:22s} return {r[key]['return']:9.4g}   progress {r[key]['progress_m']:8.3g} m   "
              f"episode {r[key]['episode_steps']:5.0f} steps")
    tr, ol = r["transfer"], r["open_loop"]
    fmt = lambda x: "n/a" if x is None else f"{x:.3g}"
    print(f"     plant/twin progress {fmt(tr['plant_over_twin'])}, plant/random {fmt(tr['plant_over_random'])}; "
          f"open loop: COM divergence at 1 s {fmt(ol['at']['1s'])} m, 0.1 m reached after "
          f"{fmt(ol['time_to_0.1m_s'])} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="runs/train_on_twin", help="output folder")
    ap.add_argument("--timesteps", type=int, default=100_000, help="training steps on the twin")
    ap.add_argument("--collect-episodes", type=int, default=10, help="plant rollouts to identify from")
    ap.add_argument("--collect-steps", type=int, default=3000,
                    help="physics steps per rollout (3000 of 1 ms: long enough for random commands to roll it)")
    ap.add_argument("--episodes", type=int, default=10, help="evaluation episodes on each")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true",
                    help="small budget: 20,480 training steps (5 updates of 4,096), 4 x 3000 collection steps, "
                    "3 evaluation episodes")
    ap.add_argument("--wrong-twin", action="store_true",
                    help="also train on twins with parameters 30 %% off: without effects (no ground) and with the "
                    "identified ground contact")
    args = ap.parse_args()
    rollout = DEFAULT_ROLLOUT
    if args.quick:  # five updates (a demo, not a result)
        args.timesteps, args.collect_episodes, args.episodes = 20_480, 4, 3
    os.makedirs(args.out, exist_ok=True)
    path = lambda name: os.path.join(args.out, name)
    t_start = time.perf_counter()

    print("== 1. the robot (MuJoCo plant)")
    write_model(path("robot.xml"), "ico", preset="robot")
    print(f"== 2. collect {args.collect_episodes} x {args.collect_steps} steps of the plant")
    data = collect(path("robot.xml"), CollectConfig(episodes=args.collect_episodes, steps=args.collect_steps,
                                                    seed=args.seed, push_every=200))
    save_dataset(path("robot.npz"), data)
    print("== 3. fit the twin")
    model = fit_twin(data, path("robot.xml"))
    save_model(path("twin.json"), model)
    effects = [e.get("name") for e in model.effects] or ["none"]
    print(f"   wrote {path('twin.json')} (effects: {', '.join(effects)})")

    arms = [("identified twin", path("twin.json"), path("policy.zip"))]
    if args.wrong_twin:
        save_model(path("wrong_twin.json"), wrong_twin(model, seed=args.seed))
        arms.append(("wrong twin (+-30 %, no effects)", path("wrong_twin.json"), path("policy_wrong.zip")))
        save_model(path("wrong_twin_contact.json"), wrong_twin(model, seed=args.seed, keep_effects=True))
        arms.append(("wrong twin (+-30 %, identified contact)", path("wrong_twin_contact.json"),
                     path("policy_wrong_contact.zip")))
    results = {}
    for name, twin, policy in arms:
        print(f"== 4. train PPO on the {name}: {args.timesteps} steps")
        r = train(TrainConfig(timesteps=args.timesteps, seed=args.seed, identified=twin, rollout=rollout), policy)
        print(f"   {r.timesteps} steps in {r.wall_s:.0f} s ({r.env_steps_per_s:.0f} steps/s) -> {policy}")
        print(f"== 5. evaluate on the twin and the plant, {args.episodes} episodes each")
        gap = measure_gap(policy, twin, args.episodes, seed=10_000 + args.seed)
        gap["train_wall_s"] = r.wall_s
        results[name] = gap
    atomic_write(path("gap.json"), lambda fh: json.dump(results, fh, indent=1))

    print("== the gap")
    for name, gap in results.items():
        print_gap(name, gap)
    plant_steps = data.n_episodes * data.n_steps
    robot_s = plant_steps * data.dt
    control = robot_s / next(iter(results.values()))["open_loop"]["dt_s"]
    print(f"   plant data used: {plant_steps} physics steps ({robot_s:.0f} s of robot time, {control:.0f} "
          f"control steps) against {args.timesteps} control steps of training, all on the twin")
    print(f"   total {time.perf_counter() - t_start:.0f} s; details in {path('gap.json')}")


if __name__ == "__main__":
    main()
