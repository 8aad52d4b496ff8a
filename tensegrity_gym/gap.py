"""The sim-to-sim gap of a policy trained on the twin: ``tensegrity gap``.

:func:`measure_gap` runs, from the same reset seeds (episode ``k`` resets with ``seed + k`` on
every env, so twin and plant start from the same perturbed pose):

* ``twin``: the policy on the identified twin (the batched vector env, one episode per sub-env);
* ``plant``: the policy on the MuJoCo plant the twin was identified from;
* ``random_plant``: uniformly random actions in [-1, 1] on the plant, the floor;
* ``open_loop``: the policy's command sequences recorded on the plant, replayed open loop on the
  twin from the same starts (the twin does not end episodes for height here: it runs every
  recorded step); the distance between the two centres of mass versus time, averaged over the
  episodes still running at that time. It isolates the model error from the policy's feedback.

Each of the first three has ``return`` (mean undiscounted episode return) and ``progress_m`` (mean
forward distance of the centre of mass per episode, m), plus the per-episode values and lengths.
``transfer`` has the ratios a transfer is judged by: plant progress over twin progress
and over the random policy's.
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from tensegrity_gym.randomize import Randomization
from tensegrity_gym.training import ENV_ID, LoadedPolicy, load_policy, plant_mjcf, torch_threads

__all__ = ["ACTIONS", "CLEAR_Z", "EpisodeSet", "against_line", "check_actions", "measure_gap", "measure_gaps", "open_loop_divergence",
           "policy_act", "reset_seeds", "run_episodes", "transfer_ratios", "twin_layout", "write_mp4"]

Act = Callable[[np.ndarray], np.ndarray]
#: How a policy acts in evaluation (:func:`policy_act`); the first is the default: PPO trains and
#: judges the policy that samples, and the mean action alone can stick on an edge where a draw does
#: not (README, "Sampled or mean actions")
ACTIONS = ("sampled", "mean")
#: Videos: frame size (pixels) and by default one frame every this many control steps (25 fps at
#: 50 Hz: real time); MuJoCo's offscreen renderer on a CPU-only machine takes ~0.1-0.6 s per frame.
VIDEO_SIZE = 320
VIDEO_EVERY = 2
#: Frames per second of every video: real time at one frame every 2 control steps, a time-lapse
#: (``every / 2`` times faster) above.
VIDEO_FPS = 25.0


@dataclass
class EpisodeSet:
    """One episode per seed: returns, forward progress and lengths (K,), per episode the actions
    taken (T_k, A) and the centre of mass at every instant (T_k + 1, 3), and the video frames of
    the first episode where they were asked for."""

    seeds: list[int]
    returns: np.ndarray
    progress: np.ndarray
    lengths: np.ndarray
    actions: list[np.ndarray]
    com: list[np.ndarray]
    diverged: np.ndarray
    frames: list[np.ndarray] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The JSON block: means, spreads and per-episode values."""
        return {
            "return": float(np.mean(self.returns)),
            "progress_m": float(np.mean(self.progress)),
            "return_std": float(np.std(self.returns)),
            "progress_std_m": float(np.std(self.progress)),
            "episode_steps": float(np.mean(self.lengths)),
            "episodes": len(self.seeds),
            "returns": [float(x) for x in self.returns],
            "progress_per_episode_m": [float(x) for x in self.progress],
            "lengths": [int(x) for x in self.lengths],
        }


