"""A cache on disk of the twin's compiled substep, so that a new process starts in about a second.

``torch.compile`` pays its tracing (dynamo), its graph transformations (AOTAutograd) and inductor's
code generation in every new process; inductor's own on-disk cache skips only part of that. Here
the substep is compiled ahead of time (``torch.compile(..., fullgraph=True).aot_compile``) and the
whole compiled function, dynamo's bytecode and guards included, is stored with
``save_compiled_function``; the next process loads it (``torch.compiler.load_compiled_function``)
instead of tracing again.

What a stored substep depends on, and how a stale one is never used:

* **the key** (the file name): the format, torch's and Python's versions, the machine, the inductor
  options and a *fingerprint* of the call: every Python scalar, string and flag reachable from the
  substep's inputs and the twin's attributes it reads (the engine's time step, effect options,
  motor limits, which optional parts exist: these are constants in the compiled code) by value,
  every tensor and array by shape, stride, dtype and device (tensors are inputs of the compiled
  code, read afresh at each call: a refitted model of the same structure uses the same substep);
* **the code**: the entry records a SHA-256 of every Python module the compiled code was traced
  through; a module that changed since makes the entry stale: it is compiled again and replaced;
* **dynamo's guards**, checked on the first call: a failing guard makes it a miss too.

Entries are written atomically (a temporary file in the same folder, then a rename): a reader sees
a whole entry or none. An entry that does not load (truncated, another torch) is a miss.

The folder: ``$TENSEGRITY_TWIN_CACHE`` if set (``0``/``off`` turns the cache off), else
``$XDG_CACHE_HOME/tensegrity-gym/twin-substep`` (``~/.cache/...``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib
import os
import pickle
import platform
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

__all__ = ["CACHE_ENV", "CachedSubstep", "cache_dir", "call_key", "load_or_compile", "prefetch"]

#: Environment variable: the cache folder, or ``0``/``off`` for no cache.
CACHE_ENV = "TENSEGRITY_TWIN_CACHE"
#: Bumped when the entry's layout changes.
FORMAT = 2


def cache_dir() -> str | None:
    """The cache folder (module docstring), ``None`` when the cache is off."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "false", "no"):
            return None
        return os.path.expanduser(value)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "tensegrity-gym", "twin-substep")


def _walk(x: Any, out: list[str], seen: dict[int, Any], depth: int = 0) -> None:
    """Append what a compiled function can depend on in ``x`` to ``out`` (see :func:`call_key`).
    ``seen``: the objects walked so far, by id (held, so that no id is reused while walking)."""
    if depth > 12:
        out.append("<deep>")
        return
    if isinstance(x, torch.Tensor):
        out.append(f"T{tuple(x.shape)}{x.stride()}{x.dtype}{x.device}{x.requires_grad}")
        return
    if isinstance(x, np.ndarray):
        out.append(f"A{x.shape}{x.strides}{x.dtype}")
        return
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes, torch.dtype, torch.device, np.generic)):
        out.append(f"{type(x).__name__}:{x!r}")
        return
    if id(x) in seen:
        out.append("<seen>")
        return
    seen[id(x)] = x
    name = f"{type(x).__module__}.{type(x).__qualname__}"
    if isinstance(x, (list, tuple)):
        out.append(f"{name}[{len(x)}")
        for v in x:
            _walk(v, out, seen, depth + 1)
        out.append("]")
    elif isinstance(x, dict):
        out.append(f"{name}{{{len(x)}")
        items = []
        for k, v in x.items():  # in the order of the keys' fingerprints (a repr may hold an address)
            kparts: list[str] = []
            _walk(k, kparts, {}, depth + 1)
            items.append(("\n".join(kparts), v))
        for ktext, v in sorted(items, key=lambda kv: kv[0]):
            out.append(ktext)
            _walk(v, out, seen, depth + 1)
        out.append("}")
    elif callable(x) and hasattr(x, "__qualname__"):
        out.append(f"fn:{getattr(x, '__module__', '')}.{x.__qualname__}")
    else:
        fields = dict(vars(x)) if hasattr(x, "__dict__") else {}
        for slot in getattr(type(x), "__slots__", ()):
            if hasattr(x, slot):
                fields[slot] = getattr(x, slot)
        if dataclasses.is_dataclass(x) and not fields:
            fields = {f.name: getattr(x, f.name) for f in dataclasses.fields(x)}
        out.append(f"{name}(")
        _walk(fields, out, seen, depth + 1)
        out.append(")")


