"""Torch's intra-op thread count, set for a block and restored after.

Torch's thread count is process-wide, and its idle threads spin: on a machine whose cores are
shared (another process, or this package's own worker processes) more threads than free cores
make torch many times slower, never faster.  The package's long-running parts (the twin, the
effect search's workers, the reproduced experiments) set their count for their own work with
:func:`torch_threads` and give the caller's back after.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["torch_threads"]


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads, then restore the caller's count
    (``None`` or the current count: nothing changes)."""
    old = torch.get_num_threads()
    if n is None or n == old:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
