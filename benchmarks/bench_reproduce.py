"""Run every experiment of ``tensegrity reproduce`` and print its rows as Markdown tables.

    .venv/bin/python benchmarks/bench_reproduce.py                 # --quick sizes, ~15 min on 2 cores
    .venv/bin/python benchmarks/bench_reproduce.py --full          # the paper's sizes (hours)
    .venv/bin/python benchmarks/bench_reproduce.py --only ico-uniform,generalization

Each run writes ``benchmarks/reproduce/<experiment>.<quick|full>.json`` (the ``--json`` of the
command) and its figures into ``benchmarks/reproduce/figures/`` (git-ignored PNGs), and prints
the wall time.  Nothing here asserts; the tables in docs/RESULTS.md are pasted from its output.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def markdown(rows: list[dict]) -> str:
    """Rows as a Markdown table (``X ± X_std`` merged; numbers to 4 significant digits)."""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    cols = [c for c in cols if not (c.endswith("_std") and c[:-4] in cols) and c != "note"
            and not any(isinstance(r.get(c), (dict, list)) for r in rows)]

    def fmt(v):
        if v is None:
            return "–"
        if isinstance(v, float):
            return f"{v:.4g}" if math.isfinite(v) else "diverged"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            s = fmt(r.get(c))
            if r.get(f"{c}_std") is not None:
                s += f" ± {fmt(r[f'{c}_std'])}"
            cells.append(s)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    from tensegrity_gym.reproduce import EXPERIMENTS, run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="the paper's sizes instead of --quick")
    ap.add_argument("--only", default=None, help="comma-separated experiment names")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    names = args.only.split(",") if args.only else list(EXPERIMENTS)
    out = os.path.join(HERE, "reproduce")
    figs = os.path.join(out, "figures")
    os.makedirs(figs, exist_ok=True)
    kind = "full" if args.full else "quick"
    for name in names:
        t0 = time.perf_counter()
        res = run(name, quick=not args.full, seed=args.seed, out=figs,
                  json_path=os.path.join(out, f"{name}.{kind}.json"), echo=None)
        print(f"\n### {name} ({kind}, seed {args.seed}): {time.perf_counter() - t0:.0f} s wall\n")
        print(markdown(json.loads(json.dumps(res.to_json()))["rows"]))
        for n in res.notes:
            print(f"\n* {n}")


if __name__ == "__main__":
    main()
