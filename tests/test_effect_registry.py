"""An effect is one file on the base class plus one registry line: a toy effect registered here (a
constant torque per rod, defined in this file and nowhere else) goes through the fit, the effect
search, the diagnosis and the twin with no code added anywhere else, and its parameters come back
exactly from data of a plant where it is true (the identified engine itself, with the torque)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from identified.dataset import Dataset
from identified.effects import EFFECTS, Effect, ParamBlock, known_names, register_effect, search_labels
from identified.engine import RodState
from identified.fit.identify import identify
from identified.fit.pipeline import fit_model
from identified.model import load_model, save_model
from identified.topology import Topology
from identified.twin import engine_from_model
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model


class ConstantTorque(Effect):
    """A constant WORLD torque on each rod (a magnetised rod in a uniform field, say)."""

    name = "constant_torque"
    description = "a constant world-frame torque on each rod"
    blocks = (ParamBlock("torque", "rod", width=3, signed=True, unit="N m"),)

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> ConstantTorque:
        return cls(topology.n_rods, topology.n_springs)

    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        eye = torch.eye(3, dtype=state.pos.dtype, device=state.pos.device)
        torque = eye.expand(state.pos.shape[:-1] + (3, 3))
        return torch.zeros_like(torque), torque


@pytest.fixture
def registered():
    register_effect(ConstantTorque)
    yield ConstantTorque
    del EFFECTS[ConstantTorque.name]


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """The icosahedron's MJCF, a MuJoCo dataset of it, and its exact spring-rod model."""
    path = tmp_path_factory.mktemp("toy") / "ico.xml"
    write_model(path, "ico", preset="paper-nonuniform", seed=3)
    data = collect(path, CollectConfig(episodes=4, steps=300, seed=7, push_every=50))
    return path, data, identify(data, Topology.from_mjcf(path))


TRUE_TORQUE = np.random.default_rng(11).normal(0.0, 0.3, (6, 3))


def _with_torque(model, data: Dataset) -> Dataset:
    """The data the engine makes from the same starts, rest lengths and pushes with the torque on."""
    eff = ConstantTorque(model.topology.n_rods, model.topology.n_springs, values=TRUE_TORQUE.ravel())
    eng = engine_from_model(model, effects=[eff])
    s0 = eng.state(*(getattr(data, k)[:, 0] for k in ("pos", "quat", "vel", "angvel")))
    with torch.no_grad():
        out = eng.rollout(s0, data.rest_length, data.push_force, data.push_point)
    return dataclasses.replace(data, **{k: getattr(out, k).numpy() for k in RodState._fields})


def test_the_registry_gives_the_toy_to_every_list(registered):
    assert "constant_torque" in search_labels() and "constant_torque" in known_names()
    from tensegrity_gym.cli import build_parser

    help_text = build_parser()._subparsers._group_actions[0].choices["fit"].format_help()
    assert "constant_torque" in " ".join(help_text.split())
    del EFFECTS["constant_torque"]
    try:
        assert "constant_torque" not in search_labels() and "constant_torque" not in known_names()
    finally:
        register_effect(ConstantTorque)
    with pytest.raises(ValueError, match="taken"):
        register_effect(type("Other", (ConstantTorque,), {}))


def test_a_registered_effect_is_fitted_exactly_where_it_is_true(registered, plant, tmp_path):
    path, data, clean = plant
    synthetic = _with_torque(clean, data)
    model = fit_model(synthetic, path, effects="constant_torque")
    got = np.array(model.effects[0]["parameters"]["torque"])
    np.testing.assert_allclose(got, TRUE_TORQUE, rtol=0, atol=1e-11)  # measured 2.7e-14 N m
    np.testing.assert_allclose(model.stiffness, clean.stiffness, rtol=1e-11)
    np.testing.assert_allclose(model.mass, clean.mass, rtol=1e-11)
    # without it the same data leave a spring-rod model that cannot explain them
    bare = fit_model(synthetic, path, effects="none")
    assert bare.metrics["one_step_rms"]["vel"] > 1e6 * model.metrics["one_step_rms"]["vel"]
    # the model file round trip holds the toy, and the twin built from it steps with it
    save_model(tmp_path / "toy.json", model)
    assert json.loads((tmp_path / "toy.json").read_text())["effects"][0]["name"] == "constant_torque"
    back = load_model(tmp_path / "toy.json")
    eng = engine_from_model(back)
    assert [type(e) for e in eng.effects] == [ConstantTorque]
    assert not eng.fused  # no component form declared: the twin steps through the tensor form
    s0 = eng.state(*(getattr(synthetic, k)[0, 0] for k in ("pos", "quat", "vel", "angvel")))
    with torch.no_grad():
        s1 = eng.step(s0, synthetic.rest_length[0, 0], synthetic.push_force[0, 0], synthetic.push_point[0, 0])
    np.testing.assert_allclose(s1.pos.numpy(), synthetic.pos[0, 1], atol=1e-12)