def call_key(fn: Callable[..., Any], inputs: Sequence[Any], options: dict[str, Any]) -> str:
    """The cache key of compiling ``fn`` for a call on ``inputs`` with inductor ``options``: the
    versions, the machine, the options, ``fn``'s name and the fingerprint of ``inputs`` (scalars
    by value, tensors and arrays by layout; module docstring). SHA-256, hex."""
    parts = [f"format {FORMAT}", f"torch {torch.__version__}", f"python {sys.version}",
             f"machine {platform.machine()} {sys.platform}", f"options {sorted(options.items())!r}",
             f"fn {fn.__module__}.{fn.__qualname__}"]
    _walk(list(inputs), parts, {})
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _module_hashes(modules: Sequence[str]) -> dict[str, str] | None:
    """SHA-256 of the source file of each module (``None`` when one has no readable file)."""
    out = {}
    for name in sorted(set(modules)):
        try:
            path = importlib.import_module(name).__file__
            with open(path, "rb") as fh:  # type: ignore[arg-type]
                out[name] = hashlib.sha256(fh.read()).hexdigest()
        except (ImportError, OSError, TypeError):
            return None
    return out


def _signature(args: Sequence[Any]) -> tuple:
    """What must stay the same for a checked compiled call to apply: which inputs are ``None``
    and the layout of the tensors (a cheap check per call instead of all of dynamo's guards)."""
    sig = []
    for a in args:
        if isinstance(a, torch.Tensor):
            sig.append((a.shape, a.dtype))
        elif isinstance(a, tuple):
            sig.append(_signature(a))
        else:
            sig.append(a is None)
    return tuple(sig)


class CachedSubstep:
    """A substep loaded from (or just stored in) the cache, for the calls it was compiled for.

    ``fn(obj, *args)`` is the ahead-of-time compiled function, its guards checked on the first
    call (:func:`load_or_compile`); calls with another signature (a push, another block shape) go
    to ``fallback()`` (made at the first such call: a plain ``torch.compile``, which compiles them
    as it always does)."""

    def __init__(self, fn: Any, obj: Any, args: Sequence[Any], fallback: Callable[[], Callable[..., Any]]) -> None:
        self.fn, self.obj, self._make_fallback = fn, obj, fallback
        self._fallback: Callable[..., Any] | None = None
        self.signature = _signature(args)

    def __call__(self, *args: Any) -> Any:
        if _signature(args) == self.signature:
            return self.fn(self.obj, *args)
        if self._fallback is None:
            self._fallback = self._make_fallback()
        return self._fallback(*args)


#: The background probe of :func:`prefetch` (joined before a load: its answers are cached).
_PREFETCH: list[threading.Thread] = []


def prefetch() -> None:
    """Start early what the first compiled step needs, when a cache is on: inductor probes the
    machine's vector instruction sets in a background thread (it builds and loads a test library
    per instruction set, each in a child process: 1-2 s of waiting) while this thread imports the
    inductor modules a load needs (1-2 s). Once per process."""
    if _PREFETCH or cache_dir() is None:
        return
    try:
        from torch._inductor import codecache, cpp_builder, cpu_vec_isa  # noqa: F401  (the imports a load needs)
    except Exception:  # noqa: BLE001 - no inductor here: nothing to prefetch
        return

    def check(isa: Any) -> None:
        with contextlib.suppress(Exception):  # the load probes again and reports what fails
            bool(isa)  # inductor's probe of one instruction set (cached on the instance)

    def probe() -> None:
        # the instruction sets the CPU reports, probed side by side (each probe mostly waits for
        # its child process); inductor's own pass over them then finds every answer cached
        with contextlib.suppress(Exception):
            flags = cpu_vec_isa.x86_isa_checker()
            sets = [isa for isa in cpu_vec_isa.supported_vec_isa_list if all(f in flags for f in str(isa).split())]
            workers = [threading.Thread(target=check, args=(isa,), daemon=True) for isa in sets]
            for w in workers:
                w.start()
            for w in workers:
                w.join()
        with contextlib.suppress(Exception):
            cpu_vec_isa.pick_vec_isa()

    thread = threading.Thread(target=probe, name="twin-substep-prefetch", daemon=True)
    _PREFETCH.append(thread)
    thread.start()
    # while the probe waits for its child processes: the rest of what a load imports (a failure
    # here shows again, and is handled, in the load)
    with contextlib.suppress(Exception):
        from torch._inductor import graph  # noqa: F401