def run_episodes(venv: gym.vector.VectorEnv, act: Act, seeds: list[int],
                 actions: np.ndarray | None = None, bar: Any = None,
                 render: Callable[[], np.ndarray] | None = None, every: int = 1) -> EpisodeSet:
    """One episode on each of the first K = len(seeds) sub-envs of ``venv``, sub-env ``k`` reset
    with ``seeds[k]``; the episodes end by the env's termination or time limit. Sub-envs beyond the
    first K (a twin the size of the one a policy trained on, whose compiled step is then reused)
    run from the seeds after ``seeds[-1]`` and are not reported.

    ``act``: (N, n_obs) observations -> (N, A) actions. ``actions`` (K, T, A): play these instead
    (open loop), each episode ending after its T steps at most (NaN rows end it early).
    ``render``: the image of sub-env 0, taken after the reset, every ``every`` steps of its episode
    and at its last (the video of the first episode, :attr:`EpisodeSet.frames`).
    """
    K, N = len(seeds), venv.num_envs
    if not 1 <= K <= N:
        raise ValueError(f"{K} seeds for {N} envs")
    obs, info = venv.reset(seed=reset_seeds(seeds, N))
    x0 = np.asarray(info["x_position"], dtype=float).copy()
    coms: list[list[np.ndarray]] = [[np.asarray(info["com"][k], dtype=float).copy()] for k in range(K)]
    taken: list[list[np.ndarray]] = [[] for _ in range(K)]
    ret = np.zeros(K)
    progress = np.zeros(K)
    lengths = np.zeros(K, dtype=int)
    diverged = np.zeros(K, dtype=bool)
    active = np.ones(K, dtype=bool)
    frames = [] if render is None else [render()]
    t = 0
    while active.any():
        if actions is not None:
            if t >= actions.shape[1]:
                break
            a = np.zeros((N, actions.shape[2]), dtype=np.float32)
            a[:K] = np.nan_to_num(actions[:, t], nan=0.0)
            active &= ~np.isnan(actions[:, t]).any(axis=1)
            if not active.any():
                break
        else:
            a = np.asarray(act(obs), dtype=np.float32).reshape(N, -1)
        obs, rew, term, trunc, info = venv.step(a)
        x = np.asarray(info["x_position"], dtype=float)
        reasons = info.get("termination_reason")
        for k in np.flatnonzero(active):
            ret[k] += float(rew[k])
            lengths[k] += 1
            taken[k].append(np.clip(a[k], -1.0, 1.0))
            coms[k].append(np.asarray(info["com"][k], dtype=float).copy())
            progress[k] = x[k] - x0[k]
            if term[k] and reasons is not None and reasons[k] == "non-finite state":
                diverged[k] = True
        if bar is not None:
            bar.update(int(active.sum()))
        was = bool(active[0])
        active &= ~(np.asarray(term)[:K] | np.asarray(trunc)[:K])
        t += 1
        if render is not None and was and (t % every == 0 or not active[0]):
            frames.append(render())
    A = venv.single_action_space.shape[0]  # type: ignore[index]
    return EpisodeSet(seeds=list(seeds), returns=ret, progress=progress, lengths=lengths,
                      actions=[np.array(x).reshape(-1, A) for x in taken],
                      com=[np.array(c) for c in coms], diverged=diverged, frames=frames)


def reset_seeds(seeds: list[int], n_envs: int) -> list[int]:
    """The reset seed of each of ``n_envs`` sub-envs when the first ``len(seeds)`` run ``seeds``
    (:func:`run_episodes`): the others the seeds after ``seeds[-1]``."""
    return [int(s) for s in seeds] + [int(seeds[-1]) + 1 + i for i in range(n_envs - len(seeds))]


def check_actions(actions: str) -> None:
    """ValueError unless ``actions`` is one of :data:`ACTIONS`."""
    if actions not in ACTIONS:
        raise ValueError(f"--actions must be one of {', '.join(ACTIONS)}, got {actions!r}")


def policy_act(policy: LoadedPolicy, actions: str, seeds: list[int], n_envs: int) -> Act:
    """How ``policy`` acts in ``n_envs`` sub-envs whose first ones run ``seeds``: ``"sampled"``, a
    draw from its action distribution, each sub-env's noise seeded by its reset seed (the same on
    the twin and the plant, :meth:`LoadedPolicy.sampling`); ``"mean"``, the distribution's mean."""
    check_actions(actions)
    return policy.act if actions == "mean" else policy.sampling(reset_seeds(seeds, n_envs))


def twin_layout(policy: LoadedPolicy, episodes: int) -> tuple[int, bool]:
    """The sub-envs of the twin that evaluates ``policy`` on ``episodes`` episodes, and whether they
    carry per-env parameters: those the policy trained with when it trained on the twin (so that the
    compiled substep its training stored on disk serves the evaluation: a compile saved, minutes
    with an elaborate contact law), at least ``episodes``; else ``episodes``, none."""
    meta = policy.meta
    if meta.get("trained_on") != "twin":
        return int(episodes), False
    r = meta.get("randomization")
    per_env = r is not None and Randomization.from_json(r, source="the policy's metadata").physical
    return max(int(episodes), int(meta.get("envs") or episodes)), per_env


def _twin_venv(identified: str | None, n: int, episode_steps: int | None, env_kwargs: dict[str, Any],
               backend_kwargs: dict[str, Any] | None, render: bool = False, per_env: bool = False
               ) -> gym.vector.VectorEnv:
    kw = dict(env_kwargs)
    if render:
        kw["render_mode"] = "rgb_array"
    return gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", backend="identified",
                        model=identified, max_episode_steps=episode_steps, backend_kwargs=backend_kwargs,
                        per_env_parameters=per_env, **kw)


