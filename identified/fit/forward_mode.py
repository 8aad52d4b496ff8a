"""Forward-mode derivatives through the engine without torch's slow path for constants.

In forward mode every input without a tangent (a Python number such as ``dt`` or ``2``, a constant
tensor such as a rest length) gets a zero tangent that torch represents by an efficient zero
tensor (no storage).  A product or sum with one, ``a * y`` with ``y`` constant, needs only the
result's shape, and torch 2.13 finds it by running the operation on its ``Meta`` device, where the
kernel registered is its Python reference implementation (``torch._refs``, through ``torch._prims``):
about 0.5 ms of Python for each such operation, whatever the tensors' size.  Measured on the marker
fit of clean 100 Hz markers (one window of 6 frames, 1 state + 2 joint steps at 5 ms): 12.3 s, of
which 8.8 s in that path; 5.2 s with :func:`shape_only_meta`, the result bit for bit the same.

:func:`shape_only_meta` registers, while it is entered, ``Meta`` kernels for the four elementwise
binary operations that compute the shape (broadcast) and the dtype (promoted) only, and removes
them on leaving, which restores torch's own.  It is entered around the Jacobians' forward passes
only (:meth:`identified.fit.output_error._Problem.jacobians`), never around ``torch.compile``,
whose fake tensors read strides from the ``Meta`` kernels.
"""

from __future__ import annotations

import contextlib
import threading
import warnings
from collections.abc import Iterator

import torch

__all__ = ["shape_only_meta"]

#: the operations a product or sum with a constant reaches (``a / y``, ``1 / a`` = ``reciprocal * 1``)
OPS = ("mul.Tensor", "add.Tensor", "sub.Tensor", "div.Tensor")

_lock = threading.Lock()
_library: torch.library.Library | None = None  # the registration while any use is inside
_uses = 0


def _shape(x) -> tuple[int, ...]:
    return tuple(x.shape) if isinstance(x, torch.Tensor) else ()


def _broadcast(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    """NumPy's broadcasting of two shapes (they broadcast: the operation itself checks them)."""
    if a == b or not b:
        return a
    if not a:
        return b
    n = max(len(a), len(b))
    a, b = (1,) * (n - len(a)) + a, (1,) * (n - len(b)) + b
    return tuple(y if x == 1 else x for x, y in zip(a, b))


def _binary(a, b, *, alpha=None):
    """``Meta`` kernel of ``mul``, ``add``, ``sub``: the broadcast shape and the promoted dtype."""
    return torch.empty(_broadcast(_shape(a), _shape(b)), dtype=torch.result_type(a, b), device="meta")


def _div(a, b):
    """``Meta`` kernel of ``div`` (true division): as :func:`_binary`, integers to the default float."""
    dtype = torch.result_type(a, b)
    if not (dtype.is_floating_point or dtype.is_complex):
        dtype = torch.get_default_dtype()
    return torch.empty(_broadcast(_shape(a), _shape(b)), dtype=dtype, device="meta")


@contextlib.contextmanager
def shape_only_meta() -> Iterator[None]:
    """Within it, :data:`OPS` on the ``Meta`` device compute shape and dtype only (the module
    docstring); torch's own kernels are back when the last use leaves, also on an exception.
    Nested or concurrent uses share one registration."""
    global _library, _uses
    with _lock:
        if _library is None:
            _library = torch.library.Library("aten", "IMPL")
            with warnings.catch_warnings():  # "overriding a previously registered kernel": meant, and undone
                warnings.simplefilter("ignore")
                for op in OPS:
                    _library.impl(op, _div if op.startswith("div") else _binary, "Meta")
        _uses += 1
    try:
        yield
    finally:
        with _lock:
            _uses -= 1
            if _uses == 0:
                _library._destroy()
                _library = None
