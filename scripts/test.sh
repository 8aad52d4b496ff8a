#!/usr/bin/env bash
# Set up ./.venv (created or reused) and run the test suite (slow experiments excluded).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec .venv/bin/python -m pytest -q "$@"
