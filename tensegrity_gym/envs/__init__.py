"""Gymnasium registration of the tensegrity environments (done when ``tensegrity_gym`` is imported).

| id | entry point | time limit |
| --- | --- | --- |
| ``TensegrityIco-v0`` | ``tensegrity_gym.envs.tensegrity_ico_v0:TensegrityIcoEnv`` | 1000 steps (20 s) |
"""

from __future__ import annotations

import gymnasium

__all__ = ["ENV_IDS", "register_envs"]

ENV_IDS: tuple[str, ...] = ("TensegrityIco-v0",)


def register_envs() -> None:
    """Register every env id with Gymnasium (idempotent)."""
    if "TensegrityIco-v0" not in gymnasium.registry:
        gymnasium.register(
            id="TensegrityIco-v0",
            entry_point="tensegrity_gym.envs.tensegrity_ico_v0:TensegrityIcoEnv",
            max_episode_steps=1000,
        )


register_envs()
