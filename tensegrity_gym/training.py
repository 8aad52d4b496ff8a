"""Training a Stable-Baselines3 policy on the identified twin (or on the plant): ``tensegrity train``.

The twin is stepped natively batched: ``gym.make_vec("TensegrityIco-v0", num_envs=K,
vectorization_mode="vector_entry_point", backend="identified", model=F)`` seen by SB3 through
:class:`~tensegrity_gym.envs.sb3.SB3VecEnvAdapter`, so one engine call steps all K envs and MuJoCo
is never stepped. ``plant=True`` trains the same algorithm with the same hyperparameters on the
MuJoCo plant the model was identified from (SB3's ``SubprocVecEnv``, one process per env): the
upper bound to compare with.

Observations are normalised by ``VecNormalize`` (running mean and variance; rewards are scaled for
PPO only). The normalisation statistics travel inside the policy file, so evaluation
(:func:`load_policy`) feeds the policy exactly what it was trained on.

The policy file is SB3's zip with one more entry, ``tensegrity.json`` (:data:`POLICY_FORMAT`): the
algorithm, the env id and its keyword arguments, the observation and action shapes, the
normalisation statistics, where it was trained and with what. SB3's ``PPO.load`` reads the file as
usual (it ignores the extra entry).

Domain randomization and budget
-------------------------------
By default the twin is randomized (``randomize="auto"``, :mod:`tensegrity_gym.randomize`: every
env draws its own contact, spring, rod, motor parameters, latency and sensor noise at each reset,
widths from the identified model's own uncertainty and unexplained residual), and ``tensegrity
train`` runs :data:`DEFAULT_TIMESTEPS` steps. Why: the policy's search finds where the nominal twin
is wrong (contact while rolling over an edge) and rolls further on the twin than on the plant;
a policy that must roll on every draw relies less on the twin's own contact (measured per seed in
README, "Randomized twins, defaults that transfer": with ``ground_contact`` it doubled the plant
progress; with the exact ``pyramid_contact`` the nominal twin transfers as well, and ``auto`` helps
where the springs and rods are wrong). The randomization is recorded in the policy's metadata
(``randomization``).

Hyperparameters (:data:`PPO_HYPERPARAMETERS`, :data:`SAC_HYPERPARAMETERS`) and why
-----------------------------------------------------------------------------------
PPO is the default. Its settings are SB3's defaults (learning rate 3e-4, 10 epochs, clip 0.2,
GAE 0.95, no entropy bonus, ``gamma`` 0.99) except for the size of an update: the rollout of one
update is 4,096 transitions (:data:`DEFAULT_ROLLOUT`: 64 steps x 64 twins, or 512 x 8 plants)
whatever the number of envs, so ``envs`` only decides how many run in parallel, not what the
algorithm does (twin and plant runs do the same updates), and mini-batches are 1,024 with Adam's
fused kernel (``policy_kwargs={"optimizer_kwargs": {"fused": True}}``: the same update rule in one
kernel call). Why the rollout: with a budget of 100k steps SB3's 2,048 x 8 = 16,384 transitions per
update leave 6 updates; 4,096 give 25, and measured on the twin (seed 0, the shipped model, 10
plant episodes) the policy then rolls 0.60 m per 1000-step episode on the plant instead of 0.44 m
(README, "Training on the twin", for the figures over seeds). Why the mini-batches: an update of
4,096 transitions in mini-batches of 128 is 320 optimizer steps of a 64 x 64 MLP, whose cost is
SB3's and torch's fixed cost per call (Python, autograd, the optimizer), not arithmetic:
mini-batches of 1,024 (40 steps) make an update 3.6-4x cheaper and the fused Adam 10-16 % more
(``benchmarks/bench_train.py --updates``); the policies it trains on the shipped model at the
300k default roll 1.18-2.15 m per episode on the plant over five seeds, against 0.61-1.24 m for
runs with mini-batches of 128 on the contact law without torques (seed 0 on that law with
mini-batches of 1,024: 1.52 m) (README, "Randomized twins, defaults that transfer"). ``gamma`` 0.99 looks 100 control steps (2 s) ahead, about the time the
0.3 m/s motors take to reel a cable through most of its range and tip the robot onto the next
face; forward speed is a dense reward, so longer horizons are not needed. The initial action
noise stays SB3's (std 1, ``log_std_init`` 0): a quieter start (std 0.37) rolled further on the
twin (0.83 m) but only 0.26 m on the plant, a policy fitted to the twin's own contact rather than
to rolling. SAC (``algo="sac"``) keeps SB3's defaults (one gradient step per
transition, batch 256), with a replay buffer no larger than the run and observation-only
normalisation; it is slower per step on a CPU and is not tuned for this robot.
"""

