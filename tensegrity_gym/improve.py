"""Closing the loop through the policy: ``tensegrity improve``.

The fit saw the plant under random commands; a policy drives the robot into states the fit never
saw (rolling over an edge, contacts the random commands rarely make), and that is where its twin is
wrong. :func:`improve` runs rounds of

1. **roll** the current policy on the plant for a few episodes, recorded at the physics rate as a
   dataset in the project's collect format (:func:`record_policy`; the episodes are also the
   round's plant evaluation: progress per episode);
2. **diagnose** the current twin on those recordings: its one-step error (every physics step
   predicted from the recorded state, RMS over rods and steps, as the fit's ``one_step_rms``) and
   its free-run position error over 1 s windows, on the policy's own states (:func:`twin_errors`);
3. **refit** the model on the fit's data with the new recordings added (cut into episodes of the
   fit's episode length), with the current model's effects;
4. **train on**: continue training the current policy (weights and observation normalisation) on
   the new twin (:class:`~tensegrity_gym.training.TrainConfig` ``init_policy``), with the same
   randomization, and evaluate it on that twin from the same reset seeds as the plant episodes.

Every round writes ``DIR/round<k>/`` (``plant.npz`` the recording, ``model.json`` the refitted
model, ``policy.zip``) and ``DIR/improve.json`` the table (per round: plant progress, twin progress,
the twin's errors on the policy's states before and after the refit, ``twin_fitted_on_s`` the
plant seconds the round's twin was fitted on, ``plant_data_s`` the plant seconds used so far, this
round's recording included).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import gymnasium as gym
import numpy as np

from identified.dataset import Dataset, atomic_write, load_dataset, save_dataset
from identified.model import load_model, save_model
from tensegrity_gym.training import ENV_ID, LoadedPolicy, TrainConfig, load_policy, plant_mjcf, train

__all__ = ["ImproveConfig", "concat_episodes", "improve", "record_policy", "twin_errors"]


@dataclass
class ImproveConfig:
    """What :func:`improve` does.

    Args:
        rounds: rounds of roll -> diagnose -> refit -> train on.
        episodes: plant episodes recorded per round (reset seeds ``seed + 1000 r + k``).
        episode_steps: control steps per recorded episode (the policy's own episode length by
            default).
        timesteps: training steps on the new twin per round.
        randomize: the twin's randomization while training on (``"auto"``, ``"none"``, FILE).
        effects: effects of the refit: ``"same"`` (the current model's, fast) or as ``fit --effects``.
        seed: reset seeds of the plant episodes and the training seed.
        envs: twins trained in parallel (``None``: the training default).
        actions: how the policy acts on the plant and the twin, ``"sampled"`` or ``"mean"``
            (:func:`tensegrity_gym.gap.policy_act`).
    """

    rounds: int = 2
    episodes: int = 2
    episode_steps: int | None = None
    timesteps: int = 100_000
    randomize: Any = "auto"
    effects: str = "same"
    seed: int = 0
    envs: int | None = None
    actions: str = "sampled"

    def validate(self) -> None:
        for name in ("rounds", "episodes", "timesteps"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v}")
        if self.episode_steps is not None and (int(self.episode_steps) != self.episode_steps or self.episode_steps < 1):
            raise ValueError(f"episode_steps must be an integer >= 1, got {self.episode_steps}")
        from tensegrity_gym.gap import check_actions

        check_actions(self.actions)


# ---------------------------------------------------------------------- recording
def record_policy(policy: LoadedPolicy, mjcf: str, seeds: list[int], episode_steps: int,
                  chunk_steps: int | None = None, actions: str = "sampled") -> tuple[Dataset, np.ndarray]:
    """The policy on the plant, one episode per seed (reset as the env resets with that seed),
    recorded at the physics rate, and the forward progress of each episode (m, over its whole
    length). The :class:`~identified.dataset.Dataset` holds every episode cut into consecutive
    pieces of ``chunk_steps`` physics steps (a shorter remainder left out; ``None``: every
    episode cut to the shortest, a dataset's episodes having one length). ``actions``: as
    :func:`tensegrity_gym.gap.policy_act` (sampled: the draws of each seed's episode on the twin)."""
    import tensegrity_gym  # noqa: F401  (registers the env)
    from tensegrity_gym.gap import policy_act

    env = gym.make(ENV_ID, model=mjcf, max_episode_steps=episode_steps, **policy.env_kwargs)
    policy.check_env(env.observation_space, env.action_space)
    plant = env.unwrapped.backend.plant  # type: ignore[attr-defined]
    rows: list[tuple] = []
    step = plant.step

    def recorded_step(push_force: Any = None, push_point: Any = None) -> None:
        s = plant.states()
        target = plant.targets.copy()
        step(push_force, push_point)
        rows.append((s, target, plant.rest_lengths()))

    plant.step = recorded_step  # the env's backend steps the plant through this
    episodes, progress = [], []
    try:
        for seed in seeds:
            rows.clear()
            obs, info = env.reset(seed=int(seed))
            act = policy_act(policy, actions, [int(seed)], 1)
            x0 = float(info["x_position"])
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(act(obs))
                done = terminated or truncated
            progress.append(float(info["x_position"]) - x0)
            last = plant.states()
            states = [r[0] for r in rows] + [last]
            episodes.append({
                "pos": np.stack([s.pos for s in states]), "quat": np.stack([s.quat for s in states]),
                "vel": np.stack([s.vel for s in states]), "angvel": np.stack([s.angvel for s in states]),
                "command": np.stack([r[1] for r in rows]), "rest_length": np.stack([r[2] for r in rows])})
    finally:
        plant.step = step
        env.close()
    T = int(chunk_steps) if chunk_steps else min(len(e["command"]) for e in episodes)
    state = ("pos", "quat", "vel", "angvel")
    pieces = [(e, j * T) for e in episodes for j in range(len(e["command"]) // T)]
    if not pieces:
        raise ValueError(f"the policy's plant episodes are shorter than {T} physics steps: nothing to record")
    cut = {k: np.stack([e[k][a: a + T + (k in state)] for e, a in pieces]) for k in episodes[0]}
    E, R = cut["pos"].shape[0], cut["pos"].shape[2]
    data = Dataset(dt=plant.dt, gravity=np.array(plant.model.opt.gravity, dtype=float),
                   rod_names=tuple(plant.rod_names), tendon_names=tuple(plant.tendon_names),
                   actuated_names=tuple(plant.actuated_names), push_force=np.zeros((E, T, R, 3)),
                   push_point=np.zeros((E, T, R, 3)), seed=int(seeds[0]), **cut).validate()
    return data, np.array(progress)


def concat_episodes(base: Dataset, new: Dataset) -> Dataset:
    """``base`` with ``new``'s episodes added (both of the same episode length)."""
    if new.n_steps != base.n_steps:
        raise ValueError(f"episodes of {new.n_steps} steps cannot join a dataset of {base.n_steps}-step episodes")
    keys = ("pos", "quat", "vel", "angvel", "command", "rest_length", "push_force", "push_point")
    return replace(base, **{k: np.concatenate([getattr(base, k), getattr(new, k)]) for k in keys}).validate()


def twin_errors(model: Any, data: Dataset, horizon_steps: int = 1000) -> dict[str, float]:
    """The twin's errors on recorded states: one-step RMS of position (m), velocity (m/s),
    angular velocity (rad/s) over every rod and physics step, and the mean free-run position error
    (m) of ``horizon_steps``-step runs from recorded states (:func:`identified.evaluate.window_error`)."""
    import torch

    from identified.evaluate import window_error
    from identified.twin import engine_from_model

    eng = engine_from_model(model, dtype=torch.float64)
    E, T = data.n_episodes, data.n_steps
    flat = lambda a, sl: torch.as_tensor(a[:, sl].reshape((E * T,) + a.shape[2:]))
    now = eng.state(*(flat(getattr(data, k), slice(0, T)) for k in ("pos", "quat", "vel", "angvel")))
    with torch.no_grad():
        nxt = eng.step(now, flat(data.rest_length, slice(None)))
    rms = lambda pred, k: float(np.sqrt(np.mean((pred.numpy() - data.__dict__[k][:, 1:].reshape(pred.shape)) ** 2)))
    out = {"one_step_pos_m": rms(nxt.pos, "pos"), "one_step_vel_m_s": rms(nxt.vel, "vel"),
           "one_step_angvel_rad_s": rms(nxt.angvel, "angvel")}
    steps = min(int(horizon_steps), T)
    out["free_run_m"] = window_error(model, data, steps)
    out["free_run_s"] = steps * data.dt
    return out


def _twin_progress(policy: LoadedPolicy, identified: str, seeds: list[int], episode_steps: int,
                   actions: str = "sampled") -> np.ndarray:
    """The policy's forward progress on the twin of ``identified`` from the given reset seeds."""
    from tensegrity_gym.gap import policy_act, run_episodes

    venv = gym.make_vec(ENV_ID, num_envs=len(seeds), vectorization_mode="vector_entry_point", backend="identified",
                        model=identified, max_episode_steps=episode_steps, **policy.env_kwargs)
    try:
        return run_episodes(venv, policy_act(policy, actions, seeds, venv.num_envs), seeds).progress
    finally:
        venv.close()


# ---------------------------------------------------------------------- the loop
def improve(identified: str, data: str, policy: str, out_dir: str, cfg: ImproveConfig,
            mjcf: str | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Run ``cfg.rounds`` rounds (module docstring) from the model ``identified`` fitted on the
    dataset ``data``, starting with the policy file ``policy``; writes ``out_dir``. Returns the
    rows of ``improve.json``: round 0 is the starting policy on the plant and the starting twin."""
    from identified.fit.pipeline import fit_model

    cfg.validate()
    for what, p in (("identified model", identified), ("dataset", data), ("policy", policy)):
        if not os.path.isfile(p):
            raise ValueError(f"{what} '{p}' does not exist or is not a file")
    os.makedirs(out_dir, exist_ok=True)
    say = (lambda msg: print(f"improve: {msg}", flush=True)) if progress else (lambda msg: None)
    model = load_model(identified)
    if mjcf is None:
        mjcf_text = plant_mjcf(identified)
        mjcf = os.path.join(out_dir, "plant.xml")
        atomic_write(mjcf, lambda fh: fh.write(mjcf_text))
    fit_data = load_dataset(data)
    pol_path, model_path = os.fspath(policy), os.fspath(identified)
    pol = load_policy(pol_path)
    steps = int(cfg.episode_steps or pol.episode_steps)
    plant_s, rows = 0.0, []
    fit_s = fit_data.n_episodes * fit_data.n_steps * fit_data.dt
    for r in range(cfg.rounds + 1):
        t0 = time.perf_counter()
        seeds = [int(cfg.seed) + 1000 * r + k for k in range(cfg.episodes)]
        rec, plant_prog = record_policy(pol, mjcf, seeds, steps, chunk_steps=fit_data.n_steps, actions=cfg.actions)
        twin_prog = _twin_progress(pol, model_path, seeds, steps, cfg.actions)
        row: dict[str, Any] = {"round": r, "policy": os.path.abspath(pol_path), "model": os.path.abspath(model_path),
                               "seeds": seeds, "plant_progress_m": float(np.mean(plant_prog)),
                               "twin_progress_m": float(np.mean(twin_prog)),
                               "twin_fitted_on_s": fit_s + plant_s,
                               "plant_progress_per_episode_m": plant_prog.tolist(),
                               "twin_progress_per_episode_m": twin_prog.tolist(),
                               "twin_error_on_policy_states": twin_errors(model, rec)}
        say(f"round {r}: plant {row['plant_progress_m']:.3f} m, twin {row['twin_progress_m']:.3f} m, twin free-run "
            f"error on the policy's states {row['twin_error_on_policy_states']['free_run_m']:.4f} m")
        if r == cfg.rounds:  # the last policy's evaluation: its recording is not used
            row["plant_data_s"] = fit_s + plant_s
            row["round_s"] = time.perf_counter() - t0
            rows.append(row)
            break
        d = os.path.join(out_dir, f"round{r + 1}")
        os.makedirs(d, exist_ok=True)
        save_dataset(os.path.join(d, "plant.npz"), rec)
        plant_s += rec.n_episodes * rec.n_steps * rec.dt
        fit_data = concat_episodes(fit_data, rec)
        effects = ",".join(e["name"] for e in model.effects) or "none" if cfg.effects == "same" else cfg.effects
        new = fit_model(fit_data, mjcf, effects=effects, progress=False)
        new.source_model = model.source_model if model.source_model else os.path.abspath(mjcf)
        model_path = os.path.join(d, "model.json")
        save_model(model_path, new)
        row["refit_error_on_policy_states"] = twin_errors(new, rec)
        row["plant_data_s"] = fit_s + plant_s
        say(f"round {r + 1}: refit on {fit_data.n_episodes} episodes ({fit_s + plant_s:.0f} s of plant data); "
            f"free-run error on the policy's states {row['refit_error_on_policy_states']['free_run_m']:.4f} m")
        model = new
        tc = TrainConfig(timesteps=cfg.timesteps, seed=cfg.seed + r + 1, identified=model_path, envs=cfg.envs,
                         randomize=cfg.randomize, init_policy=pol_path, episode_steps=pol.episode_steps,
                         env_kwargs=pol.env_kwargs)
        pol_path = os.path.join(d, "policy.zip")
        train(tc, pol_path, progress=progress)
        pol = load_policy(pol_path)
        row["round_s"] = time.perf_counter() - t0
        rows.append(row)
        _write(out_dir, cfg, rows)
    _write(out_dir, cfg, rows)
    return rows


def _write(out_dir: str, cfg: ImproveConfig, rows: list[dict[str, Any]]) -> None:
    from identified.jsonsafe import json_safe

    text = json.dumps(json_safe({"config": asdict(cfg), "rounds": rows}), indent=1)
    atomic_write(os.path.join(out_dir, "improve.json"), lambda fh: fh.write(text))
