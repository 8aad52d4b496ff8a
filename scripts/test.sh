#!/usr/bin/env bash
# Set up ./.venv (created or reused), then: ruff (the project's lint configuration), lint-imports (the
# layers written as contracts in pyproject.toml), and the test suite (slow experiments excluded).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
.venv/bin/ruff check .
.venv/bin/lint-imports --no-cache
exec .venv/bin/python -m pytest -q "$@"
