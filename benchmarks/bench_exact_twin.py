"""How often a twin that is exact passes the per-seed transfer bar: the bar's own noise floor.

``tensegrity gap`` judges a policy by its mean progress over K episodes on the plant over its mean
progress over the same K reset seeds on the twin (>= 0.9 a seed, every seed of a sweep). A roll is
chaotic, so a twin and a plant episode from the same start part ways within seconds however good
the twin, and the ratio of two K-episode means is a random number even for a perfect twin. This
script measures that floor directly: the "twin" is the plant itself, started ``--nudge`` metres
away (every rod's centre moved by an independent U(-nudge, nudge) per axis after the env's own
reset noise), with the same policy, the same reset seeds and the same action-noise draws per seed
(``gap``'s sampled actions). The ratio of a seed is then 1 in expectation: whatever spreads it,
and every miss of the 0.9 line, is the bar's noise, not a model error.

Output: per policy and block of K seeds, the plant/plant ratio, its standard error as ``gap``
reports it, the reading against 0.9 (:func:`tensegrity_gym.gap.against_line`), and the distance
between the two centres of mass at the end of each episode (how far the runs parted); then how
many blocks of a sweep (every policy at the same seeds) pass the bar, beside the same count for
the identified twin where ``--gap`` reports are given.

    python benchmarks/bench_exact_twin.py --policies runs/shipped --blocks 4 --out exact.json
    python benchmarks/bench_exact_twin.py --policies runs/shipped --blocks 2 --gap g0.json g10.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.state import RodState
from tensegrity_gym.backends.mujoco_backend import MujocoBackend
from tensegrity_gym.gap import against_line, policy_act, run_episodes, transfer_ratios
from tensegrity_gym.sweep import policies_in
from tensegrity_gym.training import ENV_ID, load_policy, plant_mjcf


class NudgedPlant(MujocoBackend):
    """The plant, every rod's centre moved by U(-nudge, nudge) per axis after each reset (its own
    generator, seeded once): the same physics started a hair's breadth away."""

    def __init__(self, model: str, nudge: float, seed: int) -> None:
        super().__init__(model)
        self.nudge = float(nudge)
        self._rng = np.random.default_rng(seed)

    def reset(self, states: RodState, rest_lengths: np.ndarray) -> None:
        d = self._rng.uniform(-self.nudge, self.nudge, size=np.shape(states.pos))
        super().reset(RodState(states.pos + d, states.quat, states.vel, states.angvel), rest_lengths)


def plant_envs(mjcf: str, n: int, steps: int, env_kwargs: dict[str, Any], nudge: float | None
               ) -> gym.vector.SyncVectorEnv:
    """``n`` plant envs (``nudge``: each a :class:`NudgedPlant`, its own nudge generator)."""
    def one(k: int):
        def make() -> gym.Env:
            backend: Any = "mujoco" if nudge is None else NudgedPlant(mjcf, nudge, seed=1000 + k)
            kw = dict(env_kwargs) if nudge is not None else {**env_kwargs, "model": mjcf}
            return gym.make(ENV_ID, backend=backend, max_episode_steps=steps, **kw)
        return make
    return gym.vector.SyncVectorEnv([one(k) for k in range(n)])


def block(policy_file: str, seeds: list[int], nudge: float, identified: str | None) -> dict[str, Any]:
    """One policy, one block of seeds: the plant against the nudged plant."""
    pol = load_policy(policy_file)
    steps = int(pol.episode_steps)
    mjcf = plant_mjcf(identified, None)
    K = len(seeds)
    runs = {}
    for name, nd in (("plant", None), ("nudged", nudge)):
        venv = plant_envs(mjcf, K, steps, pol.env_kwargs, nd)
        try:
            runs[name] = run_episodes(venv, policy_act(pol, "sampled", seeds, K), seeds)
        finally:
            venv.close()
    p, q = runs["plant"].summary(), runs["nudged"].summary()
    tr = transfer_ratios(q, p, p)  # the nudged plant in the twin's place
    apart = [float(np.linalg.norm(a[min(len(a), len(b)) - 1] - b[min(len(a), len(b)) - 1]))
             for a, b in zip(runs["plant"].com, runs["nudged"].com)]
    return {"policy": policy_file, "seeds": seeds, "plant_m": p["progress_m"], "nudged_m": q["progress_m"],
            "ratio": tr["plant_over_twin"], "stderr": tr["plant_over_twin_stderr"],
            "against_0.9": against_line(tr["plant_over_twin"], tr["plant_over_twin_stderr"]),
            "com_apart_at_end_m": apart,
            "plant_per_episode_m": p["progress_per_episode_m"], "nudged_per_episode_m": q["progress_per_episode_m"]}


