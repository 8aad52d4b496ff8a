"""Linear stability of the engine's step against the analytic map of semi-implicit Euler, and the
twin's training step chosen from it (``physics_dt="auto"``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from identified.engine import RodState, SpringGraph, SpringRodEngine, SpringRodParams
from identified.engine.stability import (
    coarsest_stable_step,
    is_stable,
    oscillation_frequencies,
    spectral_radius,
)
from tensegrity_gym.backends.identified_backend import default_model_path
from tensegrity_gym.backends.step_size import stable_physics_dt, whole_divisors
from tensegrity_gym.training import TrainConfig, resolve_physics_dt

M0, M1 = 0.7, 1.3  # kg
INV = 1 / M0 + 1 / M1


def _two_rods(K: float, c: float, h: float) -> tuple[SpringRodEngine, RodState, np.ndarray]:
    """Two free rods on the x axis joined end to end by one cable at its rest length, no gravity:
    the only non-neutral mode is their relative axial motion, ``ü = -K (1/m0 + 1/m1) u - c (1/m0 +
    1/m1) u̇``; rotations and the other translations feel no force to first order (zero tension)."""
    graph = SpringGraph.from_arrays(2, [[0, 1]], [[[0.25, 0, 0], [-0.25, 0, 0]]], [False])
    params = SpringRodParams.from_values(K, c, [M0, M1], [[0.01, 0.02, 0.02], [0.01, 0.03, 0.03]], gravity=[0, 0, 0],
                                         n_rods=2, n_springs=1)
    eng = SpringRodEngine(graph, params, h)
    state = RodState(torch.tensor([[-0.5, 0, 0], [0.5, 0, 0.0]], dtype=torch.float64),
                     torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64),
                     torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 3, dtype=torch.float64))
    return eng, state, np.array([0.5])


def _analytic_radius(K: float, c: float, h: float) -> float:
    """Spectral radius of semi-implicit Euler's map of the axial mode: ``v' = v + h(-ω² u - γ v)``,
    ``u' = u + h v'``, i.e. [[1 - h²ω², h(1 - hγ)], [-hω², 1 - hγ]]; the neutral modes' 1 beside it."""
    w2, g = K * INV, c * INV
    A = np.array([[1 - h * h * w2, h * (1 - h * g)], [-h * w2, 1 - h * g]])
    return max(float(np.abs(np.linalg.eigvals(A)).max()), 1.0)


# ω² = K (1/m0 + 1/m1), γ = c (1/m0 + 1/m1); the limit h²ω² + 2hγ = 4 is at 9.54 ms for K = 2e4,
# c = 0 (h ω = 2), 9.29 ms with c = 5 and 7.46 ms for the overdamped K = 500, c = 120
@pytest.mark.parametrize("K, c, h", [
    (20000.0, 0.0, 0.0125),   # h ω = 2.62
    (20000.0, 0.0, 0.0100),   # h ω = 2.10: just past the limit
    (20000.0, 5.0, 0.0098),   # damped: h²ω² + 2hγ = 4.44
    (500.0, 120.0, 0.0100),   # unstable through its damping: 2hγ = 5.3, h²ω² = 0.11
])
def test_spectral_radius_is_semi_implicit_eulers_of_the_axial_mode(K: float, c: float, h: float) -> None:
    eng, state, rest = _two_rods(K, c, h)
    rho = spectral_radius(eng, state, rest)
    assert rho == pytest.approx(_analytic_radius(K, c, h), rel=1e-9)
    assert rho > 1.01 and not is_stable(rho, h)


@pytest.mark.parametrize("K, c, h", [(20000.0, 0.0, 0.0090), (20000.0, 5.0, 0.0088), (500.0, 120.0, 0.0070)])
def test_below_the_limit_nothing_grows(K: float, c: float, h: float) -> None:
    eng, state, rest = _two_rods(K, c, h)
    rho = spectral_radius(eng, state, rest)
    assert _analytic_radius(K, c, h) == pytest.approx(1.0, abs=1e-12)
    assert rho == pytest.approx(1.0, abs=1e-7) and is_stable(rho, h)


@pytest.mark.parametrize("K, c", [(2000.0, 0.0), (2000.0, 20.0), (500.0, 5.0)])
def test_oscillation_frequency_is_the_axial_modes(K: float, c: float) -> None:
    """The one oscillating mode of the two rods: the rotation per step of semi-implicit Euler's map
    (exact, 1e-9); near the damped continuous frequency sqrt(ω² - γ²/4) / 2π at 1 ms: 0.1 % undamped,
    within 1.1 % damped (the step's own damping, h γ up to 0.044, shifts it)."""
    h = 0.001
    eng, state, rest = _two_rods(K, c, h)
    f = oscillation_frequencies(eng, state, rest)
    w2, g = K * INV, c * INV
    A = np.array([[1 - h * h * w2, h * (1 - h * g)], [-h * w2, 1 - h * g]])
    assert f.shape == (1,)
    assert f[0] == pytest.approx(np.abs(np.angle(np.linalg.eigvals(A))).max() / (2 * np.pi * h), rel=1e-9)
    assert f[0] == pytest.approx(np.sqrt(w2 - g * g / 4) / (2 * np.pi), rel=1e-3 if c == 0 else 1.2e-2)


