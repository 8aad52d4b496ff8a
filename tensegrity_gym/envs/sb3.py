"""Stable-Baselines3 on a Gymnasium vector env: :class:`SB3VecEnvAdapter`.

SB3's ``VecEnv`` API is not Gymnasium's vector API: ``reset()`` returns the observations only;
``step()`` returns ``(obs, rewards, dones, infos)`` with ``dones = terminated | truncated``, a list
of one info dict per env, the sub-env reset in the same step (``obs`` is already the first
observation of the next episode) and the last observation of the ended episode in
``infos[i]["terminal_observation"]`` (plus ``infos[i]["TimeLimit.truncated"]``). The adapter
translates, so SB3 trains on the batched twin directly::

    import gymnasium as gym
    from stable_baselines3 import PPO
    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    venv = gym.make_vec("TensegrityIco-v0", num_envs=64, backend="identified")
    model = PPO("MlpPolicy", SB3VecEnvAdapter(venv)).learn(100_000)

Any ``gymnasium.vector.VectorEnv`` works: with ``autoreset_mode`` ``SAME_STEP`` the adapter reads
Gymnasium's ``final_obs``/``final_info``; with ``NEXT_STEP`` (the default) or ``DISABLED`` it
resets the ended sub-envs at once with ``reset(options={"reset_mask": dones})``, so no step is
wasted. Seeds given with :meth:`SB3VecEnvAdapter.seed` apply at the next :meth:`reset`, as in SB3.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

__all__ = ["SB3VecEnvAdapter", "unbatch_infos"]


def unbatch_infos(infos: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """Gymnasium's vector info (a dict of arrays with ``_key`` masks) as ``n`` per-env dicts.

    Numeric entries become Python scalars (arrays stay arrays), object entries stay as they are;
    nested dicts (``final_info``) are unbatched recursively.
    """
    out: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, val in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get(f"_{key}")
        if isinstance(val, dict):
            nested = unbatch_infos(val, n)
            for i in (range(n) if mask is None else np.flatnonzero(mask)):
                out[i][key] = nested[i]
            continue
        arr = np.asarray(val)
        if arr.dtype != object and arr.ndim == 1:
            # one C call for the whole column (per-element .item() was a tenth of a step's time)
            items = arr.tolist()
            if mask is None:
                for d, x in zip(out, items, strict=True):
                    d[key] = x
            else:
                for i in np.flatnonzero(mask):
                    out[i][key] = items[i]
            continue
        for i in (range(n) if mask is None else np.flatnonzero(mask)):
            x = arr[i]
            if isinstance(x, np.ndarray):
                x = x.copy()
            out[i][key] = x
    return out


class SB3VecEnvAdapter(VecEnv):
    """A Gymnasium ``VectorEnv`` seen as a Stable-Baselines3 ``VecEnv`` (see the module docstring).

    Args:
        venv: the vector env, e.g. ``gym.make_vec("TensegrityIco-v0", num_envs=N, backend="identified")``.
            Its ``single_observation_space`` and ``single_action_space`` become the adapter's spaces.
    """

    def __init__(self, venv: gym.vector.VectorEnv) -> None:
        if not isinstance(venv, gym.vector.VectorEnv):
            raise TypeError(f"SB3VecEnvAdapter wraps a gymnasium.vector.VectorEnv, got {type(venv).__name__}")
        self.venv = venv
        mode = venv.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self.autoreset_mode = AutoresetMode(mode)
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    # ------------------------------------------------------------------ reset and step
    def reset(self) -> VecEnvObs:
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        options = None
        if any(self._options):
            first = self._options[0]
            if any(o != first for o in self._options[1:]):
                raise ValueError("a Gymnasium vector env takes one options dict for all sub-envs")
            options = dict(first)
        obs, infos = self.venv.reset(seed=seeds, options=options)
        self.reset_infos = unbatch_infos(infos, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        actions, self._actions = self._actions, None
        obs, rewards, terminated, truncated, infos = self.venv.step(actions)
        n = self.num_envs
        dones = np.logical_or(terminated, truncated)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            final_obs = infos.get("final_obs")
            final_info = infos.get("final_info", {})
            finals_keys = ("final_obs", "_final_obs", "final_info", "_final_info")
            top = {k: v for k, v in infos.items() if k not in finals_keys}
            step_infos = unbatch_infos(top, n)
            finals = unbatch_infos(final_info, n)
            for i in np.flatnonzero(dones):
                self.reset_infos[i] = step_infos[i]
                step_infos[i] = finals[i]
                step_infos[i]["terminal_observation"] = final_obs[i]  # type: ignore[index]
        else:
            step_infos = unbatch_infos(infos, n)
            if dones.any():
                terminal = obs[dones].copy()
                reset_obs, reset_infos = self.venv.reset(options={"reset_mask": dones.copy()})
                obs = obs.copy()
                obs[dones] = reset_obs[dones]
                per_env = unbatch_infos(reset_infos, n)
                for k, i in enumerate(np.flatnonzero(dones)):
                    step_infos[i]["terminal_observation"] = terminal[k]
                    self.reset_infos[i] = per_env[i]
        for i in range(n):
            step_infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, np.asarray(rewards, dtype=np.float32), dones, step_infos

    def close(self) -> None:
        self.venv.close()

    # ------------------------------------------------------------------ attributes and methods
    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        idx = list(self._get_indices(indices))
        if hasattr(self.venv, "get_attr"):
            values = self.venv.get_attr(attr_name)
            return [values[i] for i in idx]
        return [getattr(self.venv, attr_name) for _ in idx]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        idx = list(self._get_indices(indices))
        if not hasattr(self.venv, "set_attr"):
            raise AttributeError(f"{type(self.venv).__name__} has no set_attr")
        if len(idx) != self.num_envs:
            current = list(self.venv.get_attr(attr_name))
            for i in idx:
                current[i] = value
            self.venv.set_attr(attr_name, current)
        else:
            self.venv.set_attr(attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        idx = list(self._get_indices(indices))
        if not hasattr(self.venv, "call"):
            raise AttributeError(f"{type(self.venv).__name__} cannot call methods of its sub-envs")
        results = self.venv.call(method_name, *method_args, **method_kwargs)
        return [results[i] for i in idx]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        idx = list(self._get_indices(indices))
        envs = getattr(self.venv, "envs", None)
        if envs is None:  # a natively batched env has no sub-env objects to wrap
            return [False for _ in idx]
        from stable_baselines3.common.env_util import is_wrapped

        return [is_wrapped(envs[i], wrapper_class) for i in idx]

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.render_mode != "rgb_array":
            return [None] * self.num_envs
        return list(self.venv.render())
