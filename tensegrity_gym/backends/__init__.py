"""Physics backends of the env: one protocol (:class:`Backend`), several engines.

``make_backend(name, model, **kwargs)`` builds one by name. The registry maps a name to
``"module:Class"`` and imports the module only when that backend is asked for, so a backend's
dependencies (MuJoCo, torch) load only when used. Add a backend with :func:`register_backend`.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

from tensegrity_gym.backends.base import Backend, MotorSpec, RodState

__all__ = ["BACKENDS", "Backend", "MotorSpec", "RodState", "make_backend", "register_backend"]

#: backend name -> "module:Class"; the class is called as ``Class(model, **kwargs)``
BACKENDS: dict[str, str] = {
    "mujoco": "tensegrity_gym.backends.mujoco_backend:MujocoBackend",
    "identified": "tensegrity_gym.backends.identified_backend:IdentifiedBackend",
}


def register_backend(name: str, entry_point: str) -> None:
    """Make ``backend=name`` available; ``entry_point`` is ``"module:Class"``."""
    if ":" not in entry_point:
        raise ValueError(f"entry_point must look like 'module:Class', got {entry_point!r}")
    BACKENDS[name] = entry_point


def make_backend(name: str, model: str | os.PathLike | Any | None = None, **kwargs: Any) -> Backend:
    """Build the backend ``name`` (see :data:`BACKENDS`) for ``model`` (``None``: its default)."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; available backends: {', '.join(sorted(BACKENDS))}")
    module, _, attr = BACKENDS[name].partition(":")
    cls = getattr(importlib.import_module(module), attr)
    backend = cls(model, **kwargs)
    if not isinstance(backend, Backend):
        raise TypeError(f"{BACKENDS[name]} did not build a tensegrity_gym.backends.Backend")
    return backend