from __future__ import annotations

import io
import json
import os
import signal
import sys
import time
import zipfile
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from tensegrity_gym.backends.twin_physics import torch_threads

__all__ = [
    "ALGORITHMS",
    "DEFAULT_RANDOMIZE",
    "DEFAULT_ROLLOUT",
    "DEFAULT_TIMESTEPS",
    "ENV_ID",
    "POLICY_FORMAT",
    "PPO_HYPERPARAMETERS",
    "SAC_HYPERPARAMETERS",
    "LoadedPolicy",
    "PolicyFileError",
    "TrainConfig",
    "TrainResult",
    "checkpoint_path",
    "load_policy",
    "plant_mjcf",
    "resolve_randomize",
    "snapshot_path",
    "torch_threads",
    "train",
]

ENV_ID = "TensegrityIco-v0"
POLICY_FORMAT = "tensegrity-policy/1"
POLICY_ENTRY = "tensegrity.json"
ALGORITHMS = ("ppo", "sac")
#: Transitions collected per PPO update (64 steps x 64 twins, 512 x 8 plants), whatever ``envs`` is.
DEFAULT_ROLLOUT = 4096
DEFAULT_ENVS = {("ppo", False): 64, ("ppo", True): 8, ("sac", False): 8, ("sac", True): 4}
PPO_HYPERPARAMETERS: dict[str, Any] = {
    "learning_rate": 3e-4, "batch_size": 1024, "n_epochs": 10, "gamma": 0.99, "gae_lambda": 0.95,
    "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
    "policy_kwargs": {"optimizer_kwargs": {"fused": True}},
}
SAC_HYPERPARAMETERS: dict[str, Any] = {
    "learning_rate": 3e-4, "batch_size": 256, "tau": 0.005, "gamma": 0.99, "train_freq": 1,
    "gradient_steps": -1, "learning_starts": 5_000, "buffer_size": 1_000_000,
}
#: ``tensegrity train``'s default budget and randomization (README, "Training on the twin")
DEFAULT_TIMESTEPS = 300_000
DEFAULT_RANDOMIZE = "auto"
#: the second word of the seed of a policy's action noise in evaluation (:meth:`LoadedPolicy.sampling`):
#: its draws apart from any other stream seeded with the same reset seed
ACTION_NOISE_STREAM = 0x5A3D
#: the twin's integration step when training: the coarsest stable one (:func:`resolve_physics_dt`)
DEFAULT_PHYSICS_DT = "auto"
#: ``VecNormalize`` settings (SB3's defaults); rewards are normalised for PPO only.
NORMALIZE = {"clip_obs": 10.0, "epsilon": 1e-8}


class PolicyFileError(ValueError):
    """A policy file that is not a tensegrity policy, or not one for this env."""


