"""Identification against known truth: plants the fit has not seen, data size, scale, rank.

The plants are MuJoCo models on the default Euler integrator; the regression's equations are the
exact discretisation of their dynamics, so clean data must give the parameters to ~1e-13.
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from identified import Topology
from identified.dataset import DatasetError
from identified.fit.identify import ScaleSpec, identify
from identified.fit.regression import IdentifiabilityError
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters


def truth(preset: str, seed: int | None = None, overrides: dict | None = None, system: str = "ico"):
    p = preset_parameters(system, preset, seed, overrides)
    K = np.array([s["stiffness"] for s in p["springs"]])
    c = np.array([s["damping"] for s in p["springs"]])
    M = np.array([r["mass"] for r in p["rods"]])
    Inert = np.array([r["inertia"] for r in p["rods"]])
    return K, c, M, Inert


def rel(a, b):
    return np.max(np.abs(np.asarray(a) / np.asarray(b) - 1))


def data_for(xml, episodes=3, steps=300, seed=0, **kw):
    return collect(xml, CollectConfig(episodes=episodes, steps=steps, seed=seed, **kw))


@pytest.mark.parametrize("seed", [11, 23])
def test_nonuniform_unseen_seeds_recovered_to_machine_precision(seed):
    xml = build_model("ico", "paper-nonuniform", seed=seed)
    data = data_for(xml, seed=seed + 100, push_every=50)
    model = identify(data, Topology.from_mjcf(xml))  # pushes in newtons fix the scale
    K, c, M, Inert = truth("paper-nonuniform", seed)
    assert model.scale["anchor"] == "push"
    assert rel(model.stiffness, K) < 1e-10
    assert rel(model.damping, c) < 1e-10
    assert rel(model.mass, M) < 1e-10
    assert rel(model.inertia, Inert) < 1e-6
    assert model.control_scale == pytest.approx(1.0, abs=1e-12)
    # error bars are those of a consistent fit: tiny, and positive
    assert np.all(model.stderr["stiffness"] < 1e-8 * K)


def test_rescaled_plant_without_pushes_gives_ratios_after_global_scale():
    ov = {"stiffness_scale": 3.0, "damping_scale": 0.4, "mass_scale": 0.5}
    xml = build_model("ico", "paper-nonuniform", seed=5, overrides=ov)
    data = data_for(xml, seed=1)
    model = identify(data, Topology.from_mjcf(xml))
    K, c, M, Inert = truth("paper-nonuniform", 5, ov)
    assert model.scale["anchor"] == "normalised"
    assert np.mean(model.mass) == pytest.approx(1.0, rel=1e-14)
    lam = np.mean(M)  # the one global factor that states cannot see
    assert rel(model.stiffness * lam, K) < 1e-10
    assert rel(model.damping * lam, c) < 1e-10
    assert rel(model.mass * lam, M) < 1e-10
    assert rel(model.inertia * lam, Inert) < 1e-6


def test_known_mass_fixes_scale_and_fits_control_scale():
    xml = build_model("ico", "paper-nonuniform", seed=8)
    data = data_for(xml, seed=2, push_every=40)
    K, c, M, _ = truth("paper-nonuniform", 8)
    model = identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(masses=(("rod2", float(M[2])),)))
    assert model.scale["anchor"] == "mass"
    assert rel(model.stiffness, K) < 1e-10 and rel(model.mass, M) < 1e-10
    assert model.control_scale == pytest.approx(1.0, abs=1e-10)  # pushes were in newtons
    total = identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(total_mass=float(M.sum())))
    assert rel(total.damping, c) < 1e-10


@pytest.mark.parametrize("steps, tol", [(20, 1e-6), (4, 1e-3)])
def test_few_steps_of_one_trajectory(steps, tol):
    xml = build_model("ico", "paper-nonuniform", seed=31)
    data = data_for(xml, episodes=1, steps=steps, seed=4)
    model = identify(data, Topology.from_mjcf(xml))
    K, c, M, _ = truth("paper-nonuniform", 31)
    lam = np.mean(M)
    assert rel(model.stiffness * lam, K) < tol
    assert rel(model.damping * lam, c) < tol
    assert rel(model.mass * lam, M) < tol


def test_single_regressors_on_uniform_plant():
    xml = build_model("ico", "paper-uniform")
    data = data_for(xml, episodes=2, steps=200, seed=3, push_every=50)
    model = identify(data, Topology.from_mjcf(xml), regressors="single")
    assert np.ptp(model.stiffness) == 0 and np.ptp(model.mass) == 0
    assert model.stiffness[0] == pytest.approx(100.0, rel=1e-10)
    assert model.damping[0] == pytest.approx(10.0, rel=1e-10)
    assert model.mass[0] == pytest.approx(10.0, rel=1e-10)


def test_simple_system_of_the_paper():
    xml = build_model("simple", "paper")
    data = data_for(xml, episodes=2, steps=300, seed=9)
    model = identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(masses=(("rod0", 10.0),)))
    np.testing.assert_allclose(model.stiffness, 100.0, rtol=1e-10)
    np.testing.assert_allclose(model.damping, 10.0, rtol=1e-10)


def test_parameters_written_in_the_mjcf_are_never_read():
    xml = build_model("ico", "paper-nonuniform", seed=12)
    data = data_for(xml, episodes=2, steps=200, seed=6, push_every=50)
    scrambled = re.sub(r'(stiffness|damping|mass)="[^"]*"', r'\1="1.2345"', xml)
    scrambled = re.sub(r'diaginertia="[^"]*"', 'diaginertia="1 1 1"', scrambled)
    assert scrambled != xml
    a = identify(data, Topology.from_mjcf(xml))
    b = identify(data, Topology.from_mjcf(scrambled))
    np.testing.assert_array_equal(a.stiffness, b.stiffness)
    np.testing.assert_array_equal(a.mass, b.mass)
    np.testing.assert_array_equal(a.inertia, b.inertia)


def test_never_taut_cable_is_named_as_unidentifiable():
    xml = build_model("ico", "paper-uniform")
    # make spring5 a pull-only cable whose rest length is far longer than it ever gets
    xml_cable = re.sub(r'(<spatial name="spring5"[^>]*?)springlength="[^"]*"', r'\1springlength="0 5"', xml)
    assert xml_cable != xml
    data = data_for(xml_cable, episodes=2, steps=200, seed=3)  # the plant's cable never pulls
    with pytest.raises(IdentifiabilityError, match=r"spring5\.stiffness"):
        identify(data, Topology.from_mjcf(xml_cable))


def test_data_without_motion_is_refused():
    xml = build_model("ico", "paper-uniform")
    data = data_for(xml, episodes=1, steps=10, seed=0)
    still = replace(
        data,
        pos=np.repeat(data.pos[:, :1], 11, axis=1),
        quat=np.repeat(data.quat[:, :1], 11, axis=1),
        vel=np.zeros_like(data.vel),
        angvel=np.zeros_like(data.angvel),
    )
    with pytest.raises(DatasetError, match="no motion"):
        identify(still, Topology.from_mjcf(xml))


def test_dataset_of_another_model_is_refused():
    data = data_for(build_model("simple", "paper"), episodes=1, steps=10)
    with pytest.raises(DatasetError, match="do not match"):
        identify(data, Topology.from_mjcf(build_model("ico", "paper-uniform")))


def test_bad_scale_arguments():
    xml = build_model("ico", "paper-uniform")
    data = data_for(xml, episodes=1, steps=20)
    with pytest.raises(ValueError, match="not in the model"):
        identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(masses=(("rod99", 1.0),)))
    with pytest.raises(ValueError, match="must be positive"):
        identify(data, Topology.from_mjcf(xml), scale=ScaleSpec(total_mass=-3.0))


def test_adam_solver_approaches_the_closed_form():
    xml = build_model("ico", "paper-uniform")
    data = data_for(xml, episodes=1, steps=300, seed=2, push_every=50)
    model = identify(data, Topology.from_mjcf(xml), regressors="single", solver="adam")
    assert model.metrics["solver"] == "adam"
    assert model.stiffness[0] == pytest.approx(100.0, rel=0.05)
    assert model.mass[0] == pytest.approx(10.0, rel=0.05)


@pytest.mark.expensive
def test_refine_on_an_rk4_plant_stays_within_1e3_of_the_truth():
    """RK4 plant: central-difference regression, then refinement through the RK4 engine's rollouts
    (~15 s; the default run refines through the engine in tests/test_cli.py and tests/test_effects.py)."""
    xml = build_model("ico", "paper-nonuniform", seed=4, integrator="rk4")
    data = data_for(xml, episodes=2, steps=300, seed=5, push_every=25)  # every rod pushed in each episode
    model = identify(data, Topology.from_mjcf(xml), integrator="rk4")
    assert model.integrator == "rk4" and model.metrics["scheme"] == "central"
    from identified.fit.refine import refine

    refined = refine(model, data, horizon=50, max_windows=6, iterations=10)
    info = refined.metrics["refine"]
    assert info["loss_after"] < 0.1 * info["loss_before"]
    K, c, M, Inert = truth("paper-nonuniform", 4)
    for got, want in ((refined.stiffness, K), (refined.damping, c), (refined.mass, M), (refined.inertia, Inert)):
        assert rel(got, want) < 1e-3
    assert refined.control_scale == model.control_scale == pytest.approx(1.0)  # the push anchor is kept


@pytest.mark.parametrize("plant", ["implicitfast", "implicit"])
def test_implicit_plant_is_identified_exactly_with_its_own_equations(plant):
    """MuJoCo's implicit integrators: the implicit equations recover the plant to rounding error,
    where the Euler equations are off by O(dt)."""
    xml = build_model("ico", "paper-nonuniform", seed=27, integrator=plant)
    data = data_for(xml, episodes=2, steps=400, seed=6, push_every=40)
    K, c, M, Inert = truth("paper-nonuniform", 27)
    exact = identify(data, Topology.from_mjcf(xml), integrator="implicit")
    euler = identify(data, Topology.from_mjcf(xml))
    assert exact.integrator == "implicit"
    for got, want in ((exact.stiffness, K), (exact.damping, c), (exact.mass, M)):
        assert rel(got, want) < 1e-10
    assert rel(exact.inertia, Inert) < 1e-6
    assert rel(euler.damping, c) > 1e-3


@pytest.mark.parametrize(("plant", "expected"), [("euler", "euler"), ("implicitfast", "implicit"), ("rk4", "rk4")])
def test_auto_integrator_recognises_the_plant(plant, expected):
    xml = build_model("ico", "paper-nonuniform", seed=28, integrator=plant)
    data = data_for(xml, episodes=2, steps=300, seed=7, push_every=50)
    model = identify(data, Topology.from_mjcf(xml), integrator="auto")
    assert model.integrator == expected
    scores = model.metrics["integrator_selection"]
    assert set(scores) == {"euler", "implicit", "rk4"}
    assert min(scores, key=scores.get) == expected


def test_noisy_data_every_physical_parameter_within_one_percent():
    """1 mm position noise, 1 cm/s velocity, 1 mrad orientation, 0.01 rad/s angular velocity."""
    xml = build_model("ico", "paper-nonuniform", seed=17)
    noise = {"noise_pos": 1e-3, "noise_vel": 1e-2, "noise_quat": 1e-3, "noise_angvel": 1e-2}
    data = data_for(xml, episodes=20, steps=2000, seed=9, push_every=100, **noise)
    model = identify(data, Topology.from_mjcf(xml))  # the weak form is chosen from the recorded noise
    assert model.metrics["weak_window"] and model.metrics["weak_window"] > 1
    K, c, M, Inert = truth("paper-nonuniform", 17)
    assert rel(model.stiffness, K) < 0.01
    assert rel(model.damping, c) < 0.01
    assert rel(model.mass, M) < 0.01
    # the axial inertia too: the pushes act on the rod's surface, and the axial rotation rows, free
    # of spring torques and far less noisy than the transverse ones, get their own weight
    assert rel(model.inertia, Inert) < 0.01
    assert model.metrics["errors_in_variables"]  # the recorded noise's bias is corrected


def test_central_scheme_on_an_rk4_plant():
    """Forward differences are exact only for Euler plants; central ones are O(dt^2) for RK4."""
    xml = build_model("ico", "paper-nonuniform", seed=21, integrator="rk4")
    data = data_for(xml, episodes=2, steps=500, seed=3, push_every=50)  # every rod pushed in each episode
    K, c, M, Inert = truth("paper-nonuniform", 21)
    euler = identify(data, Topology.from_mjcf(xml))
    central = identify(data, Topology.from_mjcf(xml), integrator="rk4")
    assert rel(euler.damping, c) > 1e-3  # the O(dt) bias of the wrong discretisation is visible
    for got, want in ((central.stiffness, K), (central.damping, c), (central.mass, M), (central.inertia, Inert)):
        assert rel(got, want) < 1e-3
