#!/usr/bin/env bash
# Submit an N-member pool as a SLURM job array (one array task per member).
#
#   POOL_DIR=/shared/runs/swimmer ./shell/slurm_submit.sh 4 --iterations 900
#   LEARNING_RATES="0.01 0.1 0.1 0.2" POOL_DIR=... ./shell/slurm_submit.sh 4 --iterations 900
#
# Arguments after N go to `rl-pool train`. Run it from the repo (the tasks use
# its .venv/bin/rl-pool unless RL_POOL is set); task output goes to
# ./slurm-logs/. sbatch's own environment variables choose partition, time
# limit, account... (SBATCH_PARTITION, SBATCH_TIMELIMIT, SBATCH_ACCOUNT).
# Prints the array job id. Submitting again resumes the pool.
set -euo pipefail
if [ $# -lt 1 ] || ! [[ "$1" =~ ^[1-9][0-9]*$ ]]; then
    echo "usage: POOL_DIR=DIR $0 N [rl-pool train options]" >&2
    exit 2
fi
N="$1"; shift
[ -n "${POOL_DIR:-}" ] || { echo "slurm_submit.sh: set POOL_DIR (on the shared filesystem)" >&2; exit 2; }
mkdir -p "$POOL_DIR" slurm-logs
POOL_DIR="$(cd "$POOL_DIR" && pwd)" POOL_SIZE="$N" \
    exec sbatch --parsable --array="0-$((N - 1))" "$(dirname "$0")/slurm_pool.sbatch" "$@"
