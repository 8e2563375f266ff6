#!/usr/bin/env bash
# Launch a local pool: N `rl-pool train` processes on one pool directory, each
# with its own learning rate from a bash array, each logging to its own file,
# while `rl-pool status --watch` shows progress (redrawn in place on a
# terminal, a plain line every PROGRESS_INTERVAL seconds in a log). Ctrl-C (or
# SIGTERM) stops every member cleanly; if one member fails the others are
# stopped too; running this again resumes the pool where it is.
#
#   POOL_DIR=runs/swimmer N=2 BASE_LR=0.1 ./shell/pool.sh [extra rl-pool train options]
#   N=4 LEARNING_RATES="0.01 0.1 0.1 0.2" ./shell/pool.sh ...
#   PROGRESS=0 ./shell/pool.sh ...     # no progress display (members' logs only)
set -uo pipefail
POOL_DIR="${POOL_DIR:-runs/swimmer-v5}"
N="${N:-2}"
BASE_LR="${BASE_LR:-0.1}"
ITERATIONS="${ITERATIONS:-500}"
PROGRESS="${PROGRESS:-1}"
PROGRESS_INTERVAL="${PROGRESS_INTERVAL:-}"   # default: 0.5 s redraws on a terminal, 10 s between lines otherwise
STOP_GRACE="${STOP_GRACE:-30}"   # seconds a member has to stop on TERM before it gets KILL (files stay whole)
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
if ! [[ "$STOP_GRACE" =~ ^[0-9]+$ ]]; then
    echo "pool.sh: STOP_GRACE must be a whole number of seconds, got '$STOP_GRACE'" >&2
    exit 2
fi
if [ "${#LRS[@]}" -ne "$N" ]; then
    echo "pool.sh: ${#LRS[@]} learning rates for N=$N members" >&2
    exit 2
fi
mkdir -p "$POOL_DIR/logs"
out_of() { echo "$POOL_DIR/logs/member-$(printf %03d "$1").out"; }
pids=()
watcher=""
stopped=0
kill_at=""
killed=0
stop_members() {
    # SIGTERM, not SIGINT: bash starts background jobs with SIGINT ignored, so a member
    # that has not yet installed its handler would miss an INT; it stops cleanly on TERM.
    kill -TERM "${pids[@]}" 2>/dev/null
    [ -n "$kill_at" ] || kill_at=$((SECONDS + STOP_GRACE))
}
on_signal() {
    stopped=1
    [ -n "$watcher" ] || echo "pool.sh: stopping ${#pids[@]} members..." >&2
    stop_members
}
trap on_signal INT TERM
for ((m = 0; m < N; m++)); do
    "$RL_POOL" train --pool-dir "$POOL_DIR" --pool-size "$N" --member "$m" \
        --learning-rate "${LRS[$m]}" --iterations "$ITERATIONS" --quiet "$@" \
        >> "$(out_of "$m")" 2>&1 &
    pids+=($!)
done
echo "pool.sh: $N members on $POOL_DIR (learning rates ${LRS[*]}); logs in $POOL_DIR/logs/" >&2
if [ "$PROGRESS" != 0 ]; then
    "$RL_POOL" status "$POOL_DIR" --watch ${PROGRESS_INTERVAL:+--interval "$PROGRESS_INTERVAL"} &
    watcher=$!
else
    echo "pool.sh: watch with: rl-pool status $POOL_DIR --watch" >&2
fi
# Wait for every member; the first that fails (while we were not stopping) stops the others.
rcs=()
failed=""
left=$N
while [ "$left" -gt 0 ]; do
    for ((m = 0; m < N; m++)); do
        [ -n "${rcs[$m]:-}" ] && continue
        kill -0 "${pids[$m]}" 2>/dev/null && continue
        wait "${pids[$m]}"; rcs[$m]=$?
        left=$((left - 1))
        if [ "${rcs[$m]}" -ne 0 ] && [ "$stopped" -eq 0 ] && [ -z "$failed" ]; then
            failed=$m
            stop_members
        fi
    done
    if [ "$left" -gt 0 ] && [ "$killed" -eq 0 ] && [ -n "$kill_at" ] && [ "$SECONDS" -ge "$kill_at" ]; then
        # Every pool file is written whole or not at all, so KILL loses nothing on disk.
        echo "pool.sh: $left member(s) still running ${STOP_GRACE}s after TERM; sending KILL" >&2
        for ((m = 0; m < N; m++)); do
            [ -z "${rcs[$m]:-}" ] && kill -KILL "${pids[$m]}" 2>/dev/null  # not yet reaped: still ours
        done
        killed=1
    fi
    [ "$left" -gt 0 ] && sleep 0.2
done
if [ -n "$watcher" ]; then
    kill -TERM "$watcher" 2>/dev/null
    wait "$watcher"
fi
if [ -n "$failed" ]; then
    out="$(out_of "$failed")"
    echo "pool.sh: member $failed exited with ${rcs[$failed]}: $(tail -n 1 "$out" 2>/dev/null); stopped the others" >&2
    echo "pool.sh: (full output in $out and $POOL_DIR/logs/member-$(printf %03d "$failed").log)" >&2
    exit 1
fi
if [ "$stopped" -eq 1 ]; then
    echo "pool.sh: stopped; run the same command again to resume" >&2
    exit 130
fi
exit 0
