"""How the layout of a Newton-with-line-search loop decides what ``torch.compile`` makes of it (CPU).

A toy of the structure of :meth:`identified.effects.pyramid_contact.PyramidContact._law` (six Newton
iterations; twenty one-sided edges per rod; a line search over six step sizes; 64 envs x 6 rods),
written three ways, each compiled by inductor in a fresh cache and called 2,000 times:

* ``lead``: edges and steps on leading axes, (E, N, R) and (6, E, N, R) (the law's layout);
* ``same``: every tensor (N, R), edges and steps as Python lists (``--big``: with inductor's
  ``max_fusion_size`` unbounded, so that the whole loop can become one fused loop);
* ``trail``: the batch axes first, edges and steps trailing, (N, R, E) and (N, R, 6, E).

Prints the compile time and the time of one call::

    python benchmarks/bench_law_layouts.py lead
    python benchmarks/bench_law_layouts.py same --big

(Compiles in a fresh inductor cache unless ``TORCHINDUCTOR_CACHE_DIR`` is set. benchmarks/README.md,
`bench_train.py`: measured 2026-11-27 beside other jobs: lead 40 s / 325 us, same
249 s / 295 us, same --big 206 s / 110 us, trail 41 s / 2,376 us.)
"""

from __future__ import annotations

import argparse
import atexit
import functools
import os
import shutil
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
if "TORCHINDUCTOR_CACHE_DIR" not in os.environ:  # a cold compile, its cache removed after
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="inductor-")
    atexit.register(functools.partial(shutil.rmtree, os.environ["TORCHINDUCTOR_CACHE_DIR"], ignore_errors=True))

import torch

N, R, E, IT = 64, 6, 20, 6
STEPS = (0.0, 1.0, 0.5, 0.25, 0.1, 0.03)


def _pick(cost: list[torch.Tensor]) -> torch.Tensor:
    """The step of least cost (the first of equals), elementwise."""
    best, bs = cost[0], torch.zeros_like(cost[0])
    for k, s in enumerate(STEPS[1:], 1):
        b = cost[k] < best
        bs, best = torch.where(b, s, bs), torch.where(b, cost[k], best)
    return bs


def same(xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    x = list(xs)
    for _ in range(IT):
        v = [x[e % 6] * (1.0 + 0.1 * e) - x[(e + 1) % 6] for e in range(E)]
        w = [a.clamp_min(0.0) for a in v]
        g = [sum(w[e] * (0.5 + e) for e in range(k, E, 6)) for k in range(6)]
        cost = [sum((w[e] - s * g[e % 6]).clamp_min(0.0) ** 2 for e in range(E)) for s in STEPS]
        bs = _pick(cost)
        x = [x[k] - bs * g[k] * 0.01 for k in range(6)]
    return tuple(x)


def lead(xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    x = list(xs)
    coef = torch.arange(E, dtype=torch.float32).reshape(E, 1, 1)
    steps = torch.tensor(STEPS).reshape(6, 1, 1, 1)
    i0, i1 = torch.arange(E) % 6, (torch.arange(E) + 1) % 6
    for _ in range(IT):
        X = torch.stack(x)
        w = (X[i0] * (1.0 + 0.1 * coef) - X[i1]).clamp_min(0.0)
        g = [(w[k::6] * (0.5 + coef[k::6])).sum(0) for k in range(6)]
        cost = ((w - steps * torch.stack(g)[i0]).clamp_min(0.0) ** 2).sum(1)
        bs = _pick(list(cost))
        x = [x[k] - bs * g[k] * 0.01 for k in range(6)]
    return tuple(x)


def trail(xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    x = list(xs)
    coef = torch.arange(E, dtype=torch.float32)
    steps = torch.tensor(STEPS).reshape(6, 1)
    i0, i1 = torch.arange(E) % 6, (torch.arange(E) + 1) % 6
    for _ in range(IT):
        X = torch.stack(x, -1)
        w = (X[..., i0] * (1.0 + 0.1 * coef) - X[..., i1]).clamp_min(0.0)
        g = [(w[..., k::6] * (0.5 + coef[k::6])).sum(-1) for k in range(6)]
        G = torch.stack(g, -1)[..., i0]
        cost = ((w.unsqueeze(-2) - steps * G.unsqueeze(-2)).clamp_min(0.0) ** 2).sum(-1)
        bs = _pick(list(cost.unbind(-1)))
        x = [x[k] - bs * g[k] * 0.01 for k in range(6)]
    return tuple(x)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("layout", choices=("lead", "same", "trail"))
    ap.add_argument("--big", action="store_true", help="inductor's max_fusion_size unbounded")
    ap.add_argument("--calls", type=int, default=2000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    fn = {"lead": lead, "same": same, "trail": trail}[args.layout]
    xs = tuple(torch.randn(N, R, generator=torch.Generator().manual_seed(k)) for k in range(6))
    t0 = time.perf_counter()
    compiled = torch.compile(fn, options={"max_fusion_size": 100_000} if args.big else {})
    out = compiled(xs)
    t_compile = time.perf_counter() - t0
    diff = max(float((a - b).abs().max()) for a, b in zip(out, fn(xs)))
    t0 = time.perf_counter()
    for _ in range(args.calls):
        compiled(xs)
    t_call = (time.perf_counter() - t0) / args.calls
    print(f"{args.layout}{' --big' if args.big else ''}: compile {t_compile:.1f} s, one call {t_call * 1e6:.0f} us "
          f"(compiled vs eager {diff:.1e}); load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
