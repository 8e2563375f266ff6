#!/usr/bin/env bash
# The main job on a fresh machine: set up .venv if needed, then run a 2-member
# pool on Swimmer-v5 with the default settings (see README). Options are passed
# to every member, e.g. ./shell/train.sh --iterations 200
set -euo pipefail
cd "$(dirname "$0")/.."
source shell/setup.sh
exec ./shell/pool.sh "$@"
