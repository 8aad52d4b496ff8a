"""``tensegrity train`` and ``tensegrity gap``: training on the twin, the policy file, the gap report.

Runs are tiny (a few hundred steps, rollouts of 128-256) so the file stays fast on two cores: these
tests check the machinery, not learning. The twin is the shipped robot model with its source MJCF
written to a file first (building the preset settles its keyframe in MuJoCo; training must not).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the env)
from identified import Topology
from identified.fit.identify import identify
from identified.model import load_model, save_model
from tensegrity_gym.backends.step_size import stable_physics_dt
from tensegrity_gym.cli import main
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter
from tensegrity_gym.gap import open_loop_divergence, run_episodes, twin_layout
from tensegrity_gym.models import write_model
from tensegrity_gym.training import TrainConfig, checkpoint_path, load_policy, train
from tests._data import GROUND

TINY = ["--timesteps", "256", "--envs", "4", "--rollout", "128", "--quiet"]



@pytest.fixture(scope="module")
def robot(tmp_path_factory) -> dict[str, Path]:
    """The robot's MJCF as a file and the shipped twin pointing at it; a paper-preset fit (no motors)."""
    d = tmp_path_factory.mktemp("robot")
    f = {"xml": d / "robot.xml", "twin": d / "twin.json", "paper_xml": d / "ico.xml", "paper": d / "ico.json"}
    write_model(f["xml"], "ico", preset="robot")
    model = load_model(GROUND)  # the mechanics under test do not depend on the contact law
    model.source_model = str(f["xml"])
    save_model(f["twin"], model)
    write_model(f["paper_xml"], "ico", preset="paper-uniform")
    data = collect(f["paper_xml"], CollectConfig(episodes=2, steps=60, seed=1, push_every=20))
    paper = identify(data, Topology.from_mjcf(f["paper_xml"]))
    paper.source_model = str(f["paper_xml"])
    save_model(f["paper"], paper)
    return f


@pytest.fixture(scope="module")
def trained(robot, tmp_path_factory):
    """One short PPO run on the twin through the Python API (policy file and in-memory result)."""
    out = tmp_path_factory.mktemp("policy") / "P.zip"
    cfg = TrainConfig(timesteps=256, seed=3, identified=str(robot["twin"]), envs=4, rollout=128)
    return train(cfg, out, progress=False)


