"""Linear stability of the engine's step: how coarse a step a model can be integrated at.

Semi-implicit Euler (the engine's and MuJoCo's default, :mod:`identified.engine.integration`)
integrates a mode ``ẍ = -ω² x - γ ẋ`` by ``v' = v + h(-ω² x - γ v)``, ``x' = x + h v'``, whose
map has trace ``2 - h²ω² - hγ`` and determinant ``1 - hγ``: it is stable while ``h²ω² + 2hγ < 4``
(``hω < 2`` undamped).  A model's stiffest mode (its stiffest cable between its lightest rods,
the ground's soft constraint) therefore bounds the step.  Rather than bound ``ω`` from the
parameters, :func:`step_jacobian` linearises the engine's own step, with every force and effect
it has, at a given state, in minimal coordinates: each rod's position, rotation vector (world
frame), velocity and angular velocity, 12 numbers a rod.  :func:`spectral_radius` is the largest
``|λ|`` of that Jacobian: a perturbation grows by at most this much a step.

The parameters of an identified model are continuous-time quantities, so the same model can be
stepped at any ``h`` (:func:`identified.twin.engine_from_model` with ``dt = h``);
:func:`coarsest_stable_step` picks the coarsest of a set of steps that is stable with a factor
of safety (the twin's ``physics_dt``, :mod:`tensegrity_gym.backends.step_size`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from identified.engine.engine import SpringRodEngine
from identified.engine.integration import RodState
from identified.rotation import quat_conjugate, quat_exp, quat_multiply

#: growth rate (1/s) a coarser step may add to the model's own before it counts as unstable: a
#: rod's slow drift at a state that is not an exact equilibrium gives |λ| = 1 + O(1e-6) a step
NEUTRAL_RATE = 0.1


#: the least and the most rotation a step (rad) of an eigenvalue of the step that count as an
#: oscillation of the model (:func:`oscillation_frequencies`)
MIN_TURN = 1e-6
MAX_TURN = 0.5 * np.pi


def step_jacobian(engine: SpringRodEngine, state: RodState, rest_length: Any) -> np.ndarray:
    """The Jacobian (12R, 12R) of one :meth:`~identified.engine.SpringRodEngine.step` at ``state``
    (unbatched, R rods) and ``rest_length`` (S,), in float64 minimal coordinates ordered
    ``(dpos, drot, dvel, dangvel)``, each (R, 3) flattened; ``drot`` the world-frame rotation
    vector of the perturbation, ``q = exp(drot) q0`` in and ``2 vec(q' q0'^*)`` out."""
    if engine.dtype != torch.float64:
        raise ValueError("step_jacobian needs a float64 engine (the linearisation is to rounding)")
    s = engine.state(*state)
    rest = torch.as_tensor(np.asarray(rest_length, dtype=np.float64), device=engine.device)
    R = s.pos.shape[-2]
    with torch.no_grad():
        ref = engine.step(s, rest)

    def one_step(x: torch.Tensor) -> torch.Tensor:
        dp, dr, dv, dw = x.view(4, R, 3)
        out = engine.step(RodState(s.pos + dp, quat_multiply(quat_exp(dr), s.quat), s.vel + dv, s.angvel + dw), rest)
        dq = quat_multiply(out.quat, quat_conjugate(ref.quat))
        rot = 2.0 * dq[..., 1:] * torch.sign(dq[..., :1])
        return torch.cat([(out.pos - ref.pos).reshape(-1), rot.reshape(-1), (out.vel - ref.vel).reshape(-1),
                          (out.angvel - ref.angvel).reshape(-1)])

    x0 = torch.zeros(12 * R, dtype=torch.float64)
    try:  # one batched backward pass (vmap): half the time of 12R passes
        return torch.autograd.functional.jacobian(one_step, x0, vectorize=True).numpy()
    except RuntimeError:  # an effect vmap cannot batch: row by row
        return torch.autograd.functional.jacobian(one_step, x0).numpy()


def spectral_radius(engine: SpringRodEngine, state: RodState, rest_length: Any) -> float:
    """``max |λ|`` of :func:`step_jacobian`: the most a small perturbation grows in one step; NaN
    where the step itself is not finite at ``state``."""
    J = step_jacobian(engine, state, rest_length)
    if not np.isfinite(J).all():
        return float("nan")
    return float(np.abs(np.linalg.eigvals(J)).max())


def oscillation_frequencies(engine: SpringRodEngine, state: RodState, rest_length: Any) -> np.ndarray:
    """The frequencies (Hz, ascending, one per conjugate pair) of the oscillating modes of the
    engine's step at ``state``: ``|arg λ| / (2π h)`` of each complex eigenvalue of
    :func:`step_jacobian` (the step's own rotation per step; for semi-implicit Euler's map of
    ``ẍ = -ω² x - γ ẋ`` it tends to the damped ``sqrt(ω² - γ²/4)`` as ``h ω -> 0``). Modes that do not
    oscillate (overdamped cables, rigid-body drift) and the integrator's own sign flips (a quarter
    turn a step or more, :data:`MAX_TURN`) are not in it; empty where none do, or where the step is
    not finite at ``state``."""
    J = step_jacobian(engine, state, rest_length)
    if not np.isfinite(J).all():
        return np.zeros(0)
    arg = np.angle(np.linalg.eigvals(J))
    # one of each conjugate pair; a turn of under 1e-6 rad a step (a period of 6e6 steps) is the
    # rounding of the neutral modes' repeated eigenvalue 1 (a Jordan block splits it by ~1e-10), not
    # a mode; one of more than a quarter turn a step is the integrator's own (an eigenvalue near -1:
    # a stiff mode at the edge of the step's stability flipping sign each step), not a motion it resolves
    return np.sort(arg[(arg > MIN_TURN) & (arg < MAX_TURN)] / (2.0 * np.pi * engine.dt))


def growth_rate(rho: float, h: float) -> float:
    """The growth rate (1/s) of a step of ``h`` s whose Jacobian has spectral radius ``rho``:
    ``ln(rho) / h``, at least 0 (inf where ``rho`` is not finite)."""
    return max(float(np.log(rho)) / h, 0.0) if np.isfinite(rho) and rho > 0 else float("inf")


def is_stable(rho: float, h: float, own_rate: float = 0.0) -> bool:
    """Whether a step of ``h`` s whose Jacobian has spectral radius ``rho`` is stable: no mode
    grows faster than the model's own fastest one, ``own_rate`` (1/s: a robot tipping over at the
    state grows at any step, see :func:`coarsest_stable_step`), plus :data:`NEUTRAL_RATE`."""
    return growth_rate(rho, h) <= own_rate + NEUTRAL_RATE


@dataclass(frozen=True)
class StepChoice:
    """What :func:`coarsest_stable_step` chose and why.

    ``step``: the chosen step, s; ``margin``: the factor of safety (each candidate ``h`` was tested
    at ``margin * h``); ``radii``: ``{tested step (s): spectral radius}`` for every step tested,
    coarsest first; ``stable_at_finest``: False when even the finest candidate fails (``step`` is
    then the finest candidate, and the twin may diverge); ``own_rate``: the growth rate (1/s) of
    the model's fastest growing mode at the finest candidate itself, the physics' own (a robot not
    at rest at the state), which no step removes and against which the others are measured.
    """

    step: float
    margin: float
    radii: dict[float, float]
    stable_at_finest: bool
    own_rate: float = 0.0

    def describe(self) -> str:
        """One line: the step and the evidence, e.g. ``4 ms: stable at 10 ms (2.5x the step), not at
        12.5 ms (|λ| 1.34 a step)``."""
        def ms(h: float) -> str:
            return f"{1e3 * h:g} ms"

        tested = self.margin * self.step
        bad = [(h, r) for h, r in self.radii.items() if h >= tested and not is_stable(r, h, self.own_rate)]
        worst = ""
        if bad:
            h, r = min(bad)
            worst = f"{ms(h)} (|λ| {r:.3g} a step)" if np.isfinite(r) else f"{ms(h)} (not finite)"
        own = (f"; a mode of the model itself grows at {self.own_rate:.3g}/s there, at any step"
               if self.own_rate > NEUTRAL_RATE else "")
        if not self.stable_at_finest and not worst:
            return (f"{ms(self.step)}, the finest step: the model blows up at its own step (a mode grows at "
                    f"{self.own_rate:.3g}/s at the standing pose)")
        if not self.stable_at_finest:
            return f"{ms(self.step)}, the finest step: the model is not stable even at {worst}{own}"
        return (f"{ms(self.step)}: stable at {ms(tested)} ({self.margin:g}x the step)"
                + (f", not at {worst}" if worst else "") + own)


def coarsest_stable_step(engine_at: Callable[[float], SpringRodEngine], state: RodState, rest_length: Any,
                         candidates: Sequence[float], margin: float = 2.0,
                         filter_time_constants: Sequence[float] = ()) -> StepChoice:
    """The coarsest step ``h`` of ``candidates`` whose engine (``engine_at(margin * h)``, float64)
    is stable (:func:`is_stable`) at ``state`` and ``rest_length``: the step is ``margin`` times
    finer than the stability limit there, room for the states the linearisation did not see
    (deeper contacts, stretched cables); each first-order actuator filter of time constant ``τ``
    (``act += h (ctrl - act) / τ``, stable while ``h / τ < 2``) must hold at ``margin * h`` too.
    Stable means growing no faster than the engine at the finest candidate itself does: where the
    state is not a rest (a robot tipping over) a mode grows at the same rate ``σ`` at every small
    step (``|λ| = e^{σh}``), the physics, not the integrator, and only growth beyond it counts.
    Falls back to the finest candidate (``stable_at_finest`` False) when none is stable, or when
    the model's own growth is an e-fold within the coarsest candidate (a model that blows up: an
    unidentified fit's negative inertia, say, not a robot tipping over)."""
    if not margin >= 1:
        raise ValueError(f"margin must be >= 1, got {margin!r}")
    steps = sorted({float(h) for h in candidates}, reverse=True)
    if not steps or steps[-1] <= 0:
        raise ValueError(f"candidate steps must be positive, got {list(candidates)!r}")
    taus = [float(t) for t in filter_time_constants if t and t > 0]
    own = growth_rate(spectral_radius(engine_at(steps[-1]), state, rest_length), steps[-1])
    if not own * steps[0] <= 1.0:  # e-fold within the coarsest candidate (the control period): it blows up
        return StepChoice(steps[-1], float(margin), {steps[-1]: float(np.exp(own * steps[-1]))}, False, own)
    radii: dict[float, float] = {}
    for h in steps:
        tested = margin * h
        if any(tested / tau >= 2.0 for tau in taus):
            continue
        rho = spectral_radius(engine_at(tested), state, rest_length)
        radii[tested] = rho
        if is_stable(rho, tested, own):
            return StepChoice(h, float(margin), radii, True, own)
    return StepChoice(steps[-1], float(margin), radii, False, own)
