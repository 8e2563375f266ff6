#!/usr/bin/env bash
# Create .venv (if missing) and install rl-pool with its test extra into it, at
# the exact versions in constraints.txt (the lock). Quiet unless it fails: pip's
# output is kept in a temp file and shown only then. Re-installs when
# pyproject.toml or the lock changes. Sourced by train.sh and test.sh.
#
#   RL_POOL_UNLOCKED=1   install the newest versions pyproject.toml allows instead of the lock
#   RL_POOL_VENV=DIR     another virtual environment (default: .venv in the repo)
#   PYTHON=python3.12    the interpreter that creates it (default: python3)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-python3}"
VENV="${RL_POOL_VENV:-$ROOT/.venv}"
LOCK="${RL_POOL_LOCK:-$ROOT/constraints.txt}"
STAMP="$VENV/.rl-pool-installed"
if [ "${RL_POOL_UNLOCKED:-0}" != 0 ]; then
    mode="newest allowed versions"
    constraints=()
    hint=""
    want="$(sha256sum < "$ROOT/pyproject.toml" | cut -d' ' -f1) unlocked"
else
    mode="locked versions"
    constraints=(-c "$LOCK")
    hint="to try the newest versions pyproject.toml allows instead of $LOCK: RL_POOL_UNLOCKED=1"
    want="$(cat "$ROOT/pyproject.toml" "$LOCK" | sha256sum | cut -d' ' -f1) locked"
fi
_setup_fail() {  # _setup_fail LOG MESSAGE...: show what the tool said, then why we stop
    local log="$1"; shift
    cat "$log" >&2
    rm -f "$log"
    printf 'setup: %s\n' "$@" >&2
    return 1
}
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null || true)" != "$want" ]; then
    _setup_log="$(mktemp)"
    if [ ! -x "$VENV/bin/python" ]; then
        "$PY" -m venv "$VENV" > "$_setup_log" 2>&1 ||
            _setup_fail "$_setup_log" "could not create $VENV with $PY (on Debian/Ubuntu: apt-get install python3-venv)" ||
            { return 1 2>/dev/null || exit 1; }
    fi
    echo "setup: installing rl-pool and its dependencies ($mode) into $VENV; the first time takes a minute" >&2
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$VENV/bin/python" -m pip install -e "$ROOT[test]" "${constraints[@]}" \
            > "$_setup_log" 2>&1 ||
        _setup_fail "$_setup_log" "pip failed (its output is above)${hint:+; $hint}" ||
        { return 1 2>/dev/null || exit 1; }
    rm -f "$_setup_log"
    echo "$want" > "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