def _plant_venv(mjcf: str, n: int, episode_steps: int | None, env_kwargs: dict[str, Any], render: bool = False
                ) -> gym.vector.SyncVectorEnv:
    kw = dict(env_kwargs)
    if render:
        kw["render_mode"] = "rgb_array"
    return gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", backend="mujoco",
                        model=mjcf, max_episode_steps=episode_steps, **kw)


def _random_act(action_dim: int, seed: int) -> Act:
    rng = np.random.default_rng(seed)

    def act(obs: np.ndarray) -> np.ndarray:
        return rng.uniform(-1.0, 1.0, size=(np.asarray(obs).shape[0], action_dim)).astype(np.float32)

    return act


def open_loop_divergence(plant: EpisodeSet, twin: EpisodeSet, dt: float) -> dict[str, Any]:
    """Distance between the twin's and the plant's centres of mass under the same commands.

    ``com_divergence_m[t]``: mean over the episodes that reach instant t on both (the twin's rows
    after a non-finite state are left out) of ``|c_twin(t) - c_plant(t)|``, m.
    """
    T = max(len(c) for c in plant.com)
    d = np.full((len(plant.com), T), np.nan)
    for k, (cp, ct) in enumerate(zip(plant.com, twin.com, strict=True)):
        n = min(len(cp), len(ct) - (1 if twin.diverged[k] else 0))
        d[k, :n] = np.linalg.norm(ct[:n] - cp[:n], axis=1)
    with np.errstate(all="ignore"):
        mean = np.array([np.nanmean(col) if np.isfinite(col).any() else np.nan for col in d.T])
    t = np.arange(T) * dt
    finite = np.isfinite(mean)

    def first_over(level: float) -> float | None:
        over = np.flatnonzero(finite & (mean > level))
        return float(t[over[0]]) if over.size else None

    at = {}
    for s in (1.0, 5.0, 10.0, 20.0):
        i = round(s / dt)
        at[f"{s:g}s"] = float(mean[i]) if i < T and finite[i] else None
    return {
        "commands": "the policy's commands on the plant, replayed on the twin from the same starts",
        "dt_s": float(dt),
        "t_s": [float(x) for x in t],
        "com_divergence_m": [float(x) if np.isfinite(x) else None for x in mean],
        "mean_m": float(np.nanmean(mean)) if finite.any() else None,
        "final_m": float(mean[finite][-1]) if finite.any() else None,
        "at": at,
        "time_to_0.1m_s": first_over(0.1),
        "time_to_0.5m_s": first_over(0.5),
    }


def transfer_ratios(twin: dict[str, Any], plant: dict[str, Any], random_plant: dict[str, Any]
                    ) -> dict[str, float | None]:
    """The ratios a transfer is judged by, from :meth:`EpisodeSet.summary` blocks: the policy's
    mean progress on the plant over its progress on the twin, and over a random policy's on the
    plant (``None`` where the denominator is not positive); and the standard error of the first,
    ``plant_over_twin_stderr``, from the spread of the episodes (``None`` with fewer than two).

    The standard error is the delta method's for a ratio of two independent means,
    ``r sqrt((s_p / m_p)^2 + (s_t / m_t)^2)`` with ``s`` the standard error of each mean: a twin
    and a plant episode from the same reset seed share only their start (a roll is chaotic), so
    they are taken as independent. Ten episodes of the robot's rolls (spread 0.4-0.9 m per
    episode) leave a ratio of about 1 uncertain by 0.1-0.3: one policy's ratio tells a twin that
    predicts the plant from one that does not only when it is far from 1."""
    ratio = _ratio(plant["progress_m"], twin["progress_m"])
    return {"plant_over_twin": ratio,
            "plant_over_twin_stderr": _ratio_stderr(ratio, plant, twin),
            "plant_over_random": _ratio(plant["progress_m"], random_plant["progress_m"])}


#: Standard errors a plant/twin ratio must lie under a line to be called under it (:func:`against_line`).
CLEAR_Z = 2.0


