"""The README's Python snippets run, and print what their comments say.

Every ```python block of README.md runs in a fresh folder, in order, in one namespace per block.
A comment ``# prints "A" ... "B"`` on a line promises that the output holds each quoted text.
Sizes are cut to test scale by :data:`SMALL` (the printed figures do not depend on them: the fit
recovers the plant's parameters exactly from any clean data); ``TENSEGRITY_README_FULL=1`` runs
the snippets as written.  A snippet that reads ``F.json`` (the output of ``tensegrity fit`` on the
robot) gets the shipped robot model.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: text of a snippet -> its test-scale replacement
SMALL = {
    "CollectConfig(episodes=20, steps=2000,": "CollectConfig(episodes=2, steps=300,",
    "n_steps=64).learn(10_000)": "n_steps=8).learn(16)",  # one update (the eager twin: ~0.2 s a step)
    "num_envs=64,": "num_envs=2,",
}
BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
PRINTS = re.compile(r"#\s*prints\s+(.*)$")


def python_blocks() -> list[str]:
    return BLOCK.findall(README.read_text(encoding="utf-8"))


def promises(code: str) -> list[str]:
    """The quoted texts of every ``# prints "..."`` comment."""
    out = []
    for line in code.splitlines():
        m = PRINTS.search(line)
        if m:
            out += re.findall(r'"([^"]+)"', m.group(1))
    return out


def test_readme_has_snippets_and_promises():
    blocks = python_blocks()
    assert len(blocks) >= 3
    assert any(promises(b) for b in blocks)
    assert promises('print(x)  # prints "a: 1" ... "b: 2"') == ["a: 1", "b: 2"]
    text = README.read_text(encoding="utf-8")
    assert [full for full in SMALL if full not in text] == []  # each cut still finds its snippet


@pytest.mark.parametrize("index", range(len(python_blocks())))
def test_readme_snippet_runs_and_prints_what_it_says(index, tmp_path, monkeypatch):
    code = python_blocks()[index]
    if os.environ.get("TENSEGRITY_README_FULL") != "1":
        for full, small in SMALL.items():
            code = code.replace(full, small)
    monkeypatch.chdir(tmp_path)
    if "F.json" in code:
        shutil.copy(ROOT / "identified" / "data" / "robot.json", tmp_path / "F.json")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": "__readme__"})  # noqa: S102  (the README is ours)
    for text in promises(code):
        assert text in out.getvalue(), (text, out.getvalue()[:2000])