def no_mujoco_stepping(monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("MuJoCo was stepped")

    for name in ("mj_step", "mj_step1", "mj_step2"):
        monkeypatch.setattr(mujoco, name, refuse)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tensegrity: error: "), err
    return err[0]


# ---------------------------------------------------------------------- training
def test_train_on_twin_end_to_end_never_steps_mujoco(robot, tmp_path, monkeypatch, capsys):
    no_mujoco_stepping(monkeypatch)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # the system's temp dir, here
    out = tmp_path / "P.zip"
    assert main(["train", "--identified", str(robot["twin"]), "--seed", "1", "--out", str(out), *TINY]) == 0
    said = capsys.readouterr().out
    assert "wrote ppo policy" in said and "on the twin" in said
    assert out.is_file() and not Path(checkpoint_path(str(out))).exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["P.zip", "tmp"]  # no temporary file left
    # nor a log folder in the temp dir (SB3's default logger makes an empty SB3-<date> one per run)
    assert [p.name for p in scratch.iterdir() if p.name.startswith("SB3")] == []
    pol = load_policy(out)
    assert pol.meta["trained_on"] == "twin" and pol.meta["timesteps"] >= 256
    assert pol.meta["observation_shape"] == [133] and pol.meta["action_shape"] == [24]
    assert pol.meta["hyperparameters"]["n_steps"] == 32  # rollout 128 over 4 envs
    step = stable_physics_dt(str(robot["twin"]), 20).step  # --physics-dt auto: said, used, recorded
    assert f"the twin integrates at {1e3 * step:g} ms: stable at" in said and pol.meta["physics_dt"] == step
    assert np.all(pol.obs_var > 0) and pol.meta["normalize"]["count"] > 256  # statistics were updated
    with zipfile.ZipFile(out) as zf:
        assert {"policy.pth", "data", "tensegrity.json"} <= set(zf.namelist())
    plant = gym.make("TensegrityIco-v0", model=str(robot["xml"]))  # the guard does catch a plant step
    plant.reset(seed=0)
    with pytest.raises(AssertionError, match="MuJoCo was stepped"):
        plant.step(plant.action_space.sample())


def test_training_is_deterministic_with_a_seed(robot, tmp_path):
    def run(seed, name):
        cfg = TrainConfig(timesteps=64, seed=seed, identified=str(robot["twin"]), envs=2, rollout=32)
        r = train(cfg, tmp_path / name, progress=False)
        return [p.detach().numpy().copy() for p in r.model.policy.parameters()], r.vecnormalize.obs_rms.mean

    (a, mean_a), (b, mean_b), (c, _) = run(3, "a.zip"), run(3, "b.zip"), run(4, "c.zip")
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(mean_a, mean_b)
    assert any(not np.array_equal(x, z) for x, z in zip(a, c, strict=True))


def test_saved_and_loaded_policy_gives_the_same_actions(trained, robot):
    pol = load_policy(trained.path)
    env = gym.make("TensegrityIco-v0", backend="identified", model=str(robot["twin"]))
    obs = np.stack([env.reset(seed=s)[0] for s in range(5)])
    env.close()
    vn = trained.vecnormalize
    np.testing.assert_array_equal(pol.normalize(obs), vn.normalize_obs(obs))
    live, _ = trained.model.predict(vn.normalize_obs(obs), deterministic=True)
    np.testing.assert_array_equal(pol.act(obs), np.clip(live, -1, 1))
    assert not np.allclose(pol.act(obs)[0], pol.act(obs)[1])  # the actions depend on the observation


def test_sampled_actions_are_the_policys_gaussian_drawn_per_env_by_its_seed(trained, robot):
    """``act(obs, noise)`` is ``mean + exp(log_std) * noise`` clipped, exactly (noise 0: the mean
    action); ``sampling(seeds)`` draws env k's noise from its own seed, so the same seed acts alike
    alone or beside others, and another seed differently."""
    pol = load_policy(trained.path)
    env = gym.make("TensegrityIco-v0", backend="identified", model=str(robot["twin"]))
    obs = np.stack([env.reset(seed=s)[0] for s in range(3)])
    env.close()
    np.testing.assert_array_equal(pol.act(obs, np.zeros((3, 24))), pol.act(obs))
    noise = np.random.default_rng(0).standard_normal((3, 24))
    std = trained.model.policy.log_std.detach().exp().numpy()
    want = np.clip(pol.act(obs) + std * noise, -1, 1)  # the mean is inside [-1, 1] here
    assert np.abs(trained.model.predict(pol.normalize(obs), deterministic=True)[0]).max() < 1
    np.testing.assert_allclose(pol.act(obs, noise), want, rtol=0, atol=2e-7)
    assert np.abs(pol.act(obs, noise) - pol.act(obs)).max() > 0.1
    alone = [pol.sampling([s])(obs[[k]]) for k, s in enumerate((7, 8, 9))]
    together = pol.sampling([7, 8, 9, 10])(obs)
    # (the network rounds a batch of one and of four differently, ~1e-7 in float32)
    np.testing.assert_allclose(np.concatenate(alone), together, rtol=0, atol=1e-6)
    again = pol.sampling([7, 8, 9])
    first, second = again(obs), again(obs)  # a fresh draw every step
    np.testing.assert_array_equal(first, together)
    assert not np.allclose(first, second) and not np.allclose(pol.sampling([1, 8, 9])(obs)[0], first[0])
    from tensegrity_gym.gap import policy_act

    assert policy_act(pol, "mean", [7], 1) == pol.act  # --actions mean: the distribution's mean
    np.testing.assert_array_equal(policy_act(pol, "sampled", [7, 8, 9], 4)(obs), first)
    with pytest.raises(ValueError, match="--actions must be one of sampled, mean"):
        policy_act(pol, "noisy", [7], 1)
    with pytest.raises(ValueError, match="4 observations for 3 seeded envs"):
        pol.sampling([1, 2, 3])(np.concatenate([obs, obs[:1]]))


def test_a_sac_policy_draws_from_its_squashed_gaussian():
    """SAC's draw is ``tanh(mean + std * noise)``: at zero noise exactly SAC's own deterministic
    action (a draw without the squash would differ), inside (-1, 1) for any noise and increasing
    in it (a policy built untrained on a [-1, 1] action space)."""
    from stable_baselines3 import SAC

    from tensegrity_gym.training import LoadedPolicy

    env = gym.make("MountainCarContinuous-v0")
    sac = SAC("MlpPolicy", env, seed=0, policy_kwargs={"log_std_init": 0.5})
    pol = LoadedPolicy(sac, {"action_shape": [1]}, np.zeros(2), np.ones(2), 10.0, 0.0)
    obs = np.array([[-0.5, 0.01], [0.3, -0.02]], dtype=np.float32)
    own, _ = sac.predict(obs, deterministic=True)
    np.testing.assert_allclose(pol.act(obs, np.zeros((2, 1))), own, rtol=0, atol=1e-7)
    noise = np.array([[-9.0], [-1.0], [0.0], [1.0], [9.0]])
    drawn = np.concatenate([pol.act(obs[:1], n[None]) for n in noise])[:, 0]
    assert np.all(np.abs(drawn) <= 1) and np.all(np.diff(drawn) > 0) and drawn[0] < -0.99 < 0.99 < drawn[-1]
    env.close()


# ---------------------------------------------------------------------- gap
def _evaluate_by_hand(pol, make_env, seeds, steps, actions="sampled"):
    """Return and forward progress of one episode per seed, stepping single envs in a plain loop
    (``actions``: the mean action, or drawn with the noise of that seed alone)."""
    out = []
    for s in seeds:
        env = make_env(steps)
        obs, info = env.reset(seed=s)
        act = pol.act if actions == "mean" else pol.sampling([s])
        x0, ret, done = info["x_position"], 0.0, False
        while not done:
            obs, r, term, trunc, info = env.step(act(obs))
            ret += r
            done = term or trunc
        out.append((ret, info["x_position"] - x0))
        env.close()
    return np.array(out)


def test_gap_numbers_match_separate_evaluations(trained, robot, capsys):
    """Twin and plant episodes of ``gap`` against single envs stepped by hand from the same seeds,
    the actions drawn per env from its own seed (``sampled``, the default; ``mean``, the other
    choice, is :meth:`LoadedPolicy.act` itself: test_sampled_actions...)."""
    actions = "sampled"
    args = ["gap", "--identified", str(robot["twin"]), "--policy", trained.path, "--episodes", "2",
            "--seed", "5", "--episode-steps", "30", "--json", "--quiet"]
    assert main(args) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["actions"] == actions
    for key in ("twin", "plant", "random_plant"):
        assert {"return", "progress_m"} <= set(r[key])
        assert len(r[key]["returns"]) == 2
    assert len(r["open_loop"]["com_divergence_m"]) == len(r["open_loop"]["t_s"])
    assert r["open_loop"]["com_divergence_m"][0] == pytest.approx(0.0, abs=1e-6)  # same starts (float32 twin)
    pol = load_policy(trained.path)
    # the twin that gave these: the size the policy trained on (4 sub-envs, 2 of them padding, with
    # per-env parameters as its randomized training had), so its compiled step would be reused
    assert twin_layout(pol, 2) == (4, True) and twin_layout(pol, 6) == (6, True)
    seeds = [5, 6]
    plant = _evaluate_by_hand(pol, lambda n: gym.make("TensegrityIco-v0", model=str(robot["xml"]),
                                                     max_episode_steps=n), seeds, 30, actions)
    twin = _evaluate_by_hand(pol, lambda n: gym.make("TensegrityIco-v0", backend="identified",
                                                    model=str(robot["twin"]), max_episode_steps=n), seeds, 30,
                             actions)
    # the network on a batch of rows and on one row rounds differently in float32 (~1e-7 in the
    # actions), which the dynamics carry on; a wrong seed, start or sum would be off by far more
    tol = {"rtol": 1e-4, "atol": 1e-6}
    np.testing.assert_allclose(r["plant"]["returns"], plant[:, 0], **tol)
    np.testing.assert_allclose(r["plant"]["progress_per_episode_m"], plant[:, 1], **tol)
    # the float32 twin with ground contact carries those ~1e-7 further than the float64 plant: on
    # a return after 30 steps, 1.2e-4 relative with the component-form step (4e-6 with the tensor
    # form before it: float32 trajectories that round differently; the batched and the single
    # twin step bitwise alike given the same actions); returns of other seeds differ by far more
    twin_tol = {"rtol": 1e-3, "atol": 1e-5}
    np.testing.assert_allclose(r["twin"]["returns"], twin[:, 0], **twin_tol)
    np.testing.assert_allclose(r["twin"]["progress_per_episode_m"], twin[:, 1], **twin_tol)
    assert r["plant"]["return"] == pytest.approx(np.mean(r["plant"]["returns"]), rel=1e-12)
    assert r["twin"]["progress_m"] == pytest.approx(np.mean(r["twin"]["progress_per_episode_m"]), rel=1e-12)
    assert not np.allclose(plant[:, 1], twin[:, 1], **tol)  # the two evaluations are told apart
    assert r["random_plant"]["returns"] != r["plant"]["returns"]


def test_open_loop_replay_of_the_plant_on_the_plant_does_not_diverge(trained, robot):
    """The open-loop machinery against itself: the plant's own commands replayed on the plant."""
    pol = load_policy(trained.path)

    def plant(n):
        return gym.make_vec("TensegrityIco-v0", num_envs=n, vectorization_mode="vector_entry_point",
                            model=str(robot["xml"]), max_episode_steps=25)

    closed = run_episodes(plant(2), pol.act, [0, 1])
    seq = np.stack(closed.actions)
    replay = run_episodes(plant(2), pol.act, [0, 1], actions=seq)
    ol = open_loop_divergence(closed, replay, dt=0.02)
    assert len(ol["com_divergence_m"]) == 26
    assert max(ol["com_divergence_m"]) < 1e-12 and ol["time_to_0.1m_s"] is None
    shifted = run_episodes(plant(2), pol.act, [7, 8], actions=seq)  # other starts: it must see a difference
    assert open_loop_divergence(closed, shifted, dt=0.02)["mean_m"] > 1e-4


def test_video_frames_are_drawn_from_the_first_evaluated_episode(trained, robot):
    """``run_episodes(render=, every=)`` draws sub-env 0 after the reset, every ``every`` steps and at
    its episode's last step, without changing the episodes; here the "image" is the rod positions."""
    pol = load_policy(trained.path)

    def twin():
        return gym.make_vec("TensegrityIco-v0", num_envs=2, vectorization_mode="vector_entry_point",
                            backend="identified", model=str(robot["twin"]), max_episode_steps=5)

    v = twin()
    drawn = run_episodes(v, pol.act, [3, 4], render=lambda: v._pos[0].copy(), every=2)
    plain = run_episodes(twin(), pol.act, [3, 4])
    np.testing.assert_array_equal(drawn.returns, plain.returns)
    assert plain.frames == []
    # by hand: the same twin, sub-env 0's positions after the reset and after steps 2, 4 and 5 (its last)
    v = twin()
    obs, _ = v.reset(seed=[3, 4])
    want = [v._pos[0].copy()]
    for t in range(1, 6):
        obs, *_ = v.step(np.asarray(pol.act(obs), dtype=np.float32))
        if t in (2, 4, 5):
            want.append(v._pos[0].copy())
    assert len(drawn.frames) == 4
    for got, ref in zip(drawn.frames, want):
        np.testing.assert_array_equal(got, ref)
    assert not np.array_equal(drawn.frames[1], drawn.frames[2])


# ---------------------------------------------------------------------- bad input and interrupts
def test_bad_inputs_fail_with_one_line(robot, trained, tmp_path, capsys):
    out = tmp_path / "P.zip"
    base = ["train", "--identified", str(robot["twin"]), "--out", str(out)]
    assert main([*base, "--timesteps", "0"]) == 2
    assert "--timesteps" in one_error_line(capsys)
    assert main([*base, "--timesteps", "10", "--algo", "dqn"]) == 2
    assert "dqn" in one_error_line(capsys)
    assert main(["train", "--identified", str(robot["twin"]), "--out", str(tmp_path / "no" / "P.zip"),
                 *TINY]) == 2
    assert "--out" in (line := one_error_line(capsys)) and "does not exist" in line
    assert main(["train", "--identified", str(robot["paper"]), "--out", str(out), *TINY]) == 2
    assert "actuated" in one_error_line(capsys)
    assert not out.exists()

    # a policy file of another env (an SB3 zip without the tensegrity entry), and one whose recorded
    # spaces are not the env's
    from stable_baselines3 import PPO

    foreign = tmp_path / "pendulum.zip"
    PPO("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=64, device="cpu").save(foreign)
    gap = ["gap", "--identified", str(robot["twin"]), "--episodes", "1", "--episode-steps", "5", "--quiet"]
    assert main([*gap, "--policy", str(foreign)]) == 2
    assert "not a tensegrity policy" in one_error_line(capsys)
    other = tmp_path / "other_space.zip"
    with zipfile.ZipFile(trained.path) as src, zipfile.ZipFile(other, "w") as dst:
        for name in src.namelist():
            data = src.read(name)
            if name == "tensegrity.json":
                meta = json.loads(data)
                meta["env_kwargs"]["exclude_current_positions_from_observation"] = False
                data = json.dumps(meta).encode()
            dst.writestr(name, data)
    assert main([*gap, "--policy", str(other)]) == 2
    assert "trained on observations (133,)" in one_error_line(capsys)
    not_zip = tmp_path / "junk.zip"
    not_zip.write_text("not a zip")
    assert main([*gap, "--policy", str(not_zip)]) == 2
    assert "not a zip" in one_error_line(capsys)
    assert main([*gap, "--policy", trained.path, "--episodes", "0"]) == 2
    assert "--episodes" in one_error_line(capsys)
    assert main([*gap, "--policy", trained.path, "--video", str(not_zip)]) == 2
    assert "not a folder" in one_error_line(capsys)
    assert sorted(os.listdir(tmp_path)) == ["junk.zip", "other_space.zip", "pendulum.zip"]


def test_interrupt_keeps_the_last_complete_checkpoint(robot, tmp_path, monkeypatch, capsys):
    calls = {"n": 0}
    step = SB3VecEnvAdapter.step_wait

    def step_then_interrupt(self):
        calls["n"] += 1
        if calls["n"] > 80:  # after two updates of 32 steps per env
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(SB3VecEnvAdapter, "step_wait", step_then_interrupt)
    out = tmp_path / "P.zip"
    rc = main(["train", "--identified", str(robot["twin"]), "--out", str(out), "--timesteps", "100000",
               "--envs", "4", "--rollout", "128", "--quiet"])
    assert rc == 130
    err = capsys.readouterr().err
    ckpt = checkpoint_path(str(out))
    assert f"checkpoint (step 256) is {ckpt}" in err
    assert not out.exists() and load_policy(ckpt).meta["timesteps"] == 256
    assert sorted(os.listdir(tmp_path)) == ["P.ckpt.zip"]


# ---------------------------------------------------------------------- videos
_VIDEO_SCRIPT = """
import json, os, sys
import imageio_ffmpeg
from tensegrity_gym import gap
policy, twin, folder = sys.argv[1:4]
gap.VIDEO_SIZE = 64
try:
    r = gap.measure_gap(policy, twin, 1, episode_steps=4, video_dir=folder, progress=False)
except RuntimeError as exc:
    if "offscreen rendering is not available" in str(exc):
        print(json.dumps({"unavailable": str(exc)})); raise SystemExit(0)
    raise
out = {}
for name, path in r["videos"].items():
    with open(path, "rb") as fh:
        head = fh.read(12)
    reader = imageio_ffmpeg.read_frames(path)
    meta = next(reader)
    out[name] = {"ftyp": head[4:8].decode("latin-1"), "frames": sum(1 for _ in reader), "size": meta["size"]}
print(json.dumps({"videos": out, "files": sorted(os.listdir(folder))}))
"""


def test_gap_writes_an_mp4_of_each(trained, robot, tmp_path):

    from tests._render import render_in_subprocess

    folder = tmp_path / "videos"
    script = f"import sys; sys.argv = ['x', {trained.path!r}, {str(robot['twin'])!r}, {str(folder)!r}]\n"
    r = render_in_subprocess(script + _VIDEO_SCRIPT)
    assert r["files"] == ["plant.mp4", "random_plant.mp4", "twin.mp4", "twin_plant.mp4"]  # nothing temporary left
    for name in ("twin", "plant", "random_plant", "twin_plant"):
        v = r["videos"][name]
        assert v["ftyp"] == "ftyp" and v["size"] == ([64 + 4 + 64, 64] if name == "twin_plant" else [64, 64])
        assert v["frames"] == 3  # reset, then every 2nd of 4 steps


@pytest.mark.parametrize("command,options", [
    ("train", ["--identified", "--algo", "--timesteps", "--seed", "--out", "--plant", "--envs", "--rollout",
               "--episode-steps", "--threads", "--tensorboard", "--quiet"]),
    ("gap", ["--identified", "--policy", "--episodes", "--seed", "--episode-steps", "--json", "--video",
             "--threads", "--quiet"]),
])
def test_help_lists_options(command, options, capsys):
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: tensegrity {command}")
    for opt in options:
        assert opt in text


def test_training_counts_and_reports_a_diverging_twin(robot, tmp_path):
    """A twin that blows up (every cable pushing with -1e7 N/m) ends every training episode with a
    non-finite state; training counts them and the command says so in one warning line, where a
    stable twin's count is 0."""

    from tensegrity_gym.training import divergence_warning

    m = json.loads(Path(robot["twin"]).read_text())
    for s in m["springs"]:
        s["stiffness"] = -1e7
    bad = tmp_path / "unstable.json"
    bad.write_text(json.dumps(m))
    cfg = TrainConfig(timesteps=64, seed=0, identified=str(bad), envs=2, rollout=32)
    r = train(cfg, tmp_path / "P.zip", progress=False)
    assert r.episodes > 2 and r.diverged_episodes == r.episodes
    assert f"in {r.episodes} of {r.episodes} training episodes" in divergence_warning(r.diverged_episodes, r.episodes)
    out = tmp_path / "Q.zip"
    proc = subprocess.run([sys.executable, "-m", "tensegrity_gym.cli", "train", "--identified", str(bad),
                           "--timesteps", "64", "--envs", "2", "--rollout", "32", "--quiet", "--out", str(out)],
                          check=False, capture_output=True, text=True)
    assert proc.returncode == 0 and out.exists()
    warn = [ln for ln in proc.stderr.splitlines() if "diverged" in ln]
    assert len(warn) == 1 and warn[0].startswith("tensegrity: warning: the twin's physics diverged")


def test_stable_twin_reports_no_divergence(trained):
    from tensegrity_gym.training import divergence_warning

    assert trained.diverged_episodes == 0
    assert divergence_warning(trained.diverged_episodes, trained.episodes) is None