def against_line(ratio: float | None, stderr: float | None, line: float = 0.9, z: float = CLEAR_Z) -> str | None:
    """A plant/twin ratio read against ``line`` with its standard error: ``"met"`` (at or above
    it), ``"under"`` (under it by more than ``z`` standard errors: the twin over-predicts the plant
    beyond the episodes' noise), ``"within noise"`` (under it, but by less: the episodes cannot tell
    it from a ratio at the line; also without a standard error) or ``None`` (no ratio: the twin
    made no progress). Ten episodes of rolls leave a ratio of 1 uncertain by 0.1-0.2, so a policy
    the twin predicts falls under 0.9 one time in five or six; this says which misses are real."""
    if ratio is None:
        return None
    if ratio >= line:
        return "met"
    return "under" if stderr is not None and ratio + z * stderr < line else "within noise"


def _ratio_stderr(ratio: float | None, num: dict[str, Any], den: dict[str, Any]) -> float | None:
    a, b = (np.asarray(x.get("progress_per_episode_m", []), dtype=float) for x in (num, den))
    if ratio is None or len(a) < 2 or len(b) < 2 or a.mean() == 0:
        return None
    rel = (a.std(ddof=1) / np.sqrt(len(a)) / a.mean()) ** 2 + (b.std(ddof=1) / np.sqrt(len(b)) / b.mean()) ** 2
    return float(abs(ratio) * np.sqrt(rel))


def _ratio(a: float, b: float) -> float | None:
    return float(a / b) if b > 0 and np.isfinite(a / b) else None


