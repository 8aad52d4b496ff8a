#!/usr/bin/env bash
# Set up ./.venv (created or reused), then: ruff (the project's lint configuration), lint-imports (the
# layers written as contracts in pyproject.toml), and the test suite (slow experiments excluded), one
# pytest-xdist worker per core (each test runs torch on one thread: tests/conftest.py), a test file's
# tests on one worker (its module fixtures built once).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/ruff check .
.venv/bin/lint-imports --no-cache
exec .venv/bin/python -m pytest -q -n auto --dist loadfile "$@"
