"""``tensegrity reproduce``: every experiment of the paper, every method a row.

Experiments (names fixed, :data:`EXPERIMENTS`): ``simple-blackbox``, ``simple-physics``
(:mod:`~tensegrity_gym.reproduce.simple`), ``ico-uniform``, ``ico-nonuniform``,
``data-efficiency``, ``generalization`` (:mod:`~tensegrity_gym.reproduce.ico`).  Each returns a
:class:`~tensegrity_gym.reproduce.common.Result`; :func:`run` prints its table, writes its
figures into ``out`` and its rows to a JSON file.  Paper-scale data are the default; ``quick``
scales them down to a few minutes on two cores.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

from tensegrity_gym.reproduce.common import Context, Result, bound_heap, format_table, scratch, write_json

__all__ = ["EXPERIMENTS", "Result", "run"]


def _simple(name: str) -> Callable[[Context], Result]:
    def f(ctx: Context) -> Result:
        from tensegrity_gym.reproduce import simple

        return getattr(simple, name)(ctx)

    return f


def _ico(name: str) -> Callable[[Context], Result]:
    def f(ctx: Context) -> Result:
        from tensegrity_gym.reproduce import ico

        return getattr(ico, name)(ctx)

    return f


EXPERIMENTS: dict[str, Callable[[Context], Result]] = {
    "simple-blackbox": _simple("simple_blackbox"),
    "simple-physics": _simple("simple_physics"),
    "ico-uniform": _ico("ico_uniform"),
    "ico-nonuniform": _ico("ico_nonuniform"),
    "data-efficiency": _ico("data_efficiency"),
    "generalization": _ico("generalization"),
}


def run(name: str, quick: bool = False, seed: int = 0, out: str | None = None, json_path: str | None = None,
        progress: bool = True, echo: Callable[[str], None] | None = print) -> Result:
    """Run experiment ``name``; print its table (``echo``), write figures into ``out`` (a folder,
    created if missing) and the rows to ``json_path`` (atomically)."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment '{name}' (choose from {', '.join(EXPERIMENTS)})")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    if out:
        os.makedirs(out, exist_ok=True)
    if not quick:
        bound_heap()  # paper scale: keep the resident memory near the data's size
    with scratch() as work:
        ctx = Context(quick=quick, seed=seed, out=out, workdir=work, progress=progress)
        t0 = time.perf_counter()
        res = EXPERIMENTS[name](ctx)
        res.seconds = time.perf_counter() - t0
    res.settings = {"quick": quick, "seed": seed, **res.settings}
    if json_path:
        write_json(json_path, res)
    if echo is not None:
        echo(f"{name} ({'quick' if quick else 'paper scale'}, seed {seed}, {res.seconds:.0f} s)")
        echo(format_table(res.rows))
        for n in res.notes:
            echo(f"  * {n}")
        for f in res.figures:
            echo(f"  figure: {f}")
    return res
