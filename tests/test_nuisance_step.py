"""The windows' state-only Levenberg-Marquardt step: every window is its own problem once the
parameters are held (:func:`identified.fit.marker_bound.nuisance_step`)."""

from __future__ import annotations

import math

import torch

from identified.fit.marker_bound import nuisance_step
from identified.fit.marker_fit import STATE_SHARES, window_states_at


class _Toy:
    """W windows of one rod with one nuisance each, ``r_w(x) = a_w tanh(b_w x) - y_w``: a window with
    a steep ``b`` and a far target overshoots on a plain Gauss-Newton step (the tanh saturates)."""

    def __init__(self, a: list[float], b: list[float], y: list[float]) -> None:
        self.a, self.b, self.y = (torch.tensor(v, dtype=torch.float64) for v in (a, b, y))
        self.evaluated: list[list[int]] = []  # the windows of each residual evaluation

    def residuals(self, theta: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        return self.window_residuals(theta, dx)

    def window_residuals(self, theta: torch.Tensor, dx: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        keep = torch.arange(len(self.a)) if keep is None else keep
        self.evaluated.append(keep.tolist())
        x = dx[:, 0, 0]
        return (self.a[keep] * torch.tanh(self.b[keep] * x) - self.y[keep])[:, None]

    def jacobians(self, theta: torch.Tensor, dx: torch.Tensor, params: bool = True):
        x = dx[:, 0, 0]
        J = self.a * self.b / torch.cosh(self.b * x) ** 2
        return self.residuals(theta, dx), J[:, None, None], None


def _step(toy: _Toy, x: list[float], mu: float | torch.Tensor = 1e-3):
    dx = torch.tensor(x, dtype=torch.float64).reshape(-1, 1, 1)
    acts = torch.ones(dx.shape[0], 1, dtype=torch.float64)
    return nuisance_step(toy, torch.zeros(1), dx, acts, mu)


def test_each_window_steps_as_it_would_alone() -> None:
    # window 0 overshoots (from x = 2 in tanh's tail the Gauss-Newton step lands at x = -11.6: its cost
    # 0.929 -> 1.000); window 1 is nearly linear and far from its target (cost 4 -> 7e-4), so the two
    # windows' total falls on that same trial step
    toy = _Toy(a=[1.0, 10.0], b=[1.0, 0.01], y=[0.0, 2.0])
    dx, r, cost, mu, moved = _step(toy, [2.0, 0.0])
    evaluated = list(toy.evaluated)
    alone = [_step(_Toy([a], [b], [y]), [x]) for a, b, y, x in ((1.0, 1.0, 0.0, 2.0), (10.0, 0.01, 2.0, 0.0))]
    for w, (dx1, r1, c1, mu1, moved1) in enumerate(alone):
        assert moved1
        assert float(dx[w, 0, 0]) == float(dx1[0, 0, 0])
        assert float(mu[w]) == float(mu1[0])
        assert float(r[w, 0]) == float(r1[0, 0])
    # the overshooting window took its step at a damping raised from 1e-3 (4^k), the linear one at once
    assert float(mu[1]) == 1e-3 / 3
    k = round(math.log(float(mu[0]) * 3 / 1e-3, 4))
    assert k >= 1 and math.isclose(float(mu[0]), 1e-3 * 4 ** k / 3)
    # every window's own cost fell, and the cost returned is theirs
    before = toy.residuals(None, torch.tensor([2.0, 0.0], dtype=torch.float64).reshape(2, 1, 1)).square()[:, 0]
    assert bool((r[:, 0].square() < before).all())
    assert cost == float(r.square().sum())
    assert moved
    # the first trial runs both windows, the later ones only the window still without a step
    assert evaluated[1] == [0, 1] and len(evaluated) > 2 and all(e == [0] for e in evaluated[2:])


def test_a_window_no_step_helps_keeps_its_state() -> None:
    # window 0 at its minimum (tanh(0) = 0 = y): no step lowers its cost, and it stays, its damping
    # raised 4^8 times; window 1 steps
    toy = _Toy(a=[1.0, 1.0], b=[1.0, 1.0], y=[0.0, 0.5])
    dx, r, _, mu, moved = _step(toy, [0.0, 0.0], mu=torch.tensor([1e-3, 1e-3], dtype=torch.float64))
    assert float(dx[0, 0, 0]) == 0.0
    assert math.isclose(float(mu[0]), 1e-3 * 4 ** 8)
    assert float(dx[1, 0, 0]) > 0.0 and float(r[1, 0].abs()) < 0.5 and moved


class _Breaks(_Toy):
    """The toy whose every window costs infinity once any window's nuisance passes ``limit``: a
    contact solve that breaks for the whole batch of windows."""

    def __init__(self, *args, limit: float) -> None:
        super().__init__(*args)
        self.limit = limit

    def window_residuals(self, theta, dx, keep=None):
        r = super().window_residuals(theta, dx, keep)
        return torch.full_like(r, math.inf) if bool((dx[:, 0, 0] > self.limit).any()) else r


def test_each_window_keeps_the_share_of_the_joint_step_that_serves_it() -> None:
    # window 0: r = tanh(x) from x = 2, the full step overshoots to -2 (the same cost), half of it lands
    # on the minimum; window 1 is nearly linear, the full step is best; window 2 sits at its minimum
    # (tanh(x) = 0.5) and any share of its step raises its cost: it keeps its states
    toy = _Toy(a=[1.0, 10.0, 1.0], b=[1.0, 0.01, 1.0], y=[0.0, 2.0, 0.5])
    x0 = torch.tensor([2.0, 0.0, math.atanh(0.5)], dtype=torch.float64).reshape(3, 1, 1)
    step = torch.tensor([-4.0, 20.0, 1.0], dtype=torch.float64).reshape(3, 1, 1)
    dx, r = window_states_at(toy, torch.zeros(1), x0, step)
    assert dx[:, 0, 0].tolist() == [0.0, 20.0, math.atanh(0.5)]
    assert r[:, 0].tolist() == toy.window_residuals(None, dx)[:, 0].tolist()
    assert float(r[0, 0]) == 0.0 and abs(float(r[2, 0])) < 1e-15
    # every window's cost is the least of its three shares', and never above where it stood
    for w in range(3):
        costs = [float(toy.window_residuals(None, x0 + a * step)[w, 0] ** 2) for a in STATE_SHARES]
        assert float(r[w, 0] ** 2) == min(costs)
    # shares (1,) alone: the Gauss-Newton step as it was, every window takes all of it
    dx1, _ = window_states_at(toy, torch.zeros(1), x0, step, shares=(1.0,))
    assert torch.equal(dx1, x0 + step)


def test_a_share_that_breaks_the_solve_is_never_taken() -> None:
    # the full step takes window 1 to x = 40, past the solve's limit: every window's cost there is
    # infinite, so each takes half of its step or none
    toy = _Breaks([1.0, 10.0, 1.0], [1.0, 0.01, 1.0], [0.0, 2.0, 0.5], limit=30.0)
    x0 = torch.tensor([2.0, 0.0, math.atanh(0.5)], dtype=torch.float64).reshape(3, 1, 1)
    step = torch.tensor([-4.0, 40.0, 1.0], dtype=torch.float64).reshape(3, 1, 1)
    dx, r = window_states_at(toy, torch.zeros(1), x0, step)
    assert dx[:, 0, 0].tolist() == [0.0, 20.0, math.atanh(0.5)]
    assert bool(torch.isfinite(r).all())
    # where every share breaks, the cost returned is infinite: the joint step refuses the trial
    _, r = window_states_at(_Breaks([1.0], [1.0], [0.0], limit=-3.0), torch.zeros(1), x0[:1], step[:1])
    assert bool(torch.isinf(r).all())
