"""Gymnasium registration of the tensegrity environments (done when ``tensegrity_gym`` is imported).

| id | entry point | time limit |
| --- | --- | --- |
| ``TensegrityIco-v0`` | ``tensegrity_gym.envs.tensegrity_ico_v0:TensegrityIcoEnv`` | 1000 steps (20 s) |
| ``Tensegrity-v0`` | ``tensegrity_gym.envs.tensegrity_v0:TensegrityEnv`` (any MJCF: ``xml_file=PATH``) | 1000 steps |

``TensegrityIco-v0`` also has a ``vector_entry_point``, ``tensegrity_gym.envs.vector:make_vector_env``:
``gym.make_vec("TensegrityIco-v0", num_envs=N, backend="identified", ...)`` is the natively batched
twin (one engine call per physics step for all N envs); with the MuJoCo backend ``make_vec`` gives a
``SyncVectorEnv`` of plants, as it would without the entry point; ``Tensegrity-v0`` the same for any
MJCF (``gym.make_vec("Tensegrity-v0", num_envs=N, backend="identified", xml_file=PATH, model=F.json)``,
its MuJoCo actuators stepped in the batch).
"""

from __future__ import annotations

import gymnasium

__all__ = ["ENV_IDS", "register_envs"]

ENV_IDS: tuple[str, ...] = ("TensegrityIco-v0", "Tensegrity-v0")


def register_envs() -> None:
    """Register every env id with Gymnasium (idempotent)."""
    if "TensegrityIco-v0" not in gymnasium.registry:
        gymnasium.register(
            id="TensegrityIco-v0",
            entry_point="tensegrity_gym.envs.tensegrity_ico_v0:TensegrityIcoEnv",
            vector_entry_point="tensegrity_gym.envs.vector:make_vector_env",
            max_episode_steps=1000,
        )
    if "Tensegrity-v0" not in gymnasium.registry:
        gymnasium.register(
            id="Tensegrity-v0",
            entry_point="tensegrity_gym.envs.tensegrity_v0:TensegrityEnv",
            vector_entry_point="tensegrity_gym.envs.vector:make_tensegrity_vector_env",
            max_episode_steps=1000,
        )


register_envs()
