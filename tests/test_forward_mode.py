"""identified.fit.forward_mode: the shape-only ``Meta`` kernels give the same forward-mode
derivatives as torch's own, bit for bit, through every broadcast and promotion the engine uses,
and torch's kernels are back on leaving (also after an exception)."""

from __future__ import annotations

import pytest
import torch
from torch.func import jvp, vmap

from identified.fit.forward_mode import OPS, _broadcast, shape_only_meta

Y = torch.linspace(0.5, 2.0, 6, dtype=torch.float64).reshape(2, 3)  # a constant: no tangent


def _mixed(a: torch.Tensor) -> torch.Tensor:
    """Products, sums, differences and quotients of ``a`` (2, 3) with constants of every kind: a
    Python number, a broadcast row and column, a float32 and an integer tensor, a 0-d tensor."""
    col = torch.tensor([[2.0], [3.0]], dtype=torch.float64)
    out = 2 * a + a * Y[0] - col * a + 1.0 / a - a / col
    out = out + a * torch.tensor([1, 2, 3]) + a * torch.ones(3, dtype=torch.float32) - torch.tensor(0.5) * a
    out = out + (a.sum(0) * Y).sum(-1, keepdim=True) - Y[:, :1] / a[None]  # (1, 2, 3): a rank added
    return out + torch.div(a, torch.tensor([2, 4, 8])) * a


def test_derivatives_bit_for_bit_those_of_torchs_kernels():
    x = torch.linspace(0.3, 1.3, 6, dtype=torch.float64).reshape(2, 3)
    tangents = torch.eye(6, dtype=torch.float64).reshape(6, 2, 3)
    push = lambda t: jvp(_mixed, (x,), (t,))
    want_y, want_t = vmap(push)(tangents)
    with shape_only_meta():
        got_y, got_t = vmap(push)(tangents)
    assert got_t.shape == (6, 1, 2, 3) and got_t.dtype == torch.float64
    assert torch.equal(got_y, want_y) and torch.equal(got_t, want_t)
    # against the derivative by hand of one term: d(2a + 1/a)/da = 2 - 1/a^2
    t = torch.ones_like(x)
    with shape_only_meta():
        _, d = jvp(lambda a: 2 * a + 1.0 / a, (x,), (t,))
    torch.testing.assert_close(d, 2 - 1 / x ** 2, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize(("a", "b", "want"), [
    ((2, 3), (2, 3), (2, 3)), ((2, 3), (), (2, 3)), ((), (4,), (4,)), ((2, 1), (3,), (2, 3)),
    ((5, 1, 3), (4, 1), (5, 4, 3)), ((1,), (7, 1), (7, 1)),
])
def test_broadcast_is_numpys(a, b, want):
    assert _broadcast(a, b) == want == torch.broadcast_shapes(a, b)


def _kernels() -> str:
    return "".join(torch._C._dispatch_dump(f"aten::{op}") for op in OPS)


def test_torchs_kernels_are_back_on_leaving():
    before = _kernels()
    with shape_only_meta():
        inside = _kernels()
        assert "forward_mode.py" in inside
        with shape_only_meta():  # nested: the same registration, kept until the outer one leaves
            assert _kernels() == inside
        assert _kernels() == inside
    assert _kernels() == before
    with pytest.raises(RuntimeError, match="inside"), shape_only_meta():
        raise RuntimeError("inside")
    assert _kernels() == before
    i = torch.empty(2, 3, dtype=torch.int64, device="meta")
    with shape_only_meta():  # as torch's: integers divide to the default float, broadcast shapes
        assert (i / i[0]).dtype == torch.get_default_dtype() and (i * 0.5).dtype == torch.get_default_dtype()
        assert (i[:, :1] - i[0]).shape == (2, 3)
    # the meta kernels torch's own again: strides follow a transposed input (the shape-only ones do not)
    a = torch.empty(3, 4, device="meta").t()
    assert (a * 2.0).stride() == a.stride()
