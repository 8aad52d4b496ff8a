"""``tensegrity train --seeds`` (local processes and Ray) and ``tensegrity gap`` over several policies.

Runs are tiny (64 steps on 2 eager twins): these tests check the machinery (the seeds are the
configuration's, every file is what it says, the Ray path gives the same policies as the local
one, the spread is computed over the right numbers), not learning.
"""

from __future__ import annotations

import csv
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.model import load_model, save_model
from tensegrity_gym.cli import main
from tensegrity_gym.models import write_model
from tensegrity_gym.sweep import (
    CURVE_COLUMNS,
    EPISODE_COLUMNS,
    LAST_EPISODES,
    RUN_FILES,
    curve_csv,
    parse_seeds,
    policies_in,
    run_sweep,
    spread,
)
from tensegrity_gym.training import TrainConfig, load_policy, train
from tests._data import GROUND

SEEDS = [3, 5]



@pytest.fixture(scope="module")
def twin(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("robot")
    write_model(d / "robot.xml", "ico", preset="robot")
    model = load_model(GROUND)
    # the machinery under test needs no ground (its law is 70 % of an eager step's time): a robot
    # floating without gravity, so no episode ends early by falling
    model.effects = []
    model.gravity = np.zeros(3)
    model.source_model = str(d / "robot.xml")
    save_model(d / "twin.json", model)
    return d / "twin.json"


def tiny(twin: Path, seed: int = 0) -> TrainConfig:
    # 16-step episodes: several finish within the 64 steps, so the learning curve has rows
    return TrainConfig(timesteps=128, seed=seed, identified=str(twin), envs=2, rollout=32, episode_steps=16)


def weights(policy: str | Path) -> list[np.ndarray]:
    return [p.detach().numpy().copy() for p in load_policy(policy).model.policy.parameters()]


@pytest.fixture(scope="module")
def sweep(twin, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("sweep") / "runs"
    return out, run_sweep(tiny(twin), SEEDS, out, jobs=2, progress=False)


# ---------------------------------------------------------------------- seeds and spread
@pytest.mark.parametrize("text, seeds", [("0-4", [0, 1, 2, 3, 4]), ("7", [7]), ("0,3,7", [0, 3, 7]),
                                         ("0-2,9", [0, 1, 2, 9]), (" 2 - 3 ", [2, 3])])
def test_parse_seeds(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text, match", [("4-1", "backwards"), ("0-2,1", "twice"), ("a", "not a seed"),
                                         ("-1", "not a seed"), ("", "not a seed"), ("1.5", "not a seed")])
def test_parse_seeds_refuses(text, match):
    with pytest.raises(ValueError, match=match):
        parse_seeds(text)


def test_spread_of_known_values():
    s = spread([1.0, 2.0, None, float("nan"), 6.0])
    assert s == {"mean": 3.0, "std": pytest.approx(np.sqrt(14 / 3), rel=1e-15), "min": 1.0, "max": 6.0, "n": 3}
    assert spread([]) == {"mean": None, "std": None, "min": None, "max": None, "n": 0}


# ---------------------------------------------------------------------- local processes
def test_sweep_writes_one_folder_per_seed_and_a_summary(sweep):
    out, summary = sweep
    assert sorted(p.name for p in out.iterdir()) == ["learning_curves.png", "seed_3", "seed_5", "summary.json"]
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(summary))
    assert summary["seeds"] == SEEDS and summary["executor"] == "processes" and summary["jobs"] == 2
    for s, run in zip(SEEDS, summary["runs"], strict=True):
        folder = out / f"seed_{s}"
        assert sorted(p.name for p in folder.iterdir()) == sorted(RUN_FILES)  # no temporary file left
        pol = load_policy(folder / "policy.zip")
        assert pol.meta["seed"] == s and pol.meta["timesteps"] == run["timesteps"] == 128
        assert pol.meta["episode_steps"] == 16
        # VecNormalize's pickle holds the statistics the policy file carries
        with open(folder / "vecnormalize.pkl", "rb") as fh:
            vn = pickle.load(fh)
        np.testing.assert_array_equal(vn.obs_rms.mean, pol.obs_mean)
        np.testing.assert_array_equal(vn.obs_rms.var, pol.obs_var)
        config = json.loads((folder / "config.json").read_text())
        assert config["seed"] == s and config["timesteps"] == 128 and config["envs"] == 2
        assert config["algorithm_kwargs"]["n_steps"] == 16  # rollout 32 over 2 envs
        # every finished episode; the summary's figures are its last rows
        with open(folder / "episodes.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert tuple(rows[0]) == EPISODE_COLUMNS
        assert len(rows) == run["episodes"] == 8 and all(int(r["length"]) == 16 for r in rows)
        t = [int(r["timesteps"]) for r in rows]
        assert t == sorted(t) and t[-1] <= run["timesteps"]
        last = [float(r["progress_m"]) for r in rows][-LAST_EPISODES:]
        assert run["last_progress_m"] == pytest.approx(np.mean(last), rel=1e-12)
        # the learning curve, one row per rollout: each rollout (16 steps x 2 envs) is exactly one
        # episode of each env, so its velocity x 16 steps x 20 ms is their mean progress, and its
        # reward per step their returns over 32 steps (VecMonitor's returns are the raw rewards)
        with open(folder / "progress.csv", newline="") as fh:
            curve = list(csv.DictReader(fh))
        assert tuple(curve[0]) == CURVE_COLUMNS and [int(c["timesteps"]) for c in curve] == [32, 64, 96, 128]
        for k, c in enumerate(curve):
            eps = rows[2 * k: 2 * k + 2]
            assert float(c["velocity_m_s"]) * 16 * 0.02 == pytest.approx(np.mean([float(e["progress_m"]) for e in eps]),
                                                                         rel=1e-9, abs=1e-12)
            assert float(c["reward_per_step"]) == pytest.approx(sum(float(e["return"]) for e in eps) / 32, rel=1e-5)
        assert run["last_velocity_m_s"] == float(curve[-1]["velocity_m_s"])
        assert (folder / "learning_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    sp = summary["over_seeds"]["last_progress_m"]
    vals = [r["last_progress_m"] for r in summary["runs"]]
    assert sp["mean"] == pytest.approx(np.mean(vals)) and sp["std"] == pytest.approx(np.std(vals)) and sp["n"] == 2


def test_a_seed_of_the_sweep_is_the_same_policy_as_training_it_alone(sweep, twin, tmp_path):
    out, _ = sweep
    r = train(tiny(twin, seed=5), tmp_path / "alone.zip", progress=False)
    alone = [p.detach().numpy() for p in r.model.policy.parameters()]
    for x, y in zip(alone, weights(out / "seed_5" / "policy.zip"), strict=True):
        np.testing.assert_array_equal(x, y)
    assert any(not np.array_equal(x, y) for x, y in zip(weights(out / "seed_3" / "policy.zip"),
                                                        weights(out / "seed_5" / "policy.zip"), strict=True))
    with open(out / "seed_5" / "episodes.csv", newline="") as fh:
        sweep_rows = [(r["timesteps"], r["return"], r["progress_m"]) for r in csv.DictReader(fh)]
    alone_rows = [(r["timesteps"], r["return"], r["progress_m"]) for r in csv.DictReader(
        curve_csv(r.episode_log, EPISODE_COLUMNS).splitlines())]
    assert sweep_rows == alone_rows and len(alone_rows) == 8


def test_policies_in_a_sweep_folder(sweep, tmp_path):
    out, _ = sweep
    assert policies_in([str(out)]) == [str(out / "seed_3" / "policy.zip"), str(out / "seed_5" / "policy.zip")]
    one = str(out / "seed_5" / "policy.zip")
    assert policies_in([one, str(out)])[0] == one
    with pytest.raises(ValueError, match="holds no policies"):
        policies_in([str(tmp_path)])
    with pytest.raises(ValueError, match="does not exist"):
        policies_in([str(tmp_path / "nope")])


# ---------------------------------------------------------------------- Ray
def test_ray_tasks_give_the_same_policies_as_local_processes(sweep, twin, tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'tensegrity-gym[ray]')")
    out, local = sweep
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        summary = run_sweep(tiny(twin), SEEDS, tmp_path / "ray", ray_address="local", progress=False)
    finally:
        ray.shutdown()
    assert summary["executor"] == "ray" and summary["seeds"] == SEEDS
    for s in SEEDS:
        for x, y in zip(weights(out / f"seed_{s}" / "policy.zip"),
                        weights(tmp_path / "ray" / f"seed_{s}" / "policy.zip"), strict=True):
            np.testing.assert_array_equal(x, y)
        assert sorted(p.name for p in (tmp_path / "ray" / f"seed_{s}").iterdir()) == sorted(RUN_FILES)
    assert [r["last_progress_m"] for r in summary["runs"]] == [r["last_progress_m"] for r in local["runs"]]


# ---------------------------------------------------------------------- the command line
def test_gap_over_a_sweep_folder_reports_mean_and_spread(sweep, twin, capsys):
    out, _ = sweep
    args = ["gap", "--identified", str(twin), "--policy", str(out), "--episodes", "2", "--episode-steps", "8",
            "--quiet"]
    assert main([*args, "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["policies"] == [str(out / "seed_3" / "policy.zip"), str(out / "seed_5" / "policy.zip")]
    for where in ("twin", "plant"):
        per = [rep[where]["progress_m"] for rep in r["reports"]]
        assert r["over_policies"][where]["progress_m"]["mean"] == pytest.approx(np.mean(per), rel=1e-12)
        assert r["over_policies"][where]["progress_m"]["std"] == pytest.approx(np.std(per), rel=1e-12, abs=1e-15)
    # every policy's episodes together: the ratio of the pooled means, and the count at 90 %
    pooled = {w: [x for rep in r["reports"] for x in rep[w]["progress_per_episode_m"]] for w in ("twin", "plant")}
    if np.mean(pooled["twin"]) > 0:
        assert r["over_policies"]["plant_over_twin_pooled"]["ratio"] == pytest.approx(
            np.mean(pooled["plant"]) / np.mean(pooled["twin"]), rel=1e-12)
    else:
        assert r["over_policies"]["plant_over_twin_pooled"]["ratio"] is None
    assert r["over_policies"]["plant_over_twin_at_least_0.9"] == sum(
        (rep["transfer"]["plant_over_twin"] or 0) >= 0.9 for rep in r["reports"])
    assert r["over_policies"]["plant_over_twin_under_0.9_beyond_noise"] == sum(
        rep["transfer"]["plant_over_twin"] is not None and rep["transfer"]["plant_over_twin_stderr"] is not None
        and rep["transfer"]["plant_over_twin"] + 2 * rep["transfer"]["plant_over_twin_stderr"] < 0.9
        for rep in r["reports"])
    # the random policy ran once: both reports hold the same block
    assert r["reports"][0]["random_plant"] == r["reports"][1]["random_plant"]
    assert main(args) == 0
    said = capsys.readouterr().out
    assert "over the policies:" in said and "plant progress (m): mean" in said and "standard errors" in said


def test_train_seeds_on_the_command_line(twin, tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["train", "--identified", str(twin), "--seeds", "1", "--timesteps", "32", "--envs", "2",
                 "--rollout", "32", "--episode-steps", "16", "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "wrote 1 ppo policies" in said and "summary.json" in said
    assert load_policy(out / "seed_1" / "policy.zip").meta["seed"] == 1


@pytest.mark.parametrize("extra, match", [
    (["--seeds", "3-1", "--out", "DIR"], "--seeds '3-1': the range 3-1 runs backwards"),
    (["--seeds", "0-1", "--out", "P.zip"], "with --seeds, --out is a folder"),
    (["--seeds", "0-1", "--seed", "2", "--out", "DIR"], "either --seed or --seeds"),
    (["--ray", "local", "--out", "P.zip"], "--ray runs several seeds"),
    (["--jobs", "2", "--out", "P.zip"], "--jobs runs several seeds"),
])
def test_train_seeds_bad_input_is_one_line(twin, tmp_path, capsys, extra, match):
    extra = [str(tmp_path / x) if x in ("DIR", "P.zip") else x for x in extra]
    assert main(["train", "--identified", str(twin), "--timesteps", "32", "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tensegrity: error: ") and match in err[0], err
    assert list(tmp_path.iterdir()) == []