# ---------------------------------------------------------------------- configuration
@dataclass
class TrainConfig:
    """What :func:`train` does.

    Args:
        timesteps: environment steps to train for (>= 1; PPO finishes its last update, so a few
            more may be taken).
        seed: seeds SB3 (torch, numpy), the envs (env ``i`` resets with ``seed + i``) and the
            action sampling: the same config gives the same policy.
        algo: ``"ppo"`` (default) or ``"sac"``.
        identified: identified-model JSON of the twin (``None``: the shipped robot model); with
            ``plant=True`` it only names the plant (the MJCF it was fitted against).
        plant: train on the MuJoCo plant instead (SubprocVecEnv).
        envs: envs stepped in parallel (``None``: 64 twins or 8 plants for PPO, 8 or 4 for SAC; the
            batched twin's steps/s grow with the batch, benchmarks/README.md).
        rollout: PPO transitions per update over all envs (rounded up to a multiple of ``envs``; a
            run of fewer ``timesteps`` makes one rollout of that many).
        episode_steps: time limit of an episode in control steps (the registration's 1000).
        threads: torch intra-op threads while training (restored afterwards).
        tensorboard: folder for TensorBoard logs (needs the ``tensorboard`` package).
        env_kwargs: keyword arguments of the env (``frame_skip``, reward weights, ...).
        hyperparameters: overrides of :data:`PPO_HYPERPARAMETERS` / :data:`SAC_HYPERPARAMETERS`.
        backend_kwargs: keyword arguments of the twin's backend (``dtype``, ``effects``, ``mjcf``).
        randomize: domain randomization of the twin (:mod:`tensegrity_gym.randomize`): ``"auto"``
            (from the identified model's uncertainty and unexplained residual), ``"none"``/``None``,
            a FILE path, a mapping or a :class:`~tensegrity_gym.randomize.Randomization`; recorded
            in the policy's metadata. Ignored with ``plant=True``.
        physics_dt: the twin's integration step: ``"auto"`` (default: the coarsest whole multiple
            of the model's ``dt`` dividing the control period at which the model is stable with a
            factor of safety of 2.5, :func:`tensegrity_gym.backends.step_size.stable_physics_dt`),
            ``None`` (the model's own ``dt``, the plant's step) or seconds; recorded in the
            policy's metadata. Ignored with ``plant=True``.
        init_policy: a policy file of :func:`train` to continue from (its network weights and its
            observation normalisation; the algorithm's other settings are this config's), e.g. on
            a refitted twin (:mod:`tensegrity_gym.improve`).
        snapshots: also keep the policy after every update as :func:`snapshot_path` ``(out, N)``
            (``P.step<N>.zip``, N the steps trained so far): learning curves, e.g. the plant steps
            direct training needs to reach a given progress (benchmarks/bench_train.py).
    """

    timesteps: int
    seed: int = 0
    algo: str = "ppo"
    identified: str | None = None
    plant: bool = False
    envs: int | None = None
    rollout: int = DEFAULT_ROLLOUT
    episode_steps: int = 1000
    threads: int = 1
    tensorboard: str | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    hyperparameters: dict[str, Any] = field(default_factory=dict)
    backend_kwargs: dict[str, Any] = field(default_factory=dict)
    snapshots: bool = False
    randomize: Any = DEFAULT_RANDOMIZE
    init_policy: str | None = None
    physics_dt: float | str | None = DEFAULT_PHYSICS_DT

    def validate(self) -> None:
        """ValueError with one line for every setting out of range."""
        if self.algo not in ALGORITHMS:
            raise ValueError(f"unknown algorithm '{self.algo}' (choose from {', '.join(ALGORITHMS)})")
        for name in ("timesteps", "rollout", "episode_steps", "threads"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v}")
        if self.envs is not None and (int(self.envs) != self.envs or self.envs < 1):
            raise ValueError(f"envs must be an integer >= 1, got {self.envs}")
        if self.identified is not None and not os.path.isfile(self.identified):
            raise ValueError(f"'{self.identified}' does not exist or is not a file")
        if self.init_policy is not None and not os.path.isfile(self.init_policy):
            raise ValueError(f"'{self.init_policy}' does not exist or is not a file")
        h = self.physics_dt
        if not (h is None or h == "auto" or (isinstance(h, (int, float)) and not isinstance(h, bool)
                                             and np.isfinite(h) and h > 0)):
            raise ValueError(f"physics_dt must be 'auto', None or a positive number of seconds, got {h!r}")
        if "physics_dt" in (self.backend_kwargs or {}):
            raise ValueError("give the twin's step as physics_dt, not in backend_kwargs")

    @property
    def n_envs(self) -> int:
        return int(self.envs) if self.envs is not None else DEFAULT_ENVS[(self.algo, bool(self.plant))]

    def algo_kwargs(self) -> dict[str, Any]:
        """The algorithm's keyword arguments: the defaults above, the rollout, the overrides."""
        if self.algo == "ppo":
            hp = dict(PPO_HYPERPARAMETERS)
            # ceil: at least the rollout; a run shorter than one rollout is one rollout of its length
            hp["n_steps"] = -(-min(int(self.rollout), int(self.timesteps)) // self.n_envs)
            hp.update(self.hyperparameters)
            hp["batch_size"] = min(int(hp["batch_size"]), hp["n_steps"] * self.n_envs)
        else:
            hp = dict(SAC_HYPERPARAMETERS)
            hp["buffer_size"] = min(int(hp["buffer_size"]), int(self.timesteps))
            hp["learning_starts"] = min(int(hp["learning_starts"]), int(self.timesteps) // 10)
            hp.update(self.hyperparameters)
        return hp


@dataclass
class TrainResult:
    """What a training run did: where the policy went, how long, and the last episodes' figures;
    ``model`` (the SB3 algorithm) and ``vecnormalize`` (its observation normaliser) in memory."""

    path: str
    timesteps: int
    wall_s: float
    episodes: int
    mean_return: float | None
    mean_progress_m: float | None
    env_steps_per_s: float
    config: dict[str, Any]
    model: Any = field(default=None, repr=False)
    vecnormalize: Any = field(default=None, repr=False)
    #: the learning curve: one row per finished episode, in the order they ended, with
    #: ``timesteps`` (steps trained when it ended), ``wall_s`` (since training started),
    #: ``return``, ``progress_m`` (forward distance of the centre of mass) and ``length`` (steps)
    episode_log: list[dict[str, float]] = field(default_factory=list, repr=False)
    #: the learning curve per rollout (the envs' episodes end together, so finished episodes alone
    #: come in bursts): one row per rollout with ``timesteps`` (at its end), ``wall_s``,
    #: ``reward_per_step`` (the env's reward, before normalisation) and ``velocity_m_s`` (mean
    #: forward velocity of the centre of mass over every env and step of the rollout)
    rollout_log: list[dict[str, float]] = field(default_factory=list, repr=False)
    #: training episodes that ended because the physics diverged (``termination_reason`` ``"non-finite
    #: state"``): a twin that is not stable at its step (a fit the data do not determine, or too
    #: coarse a ``physics_dt``); :func:`divergence_warning` words it
    diverged_episodes: int = 0


def divergence_warning(diverged: int, episodes: int, plant: bool = False, seed: int | None = None) -> str | None:
    """One line saying that the physics diverged in ``diverged`` of ``episodes`` training episodes
    (of seed ``seed`` in a sweep; ``None`` when it never did): the policy then learned from a twin
    that blows up (:attr:`TrainResult.diverged_episodes`)."""
    if diverged == 0:
        return None
    of_seed = "" if seed is None else f" of seed {seed}"
    return (f"the {'plant' if plant else 'twin'}'s physics diverged (a non-finite state) in {diverged} of {episodes} "
            f"training episodes{of_seed}: the model is not stable at its step (see the fit's warnings; a coarser "
            "--physics-dt makes it worse), and a policy trained on it may not transfer")


# ---------------------------------------------------------------------- helpers
def plant_mjcf(identified: str | None, mjcf: str | None = None) -> str:
    """MJCF text of the plant an identified model belongs to (its source MJCF, as the twin resolves
    it; ``None``: the robot preset); ``mjcf`` (a path): that MJCF, a lab's own robot."""
    from tensegrity_gym.backends.identified_backend import resolve_source_mjcf
    from tensegrity_gym.backends.mujoco_backend import default_robot_xml

    if mjcf is not None:
        from identified.mjcf import read_mjcf_text

        if identified is not None:
            from identified.model import load_model

            resolve_source_mjcf(load_model(identified), mjcf)  # the twin's topology must be the MJCF's
        return read_mjcf_text(mjcf)
    if identified is None:
        return default_robot_xml()
    from identified.model import load_model

    text, _ = resolve_source_mjcf(load_model(identified))
    return text


def checkpoint_path(out: str) -> str:
    """Where training keeps its last complete checkpoint of the policy ``out`` (``P.ckpt.zip``)."""
    return out.removesuffix(".zip") + ".ckpt.zip"


def snapshot_path(out: str, steps: int) -> str:
    """Where ``snapshots=True`` keeps the policy ``out`` after ``steps`` steps (``P.step<N>.zip``)."""
    return f"{out.removesuffix('.zip')}.step{int(steps)}.zip"


def _algo_class(algo: str) -> type:
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def resolve_randomize(cfg: TrainConfig) -> Any:
    """The :class:`~tensegrity_gym.randomize.Randomization` a twin run draws from (``None``: none)."""
    from identified.model import load_model
    from tensegrity_gym.backends.identified_backend import default_model_path
    from tensegrity_gym.envs.tensegrity_ico_v0 import FRAME_SKIP
    from tensegrity_gym.randomize import resolve_randomization

    if cfg.plant or cfg.randomize is None or (isinstance(cfg.randomize, str) and cfg.randomize == "none"):
        return None
    model = load_model(cfg.identified if cfg.identified is not None else default_model_path())
    return resolve_randomization(cfg.randomize, model, int(cfg.env_kwargs.get("frame_skip", FRAME_SKIP)))


def resolve_physics_dt(cfg: TrainConfig) -> tuple[float | None, str]:
    """The twin's integration step for ``cfg``, s (``None`` with ``plant=True``), and a line saying
    why: for ``"auto"`` the coarsest stable step
    (:func:`~tensegrity_gym.backends.step_size.stable_physics_dt`, a few seconds), else the
    config's own value, checked against the model (ValueError naming ``physics_dt``)."""
    from identified.model import load_model
    from tensegrity_gym.backends.identified_backend import coarsening, default_model_path
    from tensegrity_gym.backends.step_size import stable_physics_dt
    from tensegrity_gym.envs.tensegrity_ico_v0 import FRAME_SKIP

    if cfg.plant:
        return None, "the plant steps at its own dt"
    period = int(cfg.env_kwargs.get("frame_skip", FRAME_SKIP))
    bk = cfg.backend_kwargs or {}
    if cfg.physics_dt == "auto":
        choice = stable_physics_dt(cfg.identified, period, mjcf=bk.get("mjcf"), effects=bk.get("effects", ()))
        return choice.step, f"the twin integrates at {choice.describe()} (auto)"
    dt = float(load_model(cfg.identified if cfg.identified is not None else default_model_path()).dt)
    if cfg.physics_dt is None:
        return dt, f"the twin integrates at the model's own {1e3 * dt:g} ms"
    k = coarsening(cfg.physics_dt, dt)
    if period % k:
        raise ValueError(f"{k} physics steps of the model do not divide the control period of {period} steps "
                         f"(physics_dt={float(cfg.physics_dt):g} s)")
    return float(cfg.physics_dt), f"the twin integrates at {1e3 * float(cfg.physics_dt):g} ms (given)"


def _make_twin_venv(cfg: TrainConfig, randomize: Any = None, physics_dt: float | None = None) -> Any:
    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    backend_kwargs = dict(cfg.backend_kwargs or {})
    if physics_dt is not None:
        backend_kwargs["physics_dt"] = physics_dt
    venv = gym.make_vec(ENV_ID, num_envs=cfg.n_envs, vectorization_mode="vector_entry_point",
                        backend="identified", model=cfg.identified, max_episode_steps=cfg.episode_steps,
                        backend_kwargs=backend_kwargs or None, randomize=randomize, **cfg.env_kwargs)
    return SB3VecEnvAdapter(venv)


def _plant_factory(mjcf: str, episode_steps: int, env_kwargs: dict[str, Any]) -> Callable[[], gym.Env]:
    def make() -> gym.Env:
        import tensegrity_gym  # noqa: F401  (registers the env in the worker)

        return gym.make(ENV_ID, model=mjcf, max_episode_steps=episode_steps, **env_kwargs)

    return make


def _make_plant_venv(cfg: TrainConfig, mjcf: str) -> Any:
    from stable_baselines3.common.vec_env import SubprocVecEnv

    make = _plant_factory(mjcf, cfg.episode_steps, cfg.env_kwargs)
    return SubprocVecEnv([make for _ in range(cfg.n_envs)])


# ---------------------------------------------------------------------- the policy file
def _normalizer_stats(vecnorm: Any) -> dict[str, Any]:
    rms = vecnorm.obs_rms
    return {"mean": rms.mean.tolist(), "var": rms.var.tolist(), "count": float(rms.count),
            "clip_obs": float(vecnorm.clip_obs), "epsilon": float(vecnorm.epsilon)}


def _policy_bytes(model: Any, meta: dict[str, Any]) -> bytes:
    buf = io.BytesIO()
    model.save(buf)
    with zipfile.ZipFile(buf, mode="a") as zf:
        zf.writestr(POLICY_ENTRY, json.dumps(meta, indent=1))
    return buf.getvalue()


def _write_policy(path: str, model: Any, meta: dict[str, Any]) -> None:
    from identified.dataset import atomic_write

    data = _policy_bytes(model, meta)
    atomic_write(path, lambda fh: fh.write(data), binary=True)


@dataclass
class LoadedPolicy:
    """A trained policy with its observation normalisation: :meth:`act` maps raw env observations
    to actions, as during training (deterministic: the mean of the action distribution)."""

    model: Any
    meta: dict[str, Any]
    obs_mean: np.ndarray
    obs_var: np.ndarray
    clip_obs: float
    epsilon: float

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The env's keyword arguments the policy was trained with."""
        return dict(self.meta.get("env_kwargs", {}))

    @property
    def episode_steps(self) -> int:
        return int(self.meta.get("episode_steps", 1000))

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """(..., n_obs) raw observations -> what the network saw during training (VecNormalize's)."""
        o = (np.asarray(obs, dtype=np.float64) - self.obs_mean) / np.sqrt(self.obs_var + self.epsilon)
        return np.clip(o, -self.clip_obs, self.clip_obs).astype(np.float32)

    def act(self, obs: np.ndarray, noise: np.ndarray | None = None) -> np.ndarray:
        """(N, A) actions in [-1, 1] for (N, n_obs) raw observations ((A,) for (n_obs,)): the mean of
        the policy's action distribution, or with ``noise`` (standard normal draws, the actions'
        shape) a draw from it, as the algorithm drew its actions while it trained (:meth:`_draw`)."""
        if noise is None:
            action, _ = self.model.predict(self.normalize(obs), deterministic=True)
        else:
            action = self._draw(obs, noise)
        return np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)

    def _draw(self, obs: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """The actions ``noise`` draws from the policy's distribution at raw observations ``obs``:
        PPO's Gaussian ``mean + std * noise``, SAC's squashed one ``tanh(mean + std * noise)``."""
        import torch

        obs_t, vectorized = self.model.policy.obs_to_tensor(self.normalize(obs))
        eps = torch.as_tensor(np.asarray(noise, dtype=np.float32).reshape(obs_t.shape[0], -1))
        with torch.no_grad():
            if hasattr(self.model, "actor"):
                mean, log_std, _ = self.model.actor.get_action_dist_params(obs_t)
                action = torch.tanh(mean + log_std.exp() * eps)
            else:
                dist = self.model.policy.get_distribution(obs_t).distribution
                action = dist.mean + dist.stddev * eps
        out = action.cpu().numpy()
        return out if vectorized else out[0]

    def sampling(self, seeds: Sequence[int]) -> Callable[[np.ndarray], np.ndarray]:
        """:meth:`act` with the policy's own action noise, for envs reset with ``seeds``: env ``k``'s
        draws come from a generator of its own seeded with ``seeds[k]``, so the same reset seed gives
        the same draws on the twin and on the plant, whatever the number of envs beside it."""
        rngs = [np.random.default_rng([int(s), ACTION_NOISE_STREAM]) for s in seeds]
        A = int(self.meta["action_shape"][0])

        def act(obs: np.ndarray) -> np.ndarray:
            n = int(np.prod(np.shape(obs)[:-1]))
            if n > len(rngs):
                raise ValueError(f"{n} observations for {len(rngs)} seeded envs")
            return self.act(obs, np.stack([r.standard_normal(A) for r in rngs[:n]]))

        return act

    def check_env(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        """PolicyFileError unless the env's spaces are those the policy was trained on."""
        want_o, want_a = tuple(self.meta["observation_shape"]), tuple(self.meta["action_shape"])
        if tuple(observation_space.shape) != want_o or tuple(action_space.shape) != want_a:  # type: ignore[arg-type]
            raise PolicyFileError(f"the policy was trained on observations {want_o} and actions {want_a}, "
                                  f"this env has {tuple(observation_space.shape)} and "  # type: ignore[arg-type]
                                  f"{tuple(action_space.shape)}")  # type: ignore[arg-type]


def load_policy(path: str | os.PathLike) -> LoadedPolicy:
    """Load a policy written by :func:`train` (PolicyFileError for anything else)."""
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise PolicyFileError(f"'{p}' does not exist or is not a file")
    try:
        with zipfile.ZipFile(p) as zf:
            names = zf.namelist()
            if POLICY_ENTRY not in names:
                raise PolicyFileError(f"'{p}' is not a tensegrity policy (no {POLICY_ENTRY} in it; write one "
                                      "with 'tensegrity train')")
            meta = json.loads(zf.read(POLICY_ENTRY))
    except zipfile.BadZipFile:
        raise PolicyFileError(f"'{p}' is not a policy file (not a zip archive)") from None
    if meta.get("format") != POLICY_FORMAT:
        raise PolicyFileError(f"'{p}' has policy format {meta.get('format')!r}, expected {POLICY_FORMAT!r}")
    if meta.get("algo") not in ALGORITHMS:
        raise PolicyFileError(f"'{p}' holds an unknown algorithm {meta.get('algo')!r}")
    model = _algo_class(meta["algo"]).load(p, device="cpu")
    if tuple(model.observation_space.shape) != tuple(meta["observation_shape"]):
        raise PolicyFileError(f"'{p}': the network's observation shape {model.observation_space.shape} is not "
                              f"the recorded {tuple(meta['observation_shape'])}")
    norm = meta["normalize"]
    return LoadedPolicy(model=model, meta=meta, obs_mean=np.asarray(norm["mean"], dtype=np.float64),
                        obs_var=np.asarray(norm["var"], dtype=np.float64), clip_obs=float(norm["clip_obs"]),
                        epsilon=float(norm["epsilon"]))


# ---------------------------------------------------------------------- progress and checkpoints
def _make_callback(cfg: TrainConfig, dt: float, out: str, meta: Callable[[], dict[str, Any]],
                   progress: bool) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class _Progress(BaseCallback):
        """Progress bar (mean return and forward progress of the last 20 episodes), per-episode
        forward progress, and a checkpoint of the policy after every update."""

        def __init__(self) -> None:
            super().__init__()
            self.returns: deque[float] = deque(maxlen=20)
            self.progress: deque[float] = deque(maxlen=20)
            self.episodes = 0
            self.diverged = 0
            self.log: list[dict[str, float]] = []
            self.rollouts: list[dict[str, float]] = []
            self._roll = [0.0, 0.0, 0]  # forward distance, reward, env steps of the current rollout
            self._t0 = time.perf_counter()
            self.last_checkpoint: int | None = None
            self._dist = np.zeros(cfg.n_envs)
            self._bar: Any = None

        def _on_training_start(self) -> None:
            self._t0 = time.perf_counter()
            if progress:
                from tqdm.auto import tqdm

                where = "plant" if cfg.plant else "twin"
                self._bar = tqdm(total=int(cfg.timesteps), unit="step", desc=f"train {cfg.algo} on {where}",
                                 dynamic_ncols=True, file=sys.stderr)

        def _on_step(self) -> bool:
            infos = self.locals["infos"]
            dones = self.locals["dones"]
            original = getattr(self.training_env, "get_original_reward", None)  # VecNormalize's raw reward
            self._roll[1] += float(np.sum(original() if original is not None else self.locals["rewards"]))
            self._roll[2] += len(infos)
            for i, info in enumerate(infos):
                self._dist[i] += float(info.get("x_velocity", 0.0)) * dt
                self._roll[0] += float(info.get("x_velocity", 0.0)) * dt
                if dones[i]:
                    ep = info.get("episode")
                    if ep is not None:
                        self.returns.append(float(ep["r"]))
                    self.progress.append(float(self._dist[i]))
                    self.log.append({"timesteps": int(self.num_timesteps),
                                     "wall_s": time.perf_counter() - self._t0,
                                     "return": float(ep["r"]) if ep is not None else float("nan"),
                                     "progress_m": float(self._dist[i]),
                                     "length": int(ep["l"]) if ep is not None else -1})
                    self._dist[i] = 0.0
                    self.episodes += 1
                    self.diverged += info.get("termination_reason") == "non-finite state"
            if self._bar is not None:
                self._bar.update(min(self.num_timesteps, int(cfg.timesteps)) - self._bar.n)
                if self.returns:
                    self._bar.set_postfix_str(f"return {np.mean(self.returns):.3g}, progress "
                                              f"{np.mean(self.progress):.3g} m, {self.episodes} episodes",
                                              refresh=False)
            return True

        def _on_rollout_end(self) -> None:
            dist, reward, n = self._roll
            if n:
                self.rollouts.append({"timesteps": int(self.num_timesteps), "wall_s": time.perf_counter() - self._t0,
                                      "reward_per_step": reward / n, "velocity_m_s": dist / (n * dt)})
            self._roll = [0.0, 0.0, 0]

        def _on_rollout_start(self) -> None:
            # after an update: the policy is complete, keep it (atomically) in case of an interrupt
            if self.num_timesteps > 0 and self.num_timesteps != self.last_checkpoint:
                _write_policy(checkpoint_path(out), self.model, meta())
                if cfg.snapshots:
                    _write_policy(snapshot_path(out, self.num_timesteps), self.model, meta())
                self.last_checkpoint = self.num_timesteps
            if self.progress:
                self.logger.record("rollout/progress_m", float(np.mean(self.progress)))

        def _on_training_end(self) -> None:
            if self._bar is not None:
                self._bar.close()

    return _Progress()


# ---------------------------------------------------------------------- training
def train(cfg: TrainConfig, out: str | os.PathLike, progress: bool = True) -> TrainResult:
    """Train a policy as ``cfg`` says and write it to ``out`` (atomically; see the module docstring).

    While training, the last complete policy (after each update) is kept in
    :func:`checkpoint_path` ``(out)``; it is removed when the run completes. On Ctrl-C the
    interrupt is re-raised after a line on stderr saying where that checkpoint is.
    """
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    import tensegrity_gym  # noqa: F401  (registers the env)

    cfg.validate()
    out = os.fspath(out)
    hp = cfg.algo_kwargs()
    if cfg.tensorboard is not None:
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise ValueError("--tensorboard needs the tensorboard package (pip install tensorboard)") from None

    randomization = resolve_randomize(cfg)
    physics_dt, _ = resolve_physics_dt(cfg)
    with torch_threads(cfg.threads):
        mjcf = None
        if cfg.plant:
            mjcf = plant_mjcf(cfg.identified, (cfg.backend_kwargs or {}).get("mjcf"))
            probe = gym.make(ENV_ID, model=mjcf, **cfg.env_kwargs)  # spaces and control period, here
            dt = float(probe.unwrapped.dt)  # type: ignore[attr-defined]
            spaces = (probe.observation_space, probe.action_space)
            probe.close()
            venv = _make_plant_venv(cfg, mjcf)
        else:
            venv = _make_twin_venv(cfg, randomization, physics_dt)
            dt = float(venv.venv.dt)
            spaces = (venv.observation_space, venv.action_space)
        base = venv
        try:
            venv = VecMonitor(venv)
            venv = VecNormalize(venv, norm_obs=True, norm_reward=cfg.algo == "ppo", gamma=hp["gamma"],
                                **NORMALIZE)
            model = _algo_class(cfg.algo)("MlpPolicy", venv, seed=cfg.seed, device="cpu", verbose=0,
                                          tensorboard_log=cfg.tensorboard, **hp)
            if cfg.tensorboard is None:
                # SB3's own logger would make an empty SB3-<date> folder in the temp dir at every
                # learn(); the run's records are the callback's (learning curve, checkpoints)
                model.set_logger(Logger(folder=None, output_formats=[]))
            if cfg.init_policy is not None:
                _continue_from(model, venv, cfg.init_policy, spaces)
            t0 = time.perf_counter()
            started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())

            def meta() -> dict[str, Any]:
                return {
                    "format": POLICY_FORMAT,
                    "algo": cfg.algo,
                    "env_id": ENV_ID,
                    "env_kwargs": dict(cfg.env_kwargs),
                    "episode_steps": int(cfg.episode_steps),
                    "observation_shape": list(spaces[0].shape),
                    "action_shape": list(spaces[1].shape),
                    "normalize": _normalizer_stats(venv),
                    "trained_on": "plant" if cfg.plant else "twin",
                    "identified": None if cfg.identified is None else os.path.abspath(cfg.identified),
                    "timesteps": int(model.num_timesteps),
                    "seed": int(cfg.seed),
                    "randomization": None if randomization is None else randomization.to_json(),
                    "physics_dt": physics_dt,
                    "continued_from": None if cfg.init_policy is None else os.path.abspath(cfg.init_policy),
                    "envs": cfg.n_envs,
                    "hyperparameters": {k: v for k, v in hp.items() if isinstance(v, (int, float, str, dict))},
                    "started": started,
                    "wall_s": time.perf_counter() - t0,
                }

            callback = _make_callback(cfg, dt, out, meta, progress)
            ckpt = checkpoint_path(out)
            try:
                model.learn(total_timesteps=int(cfg.timesteps), callback=callback,
                            tb_log_name=f"{cfg.algo}_{'plant' if cfg.plant else 'twin'}")
            except KeyboardInterrupt:
                if callback.last_checkpoint is not None:
                    print(f"tensegrity: training interrupted at step {model.num_timesteps}; the last complete "
                          f"checkpoint (step {callback.last_checkpoint}) is {ckpt}", file=sys.stderr)
                else:
                    print("tensegrity: training interrupted before its first update: no checkpoint",
                          file=sys.stderr)
                raise
            wall = time.perf_counter() - t0
            final = meta()
            final["wall_s"] = wall
            _write_policy(out, model, final)
            if os.path.exists(ckpt):
                os.unlink(ckpt)
        finally:
            # SubprocVecEnv workers must not outlive the run, even on an interrupt
            with _ignore_sigint():
                _close(venv, base)
    rets, prog = list(callback.returns), list(callback.progress)
    return TrainResult(
        path=out, timesteps=int(model.num_timesteps), wall_s=wall, episodes=callback.episodes,
        mean_return=float(np.mean(rets)) if rets else None,
        mean_progress_m=float(np.mean(prog)) if prog else None,
        env_steps_per_s=model.num_timesteps / wall if wall > 0 else float("nan"),
        config={"algo": cfg.algo, "plant": cfg.plant, "envs": cfg.n_envs, **hp},
        model=model, vecnormalize=venv, episode_log=list(callback.log), rollout_log=list(callback.rollouts),
        diverged_episodes=callback.diverged,
    )


def _continue_from(model: Any, venv: Any, path: str, spaces: tuple) -> None:
    """Start ``model`` from the policy file ``path``: its weights and its normalisation statistics."""
    pol = load_policy(path)
    pol.check_env(*spaces)
    if pol.meta["algo"] != ("sac" if "SAC" in type(model).__name__ else "ppo"):
        raise PolicyFileError(f"'{path}' holds a {pol.meta['algo']} policy; continue it with --algo {pol.meta['algo']}")
    model.policy.load_state_dict(pol.model.policy.state_dict())
    rms = venv.obs_rms
    rms.mean, rms.var = pol.obs_mean.copy(), pol.obs_var.copy()
    rms.count = float(pol.meta["normalize"]["count"])


def _close(venv: Any, base: Any) -> None:
    """Close the env stack; SubprocVecEnv workers that a Ctrl-C already ended (a closed pipe) are
    terminated instead."""
    try:
        venv.close()
    except (OSError, EOFError):
        for proc in getattr(base, "processes", []):
            if proc.is_alive():
                proc.terminate()
            proc.join(timeout=5)


@contextmanager
def _ignore_sigint() -> Iterator[None]:
    """Let cleanup finish when the user presses Ctrl-C again (main thread only)."""
    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not in the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