def write_mp4(path: str, frames: list[np.ndarray], fps: float) -> None:
    """Write (H, W, 3) uint8 frames as an H.264 MP4, atomically (temporary file, then rename)."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise ValueError("--video needs the imageio-ffmpeg package (pip install imageio-ffmpeg)") from None
    if not frames:
        raise ValueError("no frames to write")
    h, w = frames[0].shape[:2]
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".mp4", dir=folder)
    os.close(fd)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would hide the video from other users
        writer = imageio_ffmpeg.write_frames(tmp, (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                             macro_block_size=1, quality=7, output_params=["-y"])
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f, dtype=np.uint8))
        writer.close()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def measure_gap(policy: LoadedPolicy | str | os.PathLike, identified: str | None, episodes: int,
                seed: int = 0, episode_steps: int | None = None, video_dir: str | None = None,
                progress: bool = True, threads: int = 1,
                backend_kwargs: dict[str, Any] | None = None,
                random_plant: dict[str, Any] | None = None, video_every: int = VIDEO_EVERY,
                actions: str = ACTIONS[0]) -> dict[str, Any]:
    """The gap report (see the module docstring) as a JSON-ready dict.

    Args:
        policy: a policy file written by ``tensegrity train`` or a loaded one.
        identified: the twin's identified-model JSON (``None``: the shipped robot model); the plant
            is the MJCF it was fitted against.
        episodes: K episodes on each, reset seeds ``seed .. seed + K - 1``.
        episode_steps: time limit (``None``: the one the policy was trained with).
        video_dir: write ``twin.mp4``, ``plant.mp4`` and ``random_plant.mp4`` of episode ``seed``, and
            ``twin_plant.mp4``: the twin (left) beside the plant (right), frame by frame.
        video_every: one video frame every this many control steps (played at :data:`VIDEO_FPS`).
        threads: torch threads while the twin runs.
        random_plant: the ``random_plant`` block of an earlier report with the same plant, seeds,
            ``seed`` and episode length, reused instead of running the random policy again (with
            ``video_dir`` it runs again: its video is drawn as it runs).
        actions: ``"sampled"`` (the policy's own action noise, the same draws on twin and plant) or
            ``"mean"`` (:func:`policy_act`).
    """
    import tensegrity_gym  # noqa: F401  (registers the env)

    if int(episodes) != episodes or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes}")
    if int(video_every) != video_every or video_every < 1:
        raise ValueError(f"--video-every must be an integer >= 1, got {video_every}")
    if episode_steps is not None and (int(episode_steps) != episode_steps or episode_steps < 1):
        raise ValueError(f"episode steps must be an integer >= 1, got {episode_steps}")
    if identified is not None and not os.path.isfile(identified):
        raise ValueError(f"'{identified}' does not exist or is not a file")
    check_actions(actions)
    pol = policy if isinstance(policy, LoadedPolicy) else load_policy(policy)
    steps = int(episode_steps or pol.episode_steps)
    env_kwargs = pol.env_kwargs
    seeds = [int(seed) + k for k in range(int(episodes))]
    K = len(seeds)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=(4 if random_plant is None or video_dir is not None else 3) * K * steps, unit="step", desc="gap", dynamic_ncols=True, file=sys.stderr)
    try:
        with torch_threads(threads):
            mjcf = plant_mjcf(identified, (backend_kwargs or {}).get("mjcf"))
            n_twin, per_env = twin_layout(pol, K)
            video = video_dir is not None
            # with videos, the first episode of each run is drawn as it runs (the same episode)
            kw = {**env_kwargs, "width": VIDEO_SIZE, "height": VIDEO_SIZE} if video else env_kwargs
            twin = _twin_venv(identified, n_twin, steps, kw, backend_kwargs, render=video, per_env=per_env)
            plant = _plant_venv(mjcf, K, steps, kw, render=video)
            draw: dict[str, Any] = {}
            if video:
                draw = {"twin": {"render": lambda: twin.render_sub_env(0), "every": int(video_every)},
                        "plant": {"render": plant.envs[0].render, "every": int(video_every)}}
            try:
                for v in (twin, plant):
                    pol.check_env(v.single_observation_space, v.single_action_space)
                dt = float(twin.dt)  # type: ignore[attr-defined]
                A = int(twin.single_action_space.shape[0])  # type: ignore[index]
                on_twin = run_episodes(twin, policy_act(pol, actions, seeds, twin.num_envs), seeds, bar=bar,
                                       **draw.get("twin", {}))
                on_plant = run_episodes(plant, policy_act(pol, actions, seeds, plant.num_envs), seeds, bar=bar,
                                        **draw.get("plant", {}))
                on_random = (None if random_plant is not None and not video else
                             run_episodes(plant, _random_act(A, seed), seeds, bar=bar, **draw.get("plant", {})))
            finally:
                twin.close()
                plant.close()
            # open loop: the plant's command sequences on the twin, every recorded step
            T = int(on_plant.lengths.max())
            seq = np.full((K, T, A), np.nan)
            for k, a in enumerate(on_plant.actions):
                seq[k, : len(a)] = a
            replay_env = _twin_venv(identified, n_twin, None, {**env_kwargs, "terminate_when_unhealthy": False},
                                    backend_kwargs, per_env=per_env)
            try:
                replay = run_episodes(replay_env, pol.act, seeds, actions=seq, bar=bar)
            finally:
                replay_env.close()
            open_loop = open_loop_divergence(on_plant, replay, dt)
            videos = {}
            if video_dir is not None:
                assert on_random is not None
                videos = _write_videos(video_dir, {"twin": on_twin.frames, "plant": on_plant.frames,
                                                   "random_plant": on_random.frames})
        if bar is not None:  # episodes that ended early leave part of the estimate unused
            bar.update(bar.total - bar.n)
    finally:
        if bar is not None:
            bar.close()
    t, p = on_twin.summary(), on_plant.summary()
    r = on_random.summary() if on_random is not None else random_plant
    out: dict[str, Any] = {
        "twin": t,
        "plant": p,
        "random_plant": r,
        "open_loop": open_loop,
        "transfer": transfer_ratios(t, p, r),
        "twin_diverged_episodes": int(on_twin.diverged.sum()),
        "policy": {k: pol.meta.get(k) for k in ("algo", "trained_on", "identified", "timesteps", "seed")},
        "identified": None if identified is None else os.path.abspath(identified),
        "seeds": seeds,
        "episode_steps": steps,
        "actions": actions,
    }
    if videos:
        out["videos"] = videos
    return out


def _write_videos(folder: str, frames: dict[str, list[np.ndarray]]) -> dict[str, str]:
    """The first episode on the twin, on the plant and of the random policy on the plant (``frames``
    by those names), each as an MP4 in ``folder``, and the twin's beside the plant's
    (``twin_plant.mp4``)."""
    os.makedirs(folder, exist_ok=True)
    paths = {}
    for name in ("twin", "plant", "random_plant"):
        paths[name] = os.path.join(folder, f"{name}.mp4")
        write_mp4(paths[name], frames[name], fps=VIDEO_FPS)
    paths["twin_plant"] = os.path.join(folder, "twin_plant.mp4")
    write_mp4(paths["twin_plant"], side_by_side(frames["twin"], frames["plant"]), fps=VIDEO_FPS)
    return paths


def side_by_side(left: list[np.ndarray], right: list[np.ndarray], gap: int = 4) -> list[np.ndarray]:
    """Frames of two videos of the same size side by side (``gap`` white pixels between); the
    shorter one (an episode that ended early) holds its last frame."""
    n = max(len(left), len(right))
    out = []
    for k in range(n):
        a, b = left[min(k, len(left) - 1)], right[min(k, len(right) - 1)]
        sep = np.full((a.shape[0], gap, 3), 255, dtype=np.uint8)
        out.append(np.concatenate([a, sep, b], axis=1))
    return out

def measure_gaps(policies: list[str], identified: str | None, episodes: int, seed: int = 0,
                 episode_steps: int | None = None, video_dir: str | None = None, progress: bool = True,
                 threads: int = 1, log: Callable[[str], None] | None = None,
                 backend_kwargs: dict[str, Any] | None = None, video_every: int = VIDEO_EVERY,
                 actions: str = ACTIONS[0]) -> dict[str, Any]:
    """:func:`measure_gap` of several policies (e.g. the seeds of ``tensegrity train --seeds``) from
    the same reset seeds, and their mean and spread over policies.

    Returns ``{"policies": [path, ...], "reports": [the gap report of each], "over_policies": {...}}``
    where ``over_policies`` holds, for ``twin`` and ``plant`` progress and return and for the
    ``plant_over_twin`` ratio, the mean, standard deviation, minimum and maximum over the policies
    (:func:`tensegrity_gym.sweep.spread`), plus ``random_plant`` (run once per episode length and
    env settings: the same for every policy that shares them), how many policies roll at least
    ``0.5`` m on the plant and reach 90 % of their twin progress, how many are under 90 % by more
    than :data:`CLEAR_Z` standard errors (:func:`against_line`), and ``plant_over_twin_pooled``:
    the ratio of the mean plant to the mean twin progress over every policy's episodes together,
    with its standard error (as :func:`transfer_ratios`). ``video_dir``: the videos
    of policy ``i`` in ``video_dir/<i>``.
    """
    from tensegrity_gym.sweep import spread

    if not policies:
        raise ValueError("no policy given")
    reports: list[dict[str, Any]] = []
    randoms: dict[str, dict[str, Any]] = {}  # the random policy's block per episode length and env settings
    for i, path in enumerate(policies):
        pol = load_policy(path)
        key = f"{int(episode_steps or pol.episode_steps)} {sorted(pol.env_kwargs.items())!r}"
        vd = None if video_dir is None else (video_dir if len(policies) == 1 else os.path.join(video_dir, str(i)))
        rep = measure_gap(pol, identified, episodes, seed=seed, episode_steps=episode_steps, video_dir=vd,
                          progress=progress, threads=threads, random_plant=randoms.get(key),
                          backend_kwargs=backend_kwargs, video_every=video_every, actions=actions)
        randoms[key] = rep["random_plant"]
        reports.append(rep)
        if log is not None:
            log(f"{pol}: twin {rep['twin']['progress_m']:.3f} m, plant {rep['plant']['progress_m']:.3f} m")
    over: dict[str, Any] = {}
    for where in ("twin", "plant"):
        over[where] = {"progress_m": spread(r[where]["progress_m"] for r in reports),
                       "return": spread(r[where]["return"] for r in reports)}
    over["plant_over_twin"] = spread(r["transfer"]["plant_over_twin"] for r in reports)
    over["random_plant"] = {"progress_m": spread(r["random_plant"]["progress_m"] for r in reports)["mean"],
                            "return": spread(r["random_plant"]["return"] for r in reports)["mean"]}
    over["plant_progress_at_least_0.5m"] = sum(r["plant"]["progress_m"] >= 0.5 for r in reports)
    over["plant_over_twin_at_least_0.9"] = sum((r["transfer"]["plant_over_twin"] or 0.0) >= 0.9 for r in reports)
    # under the line beyond each policy's own noise (``against_line``): the twin exploited, not a draw
    over["plant_over_twin_under_0.9_beyond_noise"] = sum(
        against_line(r["transfer"]["plant_over_twin"], r["transfer"]["plant_over_twin_stderr"]) == "under"
        for r in reports)
    # every policy's episodes together: does the twin predict the plant over the policies?
    pooled = {w: {"progress_per_episode_m": [x for r in reports for x in r[w]["progress_per_episode_m"]]}
              for w in ("twin", "plant")}
    for b in pooled.values():
        b["progress_m"] = float(np.mean(b["progress_per_episode_m"]))
    ratio = _ratio(pooled["plant"]["progress_m"], pooled["twin"]["progress_m"])
    over["plant_over_twin_pooled"] = {"ratio": ratio, "stderr": _ratio_stderr(ratio, pooled["plant"], pooled["twin"])}
    return {"policies": [os.fspath(p) for p in policies], "reports": reports, "over_policies": over,
            "episodes": int(episodes), "seeds": reports[0]["seeds"], "actions": actions}
