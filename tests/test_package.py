"""The package as a whole: the env registers on import. The layers of docs/ARCHITECTURE.md are
import-linter contracts (pyproject.toml), checked by ``lint-imports`` in scripts/test.sh."""

from __future__ import annotations


def test_registration_on_import():
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401

    assert "TensegrityIco-v0" in gym.registry
    assert gym.registry["TensegrityIco-v0"].max_episode_steps is not None
