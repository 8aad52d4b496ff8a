"""Argument types of the ``tensegrity`` command that refuse nonsense before any work starts.

Each is an ``argparse`` ``type=``: a bad value becomes ``argument --OPTION: <reason>`` in the
command's one-line error, so the message names the option and the value the user typed.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = ["count", "finite_float", "jobs", "names", "noise", "seed"]

#: largest seed numpy's generators take
MAX_SEED = 2**63 - 1


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None


def count(minimum: int = 1) -> Callable[[str], int]:
    """A whole number ``>= minimum`` (steps, episodes, durations, windows)."""

    def parse(text: str) -> int:
        v = _int(text)
        if v < minimum:
            raise argparse.ArgumentTypeError(f"must be a whole number >= {minimum}, got {text}")
        return v

    parse.__name__ = "count"
    return parse


def jobs(text: str) -> int | str:
    """``auto`` or a whole number >= 1 of processes."""
    if text.strip() == "auto":
        return "auto"
    v = _int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be auto or a whole number >= 1, got {text}")
    return v


def names(text: str) -> tuple[str, ...]:
    """Comma-separated names (``cable0,cable7``), each non-empty, none twice."""
    out = tuple(n.strip() for n in text.split(","))
    if not all(out):
        raise argparse.ArgumentTypeError(f"an empty name in '{text}' (names are separated by commas)")
    twice = [n for i, n in enumerate(out) if n in out[:i]]
    if twice:
        raise argparse.ArgumentTypeError(f"'{twice[0]}' is named twice in '{text}'")
    return out


def seed(text: str) -> int:
    """A seed: a whole number in 0..2**63-1."""
    v = _int(text)
    if not 0 <= v <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed must be a whole number in 0..{MAX_SEED}, got {text}")
    return v


def finite_float(low: float, high: float, unit: str, low_open: bool = False) -> Callable[[str], float]:
    """A finite number in ``[low, high]`` (``(low, high]`` with ``low_open``), in ``unit``."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        bad_low = v <= low if low_open else v < low
        if not math.isfinite(v) or bad_low or v > high:
            lo = f"> {low:g}" if low_open else f">= {low:g}"
            raise argparse.ArgumentTypeError(f"must be a finite number {lo} and <= {high:g} {unit}, got {text}")
        return v

    parse.__name__ = "number"
    return parse


def noise(high: float, unit: str) -> Callable[[str], float]:
    """A sensor-noise standard deviation: finite, >= 0, at most ``high`` (beyond it the record is noise)."""
    return finite_float(0.0, high, unit)
