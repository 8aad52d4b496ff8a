"""Limits checked before work: memory a collection needs, and MuJoCo's instability warnings.

* :func:`check_memory` -- refuse up front, with the figure, a job whose arrays would not fit in
  the memory this machine has available (instead of numpy failing on a 1 PiB allocation).
* :class:`MujocoWarnings` -- while active, MuJoCo's warnings ("Nan, Inf or huge value in QACC
  ... The simulation is unstable") are caught instead of printed (and logged to
  ``MUJOCO_LOG.TXT``), so that the caller turns them into one error naming the episode.
"""

from __future__ import annotations

import os
from typing import Self

import mujoco

__all__ = ["MemoryLimitError", "MujocoWarnings", "available_memory", "check_memory", "collect_bytes",
           "format_bytes"]

#: a job may take at most this share of the available memory
MEMORY_SHARE = 0.8


class MemoryLimitError(ValueError):
    """The job's arrays would not fit in the available memory."""


def available_memory() -> int:
    """Bytes of memory available now (``MemAvailable``; physical memory where that is unknown)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2**63


def format_bytes(n: float) -> str:
    """``1.28 PiB``, ``512 MiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if abs(n) < 1024 or unit == "EiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def collect_bytes(episodes: int, steps: int, rods: int, tendons: int, actuated: int) -> int:
    """Bytes of the record of a collection: states at T+1 instants, commands and pushes at T
    (float64), twice over (noise is added to a copy, the writer compresses from it)."""
    states = episodes * (steps + 1) * rods * 13
    per_step = episodes * steps * (actuated + tendons + 6 * rods)
    return 2 * 8 * (states + per_step)


def check_memory(nbytes: int, what: str, available: int | None = None) -> None:
    """Raise :class:`MemoryLimitError` when ``nbytes`` exceed the share of memory a job may take."""
    avail = available_memory() if available is None else available
    if nbytes > MEMORY_SHARE * avail:
        raise MemoryLimitError(f"{what} needs about {format_bytes(nbytes)} of memory, this machine has "
                               f"{format_bytes(avail)} available: record less, or several smaller datasets")


class MujocoWarnings:
    """Context manager: catch MuJoCo's warnings in ``messages`` instead of printing them."""

    def __init__(self) -> None:
        self.messages: list[str] = []
        self._previous = None

    def _catch(self, msg: str) -> None:
        self.messages.append(str(msg).strip())

    def __enter__(self) -> Self:
        self._previous = mujoco.get_mju_user_warning()
        mujoco.set_mju_user_warning(self._catch)
        return self

    def __exit__(self, *exc) -> None:
        mujoco.set_mju_user_warning(self._previous)
