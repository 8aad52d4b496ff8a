"""The package as a whole: the env registers on import. The layers of docs/ARCHITECTURE.md are
import-linter contracts (pyproject.toml), checked by ``lint-imports`` in scripts/test.sh."""

from __future__ import annotations


def test_registration_on_import():
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401

    assert "TensegrityIco-v0" in gym.registry
    assert gym.registry["TensegrityIco-v0"].max_episode_steps is not None


def test_the_architecture_document_is_printed_from_the_contracts_and_the_registry():
    """docs/ARCHITECTURE.md's layer tables, data path and effect table are what
    scripts/architecture.py prints from pyproject.toml's contracts and the effect registry."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("architecture", root / "scripts" / "architecture.py")
    arch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(arch)
    text = (root / "docs" / "ARCHITECTURE.md").read_text()
    assert arch.render(text) == text, "docs/ARCHITECTURE.md is out of date: run python scripts/architecture.py"
    for layer in ("identified.fit", "identified.twin", "identified.engine", "tensegrity_gym.checks"):
        assert f"`{layer}`" in text


def test_the_readme_lists_the_effects_the_registry_holds():
    """The README's effect table and its list of the names a model file may hold are the registry's."""
    import re
    from pathlib import Path

    from identified.effects import EFFECTS, known_names

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    m = re.search(r"lists an effect other than ((?:`\w+`,?\s*)+)", readme)
    assert m, "the README's sentence on the effects a model file may list is gone"
    assert tuple(re.findall(r"`(\w+)`", m.group(1))) == known_names()
    table = readme[readme.index("| effect | law | parameters |"):]
    table = table[: table.index("\n\n")]
    assert tuple(re.findall(r"^\| `(\w+)` \|", table, re.MULTILINE)) == tuple(EFFECTS)
