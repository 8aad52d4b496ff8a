"""Training snapshots (learning curves) and the wrong twins of ``examples/train_on_twin.py``.

Tiny runs (tens of steps): these check the machinery, not learning.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.model import load_model, save_model
from tensegrity_gym.backends.identified_backend import default_model_path
from tensegrity_gym.models import preset_parameters, write_model
from tensegrity_gym.training import TrainConfig, load_policy, snapshot_path, train

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def twin(tmp_path_factory) -> Path:
    """The shipped robot twin pointing at the robot's MJCF written to a file."""
    d = tmp_path_factory.mktemp("robot")
    write_model(d / "robot.xml", "ico", preset="robot")
    model = load_model(default_model_path())
    model.source_model = str(d / "robot.xml")
    save_model(d / "twin.json", model)
    return d / "twin.json"


def _example():
    spec = importlib.util.spec_from_file_location("train_on_twin", ROOT / "examples" / "train_on_twin.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def test_snapshots_keep_the_policy_after_every_update(twin, tmp_path):
    out = tmp_path / "P.zip"
    cfg = TrainConfig(timesteps=96, seed=0, identified=str(twin), envs=2, rollout=32, snapshots=True)
    r = train(cfg, out, progress=False)
    assert r.timesteps == 96
    assert sorted(os.listdir(tmp_path)) == ["P.step32.zip", "P.step64.zip", "P.zip"]
    for n in (32, 64):
        pol = load_policy(snapshot_path(str(out), n))
        assert pol.meta["timesteps"] == n and pol.meta["trained_on"] == "twin"
    # the last snapshot is an earlier policy than the final one
    a = load_policy(snapshot_path(str(out), 64)).model.policy.parameters()
    b = load_policy(out).model.policy.parameters()
    assert any(not np.array_equal(x.detach().numpy(), y.detach().numpy()) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("keep", [False, True])
def test_wrong_twin_is_nominal_off_by_30_percent(keep):
    model = load_model(default_model_path())
    wrong = _example().wrong_twin(model, seed=0, keep_effects=keep)
    truth = preset_parameters("ico", "robot")
    springs = {s["name"]: s for s in truth["springs"]}
    rods = {r["name"]: r for r in truth["rods"]}
    topo = model.topology
    pairs = [(wrong.stiffness, [springs[n]["stiffness"] for n in topo.spring_names]),
             (wrong.damping, [springs[n]["damping"] for n in topo.spring_names]),
             (wrong.mass, [rods[n]["mass"] for n in topo.rod_names]),
             (np.asarray(wrong.inertia), [rods[n]["inertia"] for n in topo.rod_names])]
    for got, nominal in pairs:
        ratio = np.asarray(got, dtype=float) / np.asarray(nominal, dtype=float)
        np.testing.assert_allclose(np.abs(ratio - 1.0), 0.3, rtol=1e-12)
        assert (ratio > 1).any() and (ratio < 1).any()  # both signs drawn
    if keep:
        assert [e["name"] for e in wrong.effects] == [e["name"] for e in model.effects] == ["pyramid_contact"]
    else:
        assert wrong.effects == []
    assert model.effects  # the identified model itself is untouched