def _gap_blocks(files: list[str]) -> list[tuple[int, int]]:
    """(seeds at >= 0.9, seeds) of each ``tensegrity gap --json`` report over several policies."""
    res = []
    for f in files:
        with open(f) as fh:
            rep = json.load(fh)
        per = rep.get("reports") or [rep]
        ratios = [r["transfer"]["plant_over_twin"] for r in per]
        res.append((sum(r is not None and r >= 0.9 for r in ratios), len(ratios)))
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policies", nargs="+", required=True, help="policy files or `train --seeds` folders")
    ap.add_argument("--identified", default=None, help="the model the policies trained on (names the plant)")
    ap.add_argument("--episodes", type=int, default=10, help="episodes per block (gap's K)")
    ap.add_argument("--blocks", type=int, default=3, help="blocks of seeds: 0..K-1, K..2K-1, ...")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--nudge", type=float, default=1e-6, help="half-width of the start's nudge, m")
    ap.add_argument("--gap", nargs="*", default=[], help="gap --json reports of the same policies, for the side-by-side count")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    try:
        pols = policies_in(a.policies)
    except ValueError as e:
        sys.exit(f"bench_exact_twin: {e}")
    rows = []
    t0 = time.perf_counter()
    for b in range(a.blocks):
        seeds = list(range(a.first_seed + b * a.episodes, a.first_seed + (b + 1) * a.episodes))
        for f in pols:
            r = block(f, seeds, a.nudge, a.identified)
            r["block"] = b
            rows.append(r)
            print(f"block {b} {os.path.basename(os.path.dirname(f)) or f}: plant {r['plant_m']:.3f} m, "
                  f"nudged {r['nudged_m']:.3f} m, ratio {r['ratio']:.3f} ± {r['stderr'] or float('nan'):.3f} "
                  f"({r['against_0.9']}), COM apart at the end: median {np.median(r['com_apart_at_end_m']):.3f} m",
                  flush=True)
    ratios = np.array([r["ratio"] for r in rows], dtype=float)
    passed = [all(r["ratio"] >= 0.9 for r in rows if r["block"] == b) for b in range(a.blocks)]
    apart = np.concatenate([r["com_apart_at_end_m"] for r in rows])
    summary = {
        "policies": len(pols), "blocks": a.blocks, "episodes": a.episodes, "nudge_m": a.nudge,
        "seconds": time.perf_counter() - t0,
        "ratio_mean": float(ratios.mean()), "ratio_sd": float(ratios.std(ddof=1)) if len(ratios) > 1 else None,
        "seeds_under_0.9": int((ratios < 0.9).sum()), "seeds": len(ratios),
        "blocks_every_seed_at_0.9": int(sum(passed)),
        "stderr_median": float(np.median([np.nan if r["stderr"] is None else r["stderr"] for r in rows])),
        "com_apart_at_end_median_m": float(np.median(apart)),
        "com_apart_at_end_under_1cm": int((apart < 0.01).sum()), "episodes_in_all": int(apart.size),
    }
    if a.gap:
        g = _gap_blocks(a.gap)
        summary["identified_twin_blocks"] = [{"report": f, "seeds_at_0.9": m, "seeds": n} for f, (m, n) in zip(a.gap, g)]
    print(f"exact twin (the plant nudged {a.nudge:g} m): {summary['seeds_under_0.9']} of {summary['seeds']} "
          f"seed-blocks under 0.9 (ratio {summary['ratio_mean']:.3f} ± {summary['ratio_sd'] or 0:.3f} sd, "
          f"se median {summary['stderr_median']:.3f}); every seed at 0.9 in {summary['blocks_every_seed_at_0.9']} "
          f"of {a.blocks} blocks; runs apart at the end: median {summary['com_apart_at_end_median_m']:.3f} m, "
          f"{summary['com_apart_at_end_under_1cm']} of {summary['episodes_in_all']} within 1 cm")
    for b in summary.get("identified_twin_blocks", []):
        print(f"identified twin, {b['report']}: {b['seeds_at_0.9']} of {b['seeds']} seeds at 0.9")
    if a.out:
        tmp = a.out + ".tmp"
        with open(tmp, "w") as fh:
            json.dump({"summary": summary, "rows": rows}, fh, indent=1)
        os.replace(tmp, a.out)


if __name__ == "__main__":
    main()
