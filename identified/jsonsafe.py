"""JSON that is always valid: non-finite numbers become ``null`` (strict JSON has no NaN or inf)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["finite_or_none", "json_safe"]


def finite_or_none(x: Any) -> float | None:
    """``x`` as a float, or ``None`` when it is not a finite number (NaN, infinity, not a number)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def json_safe(obj: Any) -> Any:
    """``obj`` with numpy scalars and arrays made plain and every NaN or infinity replaced by ``None``."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