def test_the_diagnosis_scores_a_registered_effect_first(registered, plant):
    """The diagnosis scores every registered effect on the residual of the spring-rod model alone:
    the toy explains the data it made."""
    from identified.diagnose import diagnose

    path, data, clean = plant
    synthetic = _with_torque(clean, data)
    bare = fit_model(synthetic, path, effects="none")
    report = diagnose(bare, synthetic, horizon_s=0.2, mjcf=path)
    assert report["candidates"][0]["name"] == "constant_torque"
    assert report["candidates"][0]["score"] > 0.99


@pytest.mark.expensive
def test_the_effect_search_finds_a_registered_effect(registered, plant):
    """``--effects auto`` tries the registered effect with the library's (about 40 s: every
    candidate is fitted, cable friction's classification search among them)."""
    path, data, clean = plant
    model = fit_model(_with_torque(clean, data), path, effects="auto", jobs=1)
    assert [e["name"] for e in model.effects] == ["constant_torque"]
    assert "constant_torque" in model.metrics["effect_search"]["candidates"]
    np.testing.assert_allclose(np.array(model.effects[0]["parameters"]["torque"]), TRUE_TORQUE, atol=1e-9)


def test_the_twin_env_runs_a_registered_effect(registered, tmp_path):
    """The robot's shipped model with the toy added to its file: the twin env steps with both
    effects, the toy at zero torque changes nothing, and a torque moves the rods."""
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401
    from tensegrity_gym.backends.identified_backend import default_model_path

    obj = json.loads(Path(default_model_path()).read_text())
    R = len(obj["rods"])

    def run(torque: np.ndarray | None) -> np.ndarray:
        if torque is not None:
            obj["effects"] = [e for e in obj["effects"] if e["name"] != "constant_torque"] + [
                {"name": "constant_torque", "parameters": {"torque": torque.tolist()}, "stderr": None, "options": {}}]
        path = tmp_path / "twin.json"
        path.write_text(json.dumps(obj))
        env = gym.make("TensegrityIco-v0", backend="identified", model=str(path),
                       backend_kwargs={"dtype": "float64", "compile": False})
        try:
            env.reset(seed=0)
            names = [e.name for e in env.unwrapped.backend.engine.effects]
            assert names[-1:] == (["constant_torque"] if torque is not None else names[-1:])
            out = [env.step(np.zeros(env.action_space.shape, dtype=env.action_space.dtype))[0] for _ in range(5)]
        finally:
            env.close()
        assert np.all(np.isfinite(out))
        return np.array(out)

    shipped = run(None)
    np.testing.assert_array_equal(run(np.zeros((R, 3))), shipped)
    assert np.abs(run(np.full((R, 3), 2.0)) - shipped).max() > 1e-3


def test_two_laws_of_one_thing_are_rivals():
    """The two ground-contact laws model one thing: a model holds one, the search and the diagnosis
    do not offer the other beside it; other effects are no one's rivals."""
    from identified.effects import rival

    assert rival("pyramid_contact", ["linear_drag", "ground_contact"]) == "ground_contact"
    assert rival("ground_contact", ["pyramid_contact"]) == "pyramid_contact"
    assert rival("ground_contact", ["ground_contact", "linear_drag"]) is None  # itself is not its rival
    assert rival("linear_drag", ["ground_contact", "linear_drag:implicit"]) is None
    assert rival("linear_drag:implicit", ["pyramid_contact"]) is None
