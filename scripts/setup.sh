#!/usr/bin/env bash
# Create or reuse ./.venv and install tensegrity-gym into it (torch first, CPU build).
# Sourced by scripts/demo.sh and scripts/test.sh; safe to run again (re-installs only when
# pyproject.toml changed).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
STAMP=.venv/.tensegrity-installed
WANT="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
    # torch first, pinned to the 2.13 series: on the project's machines this takes the local CPU
    # build instead of pulling several GB of CUDA packages.
    .venv/bin/python -m pip install -q "torch==2.13.*"
    .venv/bin/python -m pip install -q -e ".[dev]"
    echo "$WANT" > "$STAMP"
fi
export MUJOCO_GL="${MUJOCO_GL:-egl}"