def test_an_overdamped_cable_does_not_oscillate() -> None:
    eng, state, rest = _two_rods(500.0, 120.0, 0.001)  # γ² / 4 = 6.6e4 > ω² = 1.1e3
    assert oscillation_frequencies(eng, state, rest).size == 0


def test_coarsest_stable_step_keeps_a_factor_of_safety() -> None:
    """The axial mode's limit is h = 2 / ω = 9 ms; of the steps dividing a 20 ms period (1, 2, 4, 5,
    10, 20 ms) 5 ms is stable, but only 4 ms is stable at twice itself (8 < 9 ms)."""
    w = 2 / 0.009
    K = w * w / INV

    def engine_at(h: float) -> SpringRodEngine:
        return _two_rods(K, 0.0, h)[0]

    _, state, rest = _two_rods(K, 0.0, 0.001)
    steps = [k * 0.001 for k in whole_divisors(20)]
    choice = coarsest_stable_step(engine_at, state, rest, steps, margin=2.0)
    assert choice.step == pytest.approx(0.004) and choice.stable_at_finest
    assert sorted(choice.radii) == pytest.approx([0.008, 0.010, 0.020, 0.040])  # 40, 20, 10 failed, 8 held
    assert coarsest_stable_step(engine_at, state, rest, steps, margin=1.0).step == pytest.approx(0.005)
    # a first-order actuator filter of 3 ms is stable while 2 h / 3 ms < 2: 2 ms
    assert coarsest_stable_step(engine_at, state, rest, steps, filter_time_constants=[0.003]).step == \
        pytest.approx(0.002)
    # a cable too stiff for even the finest step: that step, said to be unstable
    stiff = coarsest_stable_step(lambda h: _two_rods(1e8, 0.0, h)[0], state, rest, steps)
    assert stiff.step == pytest.approx(0.001) and not stiff.stable_at_finest
    assert "blows up at its own step" in stiff.describe()
    with pytest.raises(ValueError, match="margin"):
        coarsest_stable_step(engine_at, state, rest, steps, margin=0.5)


def test_a_robot_that_tips_over_is_not_an_unstable_step() -> None:
    """A cable of negative stiffness pushes the rods apart at ``σ = sqrt(-K (1/m0 + 1/m1))`` (the
    physics: a robot tipping over at the linearisation's state); every step shows it
    (``|λ| ≈ e^{σh}``), so only growth beyond the model's own counts and the coarsest step is taken."""
    K = -100.0
    sigma = np.sqrt(-K * INV)

    def engine_at(h: float) -> SpringRodEngine:
        return _two_rods(K, 0.0, h)[0]

    _, state, rest = _two_rods(K, 0.0, 0.001)
    choice = coarsest_stable_step(engine_at, state, rest, [k * 0.001 for k in whole_divisors(20)])
    assert choice.own_rate == pytest.approx(sigma, rel=1e-4)  # semi-implicit Euler: σ (1 - (hσ)²/24 + ...)
    assert choice.step == pytest.approx(0.020) and choice.stable_at_finest
    assert "grows at 14.8/s there, at any step" in choice.describe()
    rho = spectral_radius(engine_at(0.040), state, rest)
    assert not is_stable(rho, 0.040) and is_stable(rho, 0.040, choice.own_rate)  # absolute vs relative


def test_shipped_robot_trains_at_4_ms() -> None:
    """The robot preset's model is stable to about 11.1 ms at its standing pose (bisected by
    benchmarks/bench_physics_dt.py), so with the factor of 2.5 the coarsest step dividing 20 ms is
    4 ms (stable at 10 ms, not at 12.5 ms)."""
    choice = stable_physics_dt(None, 20)
    assert choice.step == pytest.approx(0.004) and choice.stable_at_finest and choice.margin == 2.5
    radius = {round(1e4 * h): r for h, r in choice.radii.items()}  # tenths of ms: |λ|
    assert sorted(radius) == [100, 125, 250, 500]
    assert is_stable(radius[100], 0.010, choice.own_rate) and not is_stable(radius[125], 0.0125, choice.own_rate)
    step, why = resolve_physics_dt(TrainConfig(timesteps=1, identified=default_model_path()))
    assert step == pytest.approx(0.004) and "4 ms: stable at 10 ms (2.5x the step)" in why
    assert resolve_physics_dt(TrainConfig(timesteps=1, physics_dt=None))[0] == pytest.approx(0.001)
    assert resolve_physics_dt(TrainConfig(timesteps=1, physics_dt=0.002))[0] == pytest.approx(0.002)
    with pytest.raises(ValueError, match="do not divide the control period"):
        resolve_physics_dt(TrainConfig(timesteps=1, physics_dt=0.003))


@pytest.mark.parametrize("bad", ["fast", 0.0, -0.004, float("nan"), True])
def test_train_config_refuses_bad_physics_dt(bad: object) -> None:
    with pytest.raises(ValueError, match="physics_dt must be 'auto', None or a positive number"):
        TrainConfig(timesteps=1, physics_dt=bad).validate()  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="give the twin's step as physics_dt"):
        TrainConfig(timesteps=1, backend_kwargs={"physics_dt": 0.004}).validate()
