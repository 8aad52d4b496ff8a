"""Run an offscreen-rendering script in a fresh process, trying EGL, then OSMesa."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


def render_in_subprocess(script: str) -> dict:
    """The last stdout line of ``script`` as JSON, from the first GL back-end that works.

    MuJoCo picks its GL back-end at import, so each try needs a new process; when neither back-end
    is available the calling test is skipped with what both said.
    """
    results = {}
    for gl in ("egl", "osmesa"):
        p = subprocess.run([sys.executable, "-c", script], env={**os.environ, "MUJOCO_GL": gl},
                           capture_output=True, text=True, timeout=120, check=False)
        assert p.returncode == 0, p.stderr[-2000:]
        results[gl] = json.loads(p.stdout.strip().splitlines()[-1])
        if "unavailable" not in results[gl]:
            return results[gl]
    pytest.skip(f"no offscreen OpenGL here (MUJOCO_GL=egl and osmesa both failed): {results}")
