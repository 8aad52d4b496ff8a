"""How little plant data the twin pipeline needs: plant seconds against plant progress.

    python benchmarks/bench_plant_data.py [--seconds 4,10,20] [--episode-seconds 2] [--seeds 0-4]
                                          [--jobs 2] [--collect-seed 11] [--episodes 10]
                                          [--direct runs/bench_train/bench_train.json]
                                          [--out runs/plant_data]

For every plant-data budget S (seconds of robot time) it runs the pipeline a user runs, through the
command line, on a fresh collection of the robot preset:

    tensegrity model ico --preset robot --out DIR/robot.xml
    tensegrity collect --model DIR/robot.xml --episodes S/E --steps 1000 E --seed C --push-every 200 --out DIR/S/data.npz
    tensegrity fit DIR/S/data.npz --model DIR/robot.xml --effects auto --out DIR/S/model.json
    tensegrity train --identified DIR/S/model.json --seeds 0-4 --jobs J --out DIR/S/runs     # the defaults
    tensegrity gap --identified DIR/S/model.json --policy DIR/S/runs --episodes 10 --json   > DIR/S/gap.json

(``E`` = ``--episode-seconds``; a step whose output exists is not run again, so an interrupted run
resumes). It prints, per budget, every seed's plant progress and plant/twin ratio, how many seeds
roll >= 0.5 m and how many reach 90 % of their twin progress, and writes ``OUT/plant_data.json``,
``OUT/plant_data.md`` (the table) and ``OUT/plant_data.png`` (plant seconds against plant progress,
every seed, and the direct training's learning curve when ``--direct`` is given).

``--direct FILE``: the ``bench_train.json`` of ``python benchmarks/bench_train.py --curve`` (direct
PPO training on the plant, its policy evaluated on the plant after N plant control steps of 20 ms).
With it, each budget's plant seconds are also given as a percentage of the robot time that direct
training needed to reach the same plant progress (the worst seed's and the mean's); where direct
training never reached it within its run, only a bound is known (``<``). Wang et al. (arXiv
2011.04929) report 0.25 %.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONTROL_DT = 0.02  # s: the env's control period (frame_skip 20 x 1 ms)


def _cli() -> list[str]:
    exe = os.path.join(os.path.dirname(sys.executable), "tensegrity")
    return [exe] if os.path.exists(exe) else [sys.executable, "-m", "tensegrity_gym.cli"]


def run(cmd: list[str], out: str, log: str, stdout: str | None = None) -> float:
    """Run ``cmd`` unless ``out`` exists; wall seconds (0 when skipped)."""
    if os.path.exists(out):
        return 0.0
    t0 = time.time()
    with open(log, "a") as lg:
        lg.write("$ " + " ".join(cmd) + "\n")
        lg.flush()
        if stdout is None:
            subprocess.run(cmd, check=True, stdout=lg, stderr=lg, cwd=ROOT)
        else:
            tmp = stdout + ".part"
            with open(tmp, "w") as fh:
                subprocess.run(cmd, check=True, stdout=fh, stderr=lg, cwd=ROOT)
            os.replace(tmp, stdout)
    return time.time() - t0


def budget(args: argparse.Namespace, seconds: float, xml: str) -> dict:
    """The pipeline on ``seconds`` of plant data; its gap report reduced to the figures."""
    d = os.path.join(args.out, f"{seconds:g}s")
    os.makedirs(d, exist_ok=True)
    log = os.path.join(d, "log.txt")
    steps = round(args.episode_seconds * 1000)
    episodes = max(1, round(seconds / args.episode_seconds))
    data, model, runs, gapf = (os.path.join(d, f) for f in ("data.npz", "model.json", "runs", "gap.json"))
    t = {"collect": run([*_cli(), "collect", "--model", xml, "--episodes", str(episodes), "--steps", str(steps),
                         "--seed", str(args.collect_seed), "--push-every", "200", "--out", data], data, log),
         "fit": run([*_cli(), "fit", data, "--model", xml, "--effects", "auto", "--out", model, "--quiet"], model, log),
         "train": run([*_cli(), "train", "--identified", model, "--seeds", args.seeds, "--jobs", str(args.jobs),
                       "--out", runs], os.path.join(runs, "summary.json"), log),
         "gap": run([*_cli(), "gap", "--identified", model, "--policy", runs, "--episodes", str(args.episodes),
                     "--json"], gapf, log, stdout=gapf)}
    with open(gapf) as fh:
        rep = json.JSONDecoder().raw_decode(fh.read())[0]
    plant = [r["plant"]["progress_m"] for r in rep["reports"]]
    twin = [r["twin"]["progress_m"] for r in rep["reports"]]
    with open(model) as fh:
        fitted = json.load(fh)
    effects = [e.get("name") for e in fitted.get("effects", [])]
    return {"plant_s": episodes * steps * 1e-3, "episodes": episodes, "episode_steps": steps, "effects": effects,
            "plant_m": plant, "twin_m": twin,
            "ratio": [p / w if w > 0 else None for p, w in zip(plant, twin)],
            "seeds_over_0.5m": int(sum(p >= 0.5 for p in plant)),
            "seeds_ratio_over_0.9": int(sum(w > 0 and p / w >= 0.9 for p, w in zip(plant, twin))),
            "wall_s": t}


def direct_anchor(curve: list, level: float) -> dict:
    """Plant robot seconds direct training needed to reach ``level`` m (first snapshot at or above
    it); ``reached`` False: not within its run (then ``robot_s`` is its whole run, a lower bound)."""
    first = next((n for n, p in curve if p >= level), None)
    if first is None:
        return {"reached": False, "robot_s": curve[-1][0] * CONTROL_DT}
    return {"reached": True, "robot_s": first * CONTROL_DT}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", default="4,10,20", help="plant-data budgets, seconds of robot time")
    ap.add_argument("--episode-seconds", type=float, default=2.0, help="length of each collected episode (s)")
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--collect-seed", type=int, default=11)
    ap.add_argument("--episodes", type=int, default=10, help="gap episodes per policy")
    ap.add_argument("--direct", default=None, help="bench_train.json of `bench_train.py --curve`")
    ap.add_argument("--out", default=os.path.join(ROOT, "runs", "plant_data"))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    xml = os.path.join(args.out, "robot.xml")
    run([*_cli(), "model", "ico", "--preset", "robot", "--out", xml], xml, os.path.join(args.out, "log.txt"))
    curve = None
    if args.direct:
        with open(args.direct) as fh:
            curve = [tuple(x) for x in json.load(fh)["plant_curve"]]
    rows = []
    for s in (float(x) for x in args.seconds.split(",")):
        row = budget(args, s, xml)
        if curve:
            for key, level in (("worst", min(row["plant_m"])), ("mean", float(np.mean(row["plant_m"])))):
                a = direct_anchor(curve, level)
                a["percent"] = 100 * row["plant_s"] / a["robot_s"]
                row[f"direct_{key}"] = a
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "wall_s"}), flush=True)
    head = ("| plant data | per seed: plant progress (plant / twin) | worst | mean | seeds >= 0.5 m | "
            "seeds >= 90 % | of direct training's plant time (worst / mean) |")
    lines = [head, "|" + " --- |" * 7]
    for r in rows:
        per = ", ".join(f"{p:.2f} ({q:.2f})" if q is not None else f"{p:.2f} (-)" for p, q in zip(r["plant_m"], r["ratio"]))
        pct = "-"
        if "direct_worst" in r:
            pct = " / ".join(("" if r[k]["reached"] else "< ") + f"{r[k]['percent']:.2f} %" for k in ("direct_worst", "direct_mean"))
        lines.append(f"| {r['plant_s']:g} s ({r['episodes']} x {r['episode_steps']} steps) | {per} | "
                     f"{min(r['plant_m']):.2f} m | {np.mean(r['plant_m']):.2f} m | {r['seeds_over_0.5m']} / {len(r['plant_m'])} | "
                     f"{r['seeds_ratio_over_0.9']} / {len(r['plant_m'])} | {pct} |")
    table = "\n".join(lines)
    print(table)
    with open(os.path.join(args.out, "plant_data.md"), "w") as fh:
        fh.write(table + "\n")
    with open(os.path.join(args.out, "plant_data.json.part"), "w") as fh:
        json.dump({"budgets": rows, "direct_curve": curve}, fh, indent=1)
    os.replace(os.path.join(args.out, "plant_data.json.part"), os.path.join(args.out, "plant_data.json"))
    plot(rows, curve, os.path.join(args.out, "plant_data.png"))


def plot(rows: list[dict], curve: list | None, path: str) -> None:
    """Plant seconds (log) against plant progress: every seed, the mean, direct training's curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r in rows:
        ax.scatter([r["plant_s"]] * len(r["plant_m"]), r["plant_m"], color="tab:blue", s=14, alpha=0.6)
    ax.plot([r["plant_s"] for r in rows], [np.mean(r["plant_m"]) for r in rows], "o-", color="tab:blue",
            label="twin pipeline: fit on S s, 5 seeds (mean)")
    if curve:
        ax.plot([n * CONTROL_DT for n, _ in curve], [p for _, p in curve], "s--", color="tab:red",
                label="direct PPO on the plant")
    ax.axhline(0.5, color="grey", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("plant data (s of robot time)")
    ax.set_ylabel("progress on the plant per 1000-step episode (m)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path + ".part.png", dpi=120)
    plt.close(fig)
    os.replace(path + ".part.png", path)


if __name__ == "__main__":
    main()
