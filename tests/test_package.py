"""The package split of docs/ARCHITECTURE.md: ``identified`` stands on its own."""

from __future__ import annotations

import subprocess
import sys


def test_identified_imports_neither_gymnasium_nor_mujoco_nor_tensegrity_gym():
    code = (
        "import sys, identified, identified.engine, identified.fit.identify, identified.fit.refine, "
        "identified.predict, identified.model\n"
        "print(sorted(m for m in ('gymnasium', 'mujoco', 'tensegrity_gym') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_registration_on_import():
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401

    assert "TensegrityIco-v0" in gym.registry
    assert gym.registry["TensegrityIco-v0"].max_episode_steps is not None
