#!/usr/bin/env bash
# Rewrite constraints.txt (the lock) from what is installed in .venv now:
# `pip freeze` less rl-pool itself (pip and setuptools are never listed).
# Run it after changing dependencies in pyproject.toml and checking that the
# tests pass with the new versions (RL_POOL_UNLOCKED=1 ./shell/test.sh).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${RL_POOL_VENV:-$ROOT/.venv}"
PY_VERSION="$("$VENV/bin/python" -c 'import platform; print(platform.python_version(), platform.machine())')"
{
    echo "# The exact versions rl-pool is tested and its results were made with (pip constraints)."
    echo "# shell/setup.sh installs with: pip install -c constraints.txt -e .[test]  (RL_POOL_UNLOCKED=1: newest allowed)."
    echo "# Made by shell/lock.sh from a working .venv (Python $PY_VERSION); do not edit by hand."
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$VENV/bin/python" -m pip freeze --exclude-editable |
        grep -viE '^(rl-pool|rl_pool)([=@ ]|$)'
} > "$ROOT/constraints.txt.tmp"
mv "$ROOT/constraints.txt.tmp" "$ROOT/constraints.txt"
echo "constraints.txt: $(grep -vc '^#' "$ROOT/constraints.txt") pinned packages"
