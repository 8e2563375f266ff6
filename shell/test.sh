#!/usr/bin/env bash
# Set up .venv if needed, then lint and run the whole test suite.
# Usage: ./shell/test.sh [pytest args]   (e.g. -m "not multiprocess" for the fast tiers only)
set -euo pipefail
cd "$(dirname "$0")/.."
source shell/setup.sh
ruff check .
python -m pytest -q "$@"
