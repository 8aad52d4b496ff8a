"""``tensegrity improve``: the policy's plant episodes recorded in the collect format, the twin's
errors on them, the refit with them added, training on from the current policy. Tiny budgets:
these tests check the machinery, not learning."""

from __future__ import annotations

import json

import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.dataset import load_dataset, save_dataset
from identified.fit.pipeline import fit_model
from identified.model import load_model, save_model
from tensegrity_gym.cli import main
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.improve import concat_episodes, record_policy, twin_errors
from tensegrity_gym.models import write_model
from tensegrity_gym.plant import MujocoPlant
from tensegrity_gym.training import TrainConfig, load_policy, train
from tests._data import GROUND


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("improve")
    xml = d / "robot.xml"
    write_model(xml, "ico", preset="robot")
    model = load_model(GROUND)  # the mechanics under test do not depend on the contact law
    model.source_model = str(xml)
    save_model(d / "twin.json", model)
    data = collect(xml, CollectConfig(episodes=4, steps=400, seed=3, push_every=50))
    save_dataset(d / "data.npz", data)
    cfg = TrainConfig(timesteps=128, seed=0, identified=str(d / "twin.json"), envs=2, rollout=64, episode_steps=30,
                      backend_kwargs={"compile": False})
    train(cfg, d / "P.zip", progress=False)
    return {"dir": d, "xml": str(xml), "twin": str(d / "twin.json"), "data": str(d / "data.npz"),
            "policy": str(d / "P.zip")}


def test_recording_replays_on_the_plant(setup):
    """The recorded states are the plant's: its recorded rest lengths replayed on a fresh plant from
    the first recorded state give the same states (MuJoCo is deterministic), and the dataset is in
    the collect format, cut into pieces of the asked length."""
    pol = load_policy(setup["policy"])
    # the mean action: the motors' state at a cut (not in the recording) is as smooth as the commands
    data, prog = record_policy(pol, setup["xml"], [5, 6], 30, chunk_steps=200, actions="mean")
    assert data.n_steps == 200 and data.n_episodes == 6  # 2 episodes x 600 physics steps
    assert prog.shape == (2,)
    plant = MujocoPlant(setup["xml"])
    from identified.state import RodState

    e = 1  # the second piece of the first episode: starts mid-episode
    plant.reset(RodState(data.pos[e, 0], data.quat[e, 0], data.vel[e, 0], data.angvel[e, 0]),
                data.rest_length[e, 0])
    for t in range(data.n_steps):
        plant.set_targets(data.command[e, t])
        plant.step()
    s = plant.states()
    assert np.abs(s.pos - data.pos[e, -1]).max() < 1e-4  # the motors' state at a cut is not a rest length
    np.testing.assert_allclose(data.pos[0, 200], data.pos[1, 0])  # consecutive pieces share their end state


def test_concat_and_twin_errors(setup):
    base = load_dataset(setup["data"])
    new, _ = record_policy(load_policy(setup["policy"]), setup["xml"], [1], 30, chunk_steps=400)
    both = concat_episodes(base, new)
    assert both.n_episodes == base.n_episodes + new.n_episodes
    np.testing.assert_array_equal(both.pos[base.n_episodes:], new.pos)
    model = load_model(setup["twin"])
    err = twin_errors(model, new, horizon_steps=100)
    # the true parameters (the robot preset's springs and rods, the fitted contact) predict one
    # step far better than a model with every stiffness doubled
    bad = load_model(setup["twin"])
    bad.stiffness = 2 * bad.stiffness
    worse = twin_errors(bad, new, horizon_steps=100)
    assert worse["one_step_vel_m_s"] > 3 * err["one_step_vel_m_s"]
    assert worse["free_run_m"] > err["free_run_m"]


def test_improve_command_runs_rounds(setup, capsys):
    out = setup["dir"] / "run"
    code = main(["improve", "--identified", setup["twin"], "--data", setup["data"], "--policy", setup["policy"],
                 "--model", setup["xml"], "--rounds", "1", "--episodes", "1", "--episode-steps", "40",
                 "--timesteps", "64", "--effects", "ground_contact", "--randomize", "none", "--out", str(out),
                 "--quiet"])
    assert code == 0, capsys.readouterr().err
    rep = json.loads((out / "improve.json").read_text())
    rows = rep["rounds"]
    assert [r["round"] for r in rows] == [0, 1]
    base = 4 * 400 * 0.001
    rec = load_dataset(out / "round1" / "plant.npz")
    assert rec.n_episodes * rec.n_steps == 40 * 20  # --episode-steps 40 control steps of 20 physics steps
    assert rows[0]["plant_data_s"] == pytest.approx(base + rec.n_episodes * rec.n_steps * 0.001)
    assert rows[0]["twin_fitted_on_s"] == pytest.approx(base)
    assert rows[1]["twin_fitted_on_s"] == pytest.approx(rows[0]["plant_data_s"])
    refit = load_model(out / "round1" / "model.json")
    assert refit.metrics["data"]["episodes"] == 4 + rec.n_episodes
    meta = load_policy(out / "round1" / "policy.zip").meta
    assert meta["continued_from"] == setup["policy"] and meta["identified"] == str(out / "round1" / "model.json")
    assert rows[1]["model"] == str(out / "round1" / "model.json")


def test_training_continues_from_a_policy(setup, tmp_path):
    """Training on from a policy starts from its weights and normalisation (learning rate 0: the
    same weights; the normalisation goes on counting)."""
    pol = load_policy(setup["policy"])
    cfg = TrainConfig(timesteps=1, seed=1, identified=setup["twin"], envs=2, rollout=2, episode_steps=30,
                      init_policy=setup["policy"], hyperparameters={"learning_rate": 0.0},
                      backend_kwargs={"compile": False})
    train(cfg, tmp_path / "Q.zip", progress=False)
    q = load_policy(tmp_path / "Q.zip")
    a, b = q.model.policy.state_dict(), pol.model.policy.state_dict()
    assert a.keys() == b.keys() and all(bool((a[k] == b[k]).all()) for k in a)
    n0, n1 = pol.meta["normalize"]["count"], q.meta["normalize"]["count"]
    assert n0 < n1 <= n0 + 4
    fresh = TrainConfig(timesteps=1, seed=1, identified=setup["twin"], envs=2, rollout=2, episode_steps=30,
                        hyperparameters={"learning_rate": 0.0}, backend_kwargs={"compile": False})
    train(fresh, tmp_path / "R.zip", progress=False)
    r = load_policy(tmp_path / "R.zip").model.policy.state_dict()
    assert not all(bool((r[k] == b[k]).all()) for k in r)


def test_improve_rejects_missing_inputs(tmp_path, capsys):
    code = main(["improve", "--identified", str(tmp_path / "no.json"), "--data", "x.npz", "--policy", "p.zip",
                 "--out", str(tmp_path / "o")])
    assert code == 2 and "no.json" in capsys.readouterr().err
    code = main(["improve", "--identified", str(tmp_path / "no.json"), "--data", "x.npz", "--policy", "p.zip",
                 "--episode-steps", "0", "--out", str(tmp_path / "o")])
    assert code == 2 and "--episode-steps must be at least 1, got 0" in capsys.readouterr().err
    _ = fit_model  # the refit's entry point, imported here so a rename fails this file first