def _read(path: str, key: str) -> Any | None:
    """The compiled function stored at ``path`` if it is whole, for ``key``, of this code; else ``None``."""
    try:
        with open(path, "rb") as fh:
            entry = pickle.load(fh)
        if not isinstance(entry, dict) or entry.get("format") != FORMAT or entry.get("key") != key:
            return None
        if _module_hashes(list(entry["modules"])) != entry["modules"]:
            return None  # the code it was traced through has changed: stale
        import io

        return torch.compiler.load_compiled_function(io.BytesIO(entry["payload"]))
    except Exception:  # noqa: BLE001 - a damaged or foreign entry is a miss, whatever it raises
        return None


def _write(path: str, key: str, compiled: Any) -> bool:
    """Store ``compiled`` at ``path`` atomically; ``False`` (nothing written) when it cannot be."""
    try:
        modules = sorted({s.module for s in compiled.source_info().inlined_sources})
        hashes = _module_hashes(modules)
        if hashes is None:
            return False
        payload = type(compiled).serialize(compiled).serialized_data
        entry = {"format": FORMAT, "key": key, "torch": torch.__version__, "modules": hashes, "payload": payload}
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".tmp-", suffix=".substep")
        try:
            with os.fdopen(fd, "wb") as fh:
                pickle.dump(entry, fh, protocol=pickle.HIGHEST_PROTOCOL)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except Exception:  # noqa: BLE001 - a cache that cannot be written is no cache, not an error
        return False
    return True


def load_or_compile(fn: Callable[..., Any], obj: Any, args: Sequence[Any], options: dict[str, Any],
                    fallback: Callable[[], Callable[..., Any]], reads: dict[str, Any]
                    ) -> tuple[Callable[..., Any], str]:
    """``fn(obj, *args)`` compiled: loaded from the cache, or compiled ahead of time and stored.

    ``reads``: the attributes of ``obj`` that ``fn`` reads (by name), fingerprinted into the key
    with ``args`` (the rest of ``obj`` is state that does not shape the compiled code).

    Returns ``(substep, status)``: ``substep(*args)`` a :class:`CachedSubstep`, ``status``
    ``"hit"`` (loaded) or ``"stored"`` (compiled now and stored; ``"unsaved"`` where the folder
    cannot be written); or ``(fallback(), "off")`` when the cache is off and ``(fallback(),
    "failed")`` when the ahead-of-time compilation fails (a graph break, an unsupported input):
    the caller compiles as before (``fallback``: makes the plain compiled function). Errors of
    ``fallback`` itself are the caller's."""
    folder = cache_dir()
    if folder is None:
        return fallback(), "off"
    for thread in _PREFETCH:
        thread.join()
    inputs = (obj, *args)
    key = call_key(fn, (reads, *args), options)
    path = os.path.join(folder, key + ".substep")
    compiled = _read(path, key) if os.path.exists(path) else None
    status = "hit"
    if compiled is not None:
        try:
            if not compiled.guard_check(*inputs):
                compiled = None
        except Exception:  # noqa: BLE001 - guards that cannot be evaluated: not this call's
            compiled = None
    if compiled is None:
        status = "stored"
        try:
            compiled = torch.compile(fn, fullgraph=True, dynamic=False, options=options).aot_compile((inputs, {}))
        except Exception:  # noqa: BLE001 - no ahead-of-time compilation here: the plain one
            return fallback(), "failed"
        if not _write(path, key, compiled):
            status = "unsaved"
    compiled.disable_guard_check()  # checked above (or just traced for these inputs); see CachedSubstep
    return CachedSubstep(compiled, obj, args, fallback), status
