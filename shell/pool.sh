#!/usr/bin/env bash
# Launch a local pool: N `rl-pool train` processes on one pool directory, each
# with its own learning rate from a bash array, each logging to its own file.
# Ctrl-C (or SIGTERM) stops every member cleanly; running this again resumes
# the pool where it is.
#
#   POOL_DIR=runs/swimmer N=2 BASE_LR=0.1 ./shell/pool.sh [extra rl-pool train options]
#   N=4 LEARNING_RATES="0.01 0.1 0.1 0.2" ./shell/pool.sh ...
set -uo pipefail
POOL_DIR="${POOL_DIR:-runs/swimmer-v5}"
N="${N:-2}"
BASE_LR="${BASE_LR:-0.1}"
ITERATIONS="${ITERATIONS:-500}"
# rl-pool: $RL_POOL, else this repo's .venv, else whatever is on PATH
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RL_POOL="${RL_POOL:-}"
if [ -z "$RL_POOL" ]; then
    if [ -x "$HERE/.venv/bin/rl-pool" ]; then RL_POOL="$HERE/.venv/bin/rl-pool"; else RL_POOL=rl-pool; fi
fi
if [ -n "${LEARNING_RATES:-}" ]; then
    read -r -a LRS <<< "$LEARNING_RATES"
else
    # The first member steps at 1/10 of the others' rate: if the others' updates
    # turn out too large, the pool still has a branch that improves.
    LRS=()
    for ((m = 0; m < N; m++)); do
        if [ "$m" -eq 0 ] && [ "$N" -gt 1 ]; then
            LRS+=("$(python3 -c "print($BASE_LR / 10)")")
        else
            LRS+=("$BASE_LR")
        fi
    done
fi
if [ "${#LRS[@]}" -ne "$N" ]; then
    echo "pool.sh: ${#LRS[@]} learning rates for N=$N members" >&2
    exit 2
fi
mkdir -p "$POOL_DIR/logs"
pids=()
stopped=0
stop() {
    stopped=1
    echo "pool.sh: stopping ${#pids[@]} members..." >&2
    # SIGTERM, not SIGINT: bash starts background jobs with SIGINT ignored, so a member
    # that has not yet installed its handler would miss an INT; it stops cleanly on TERM.
    kill -TERM "${pids[@]}" 2>/dev/null
}
trap stop INT TERM
for ((m = 0; m < N; m++)); do
    "$RL_POOL" train --pool-dir "$POOL_DIR" --pool-size "$N" --member "$m" \
        --learning-rate "${LRS[$m]}" --iterations "$ITERATIONS" --quiet "$@" \
        >> "$POOL_DIR/logs/member-$(printf %03d "$m").out" 2>&1 &
    pids+=($!)
done
echo "pool.sh: $N members on $POOL_DIR (learning rates ${LRS[*]}); logs in $POOL_DIR/logs/" >&2
echo "pool.sh: watch with: rl-pool status $POOL_DIR" >&2
status=0
for ((m = 0; m < N; m++)); do
    # wait returns early when a trapped signal arrives; wait again for the member itself
    while true; do
        wait "${pids[$m]}"; rc=$?
        kill -0 "${pids[$m]}" 2>/dev/null || break
    done
    out="$POOL_DIR/logs/member-$(printf %03d "$m").out"
    if [ "$rc" -ne 0 ] && [ "$stopped" -eq 0 ]; then
        echo "pool.sh: member $m exited with $rc: $(tail -n 1 "$out" 2>/dev/null)" >&2
        echo "pool.sh: (full output in $out and $POOL_DIR/logs/member-$(printf %03d "$m").log)" >&2
        status=1
    fi
done
"$RL_POOL" status "$POOL_DIR" --last 5 2>/dev/null
if [ "$stopped" -eq 1 ]; then
    echo "pool.sh: stopped; run the same command again to resume" >&2
    exit 130
fi
exit $status
