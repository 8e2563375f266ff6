#!/usr/bin/env bash
# A real single-node SLURM cluster, private to this run, and three pools on it:
#   (a) a reference pool run locally with `rl-pool launch`;
#   (b) the same pool as a 2-task job array (shell/slurm_submit.sh -> slurm_pool.sbatch):
#       every iteration has both deposits and the selection history equals (a);
#   (c) the array again, with array task 1 cancelled mid-run (scancel: SIGTERM) and
#       resubmitted alone (sbatch --array=1): the pool resumes and still equals (a).
# Prints: submit -> first deposit, array vs launch wall time, the pool's wait
# while a member was cancelled.
#
# Needs root (it installs slurmctld slurmd slurm-client munge with apt-get if
# missing and runs the daemons). Its daemons use their own config, ports, state
# and munge socket under a temp dir, are started without systemd, and are
# stopped by PID on exit. When SLURM cannot be installed or started it prints
# "SKIP: <reason>" and exits 77. Exit 0: all checks passed; 1: a check failed.
#
#   sudo ./shell/slurm_selftest.sh          (RL_POOL=... to test another rl-pool; KEEP=1 keeps the temp dir)
# shellcheck disable=SC2317  # the cleanup functions are reached from the EXIT trap
set -uo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
RL_POOL="${RL_POOL:-$ROOT/.venv/bin/rl-pool}"
PY="${PYTHON:-$(dirname "$RL_POOL")/python}"
ITERS="${ITERS:-24}"
# Short episodes: a whole pool takes seconds. Enough iterations that the pool is
# still running when the scancel of (c) lands.
SETTINGS=(--max-episode-steps 60 --train-episodes 4 --batch-episodes 2 --eval-episodes 2 --iterations "$ITERS")
LRS_SPACE="0.003 0.03"
LRS_COMMA="0.003,0.03"

WORK="" MUNGE_PID="" CTLD_PID="" SLURMD_PID="" LAUNCH_PID="" JOBS=()

say() { echo "slurm_selftest: $*"; }
skip() { echo "SKIP: $*"; exit 77; }
fail() { echo "FAIL: $*"; exit 1; }
now() { date +%s.%N; }
secs() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; }
tail_file() { [ -f "$1" ] && { echo "--- last lines of $1"; tail -n "${2:-15}" "$1"; }; }

# ------------------------------------------------------------------ cleanup
children_of() { ps -o pid= --ppid "$1" 2>/dev/null | tr -d ' '; }

stop_pid() {  # TERM, bounded wait, then KILL; only the PIDs this script started
    local pid="$1" name="$2" t
    [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null || return 0
    kill -TERM "$pid" 2>/dev/null
    for ((t = 0; t < 100; t++)); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.1; done
    say "$name (pid $pid) ignored SIGTERM for 10s; SIGKILL"
    kill -KILL "$pid" 2>/dev/null
    wait "$pid" 2>/dev/null
}

cleanup() {
    local rc=$? t pid kids=""
    trap - EXIT INT TERM
    [ -n "$LAUNCH_PID" ] && stop_pid "$LAUNCH_PID" "rl-pool launch"
    if [ -n "$CTLD_PID" ] && kill -0 "$CTLD_PID" 2>/dev/null && [ "${#JOBS[@]}" -gt 0 ]; then
        scancel "${JOBS[@]}" 2>/dev/null
        for ((t = 0; t < 300; t++)); do
            [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break
            sleep 0.1
        done
    fi
    # members whose job step outlived the cancel: ours, recognised by our temp dir in their command line
    if [ -n "$WORK" ]; then
        for pid in $(pgrep -f -- "--pool-dir $WORK/" 2>/dev/null); do stop_pid "$pid" "leftover member"; done
    fi
    for pid in $CTLD_PID $SLURMD_PID; do kids="$kids $(children_of "$pid")"; done  # e.g. slurmscriptd
    stop_pid "$SLURMD_PID" slurmd
    stop_pid "$CTLD_PID" slurmctld
    for pid in $kids; do stop_pid "$pid" "slurm helper"; done
    stop_pid "$MUNGE_PID" munged
    if [ -n "$WORK" ]; then
        if [ "${KEEP:-0}" = 1 ]; then say "kept $WORK"; else rm -rf "$WORK"; fi
    fi
    exit "$rc"
}
trap cleanup EXIT
trap 'echo "slurm_selftest: interrupted"; exit 130' INT TERM

# ------------------------------------------------------------------ install
[ "$(id -u)" -eq 0 ] || skip "not root (needed to install and run slurmctld, slurmd and munged)"
[ -x "$RL_POOL" ] || fail "no rl-pool at $RL_POOL (run ./shell/setup.sh, or set RL_POOL)"
[ -x "$PY" ] || fail "no python at $PY (set PYTHON)"

have_slurm() { command -v slurmctld && command -v slurmd && command -v sbatch && command -v munged; } >/dev/null 2>&1
if ! have_slurm; then
    command -v apt-get >/dev/null || skip "SLURM is not installed and there is no apt-get to install it"
    say "installing slurmctld slurmd slurm-client munge (apt-get)..."
    log=$(mktemp /tmp/rl-pool-slurm-apt.XXXXXX)
    if ! DEBIAN_FRONTEND=noninteractive timeout 900 apt-get install -y --no-install-recommends \
            slurmctld slurmd slurm-client munge >"$log" 2>&1; then
        tail -n 5 "$log"; rm -f "$log"
        skip "apt-get install of slurmctld slurmd slurm-client munge failed"
    fi
    rm -f "$log"
    have_slurm || skip "SLURM commands still missing after apt-get install"
fi
id munge >/dev/null 2>&1 || skip "no munge user (the munge package creates it)"

WORK="$(mktemp -d /tmp/rl-pool-slurm.XXXXXX)" || fail "mktemp failed"
chmod 755 "$WORK"   # munged runs as the munge user and must reach its dir
mkdir -p "$WORK/munge" "$WORK/slurm/state" "$WORK/slurm/spool" "$WORK/pools" "$WORK/submit/slurm-logs"
chown munge: "$WORK/munge" && chmod 755 "$WORK/munge"   # munged: clients must reach the socket

# ------------------------------------------------------------------ munge
KEY=/etc/munge/munge.key
if [ ! -s "$KEY" ]; then
    say "creating $KEY"
    mkdir -p /etc/munge && chown munge: /etc/munge && chmod 700 /etc/munge
    if command -v mungekey >/dev/null; then
        mungekey --create --keyfile="$KEY" || skip "mungekey could not create $KEY"
    else
        dd if=/dev/urandom of="$KEY" bs=1024 count=1 status=none || skip "could not create $KEY"
    fi
    chown munge: "$KEY" && chmod 400 "$KEY"
fi
SOCK="$WORK/munge/munge.socket"
if command -v setpriv >/dev/null; then
    AS_MUNGE=(setpriv --reuid=munge --regid=munge --init-groups)
else
    AS_MUNGE=(runuser -u munge --)
fi
"${AS_MUNGE[@]}" munged -F --socket="$SOCK" --key-file="$KEY" --log-file="$WORK/munge/munged.log" \
    --pid-file="$WORK/munge/munged.pid" --seed-file="$WORK/munge/munged.seed" >"$WORK/munged.out" 2>&1 &
MUNGE_PID=$!
for ((t = 0; t < 100; t++)); do
    [ -S "$SOCK" ] && munge -n -S "$SOCK" 2>/dev/null | unmunge -S "$SOCK" >/dev/null 2>&1 && break
    kill -0 "$MUNGE_PID" 2>/dev/null || break
    sleep 0.1
done
if ! munge -n -S "$SOCK" 2>/dev/null | unmunge -S "$SOCK" >/dev/null 2>&1; then
    tail_file "$WORK/munged.out"; tail_file "$WORK/munge/munged.log"
    skip "munged did not come up"
fi

# ------------------------------------------------------------------ slurm
HOST="$(hostname -s)"
NODE="$(slurmd -C 2>/dev/null | head -n 1)"
CPUS="$(sed -n 's/.*CPUs=\([0-9]*\).*/\1/p' <<< "$NODE")"
MEM="$(sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' <<< "$NODE")"
[ -n "$CPUS" ] && [ -n "$MEM" ] || skip "slurmd -C did not report CPUs and RealMemory ($NODE)"
[ "$CPUS" -ge 2 ] || skip "$CPUS CPU on this node; the 2-task array needs 2"
read -r PORT_CTLD PORT_SLURMD < <("$PY" -c '
import socket
ss = [socket.socket() for _ in range(2)]
for s in ss:
    s.bind(("127.0.0.1", 0))
print(*(s.getsockname()[1] for s in ss))')
export SLURM_CONF="$WORK/slurm/slurm.conf"
cat > "$SLURM_CONF" <<EOF
ClusterName=rlpooltest
SlurmctldHost=$HOST(127.0.0.1)
SlurmctldPort=$PORT_CTLD
SlurmdPort=$PORT_SLURMD
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$SOCK
StateSaveLocation=$WORK/slurm/state
SlurmdSpoolDir=$WORK/slurm/spool
SlurmctldPidFile=$WORK/slurm/slurmctld.pid
SlurmdPidFile=$WORK/slurm/slurmd.pid
SlurmctldLogFile=$WORK/slurm/slurmctld.log
SlurmdLogFile=$WORK/slurm/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
MailProg=/bin/true
ReturnToService=2
KillWait=30
MinJobAge=600
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
slurmctld -D -i -f "$SLURM_CONF" >"$WORK/slurm/slurmctld.out" 2>&1 &
CTLD_PID=$!
slurmd -D -f "$SLURM_CONF" >"$WORK/slurm/slurmd.out" 2>&1 &
SLURMD_PID=$!
state=""
for ((t = 0; t < 600; t++)); do   # 60 s
    state="$(sinfo -h -n "$HOST" -o %t 2>/dev/null)"
    [ "$state" = idle ] && break
    kill -0 "$CTLD_PID" 2>/dev/null && kill -0 "$SLURMD_PID" 2>/dev/null || break
    sleep 0.1
done
if [ "$state" != idle ]; then
    for f in slurmctld.out slurmctld.log slurmd.out slurmd.log; do tail_file "$WORK/slurm/$f" 8; done
    skip "the single-node SLURM cluster did not come up (node state '${state:-none}' after 60s)"
fi
say "SLURM $(sinfo -V | awk '{print $2}') up: node $HOST idle with $CPUS CPUs (conf $SLURM_CONF)"

# ------------------------------------------------------------------ helpers
pool_history() {  # per iteration: selected member, its eval return, its agent's hash
    "$PY" - "$1" "$ITERS" <<'EOF'
import json, os, sys
d, n = sys.argv[1], int(sys.argv[2])
for i in range(1, n + 1):
    p = os.path.join(d, "iterations", f"{i:06d}", "selected.json")
    try:
        s = json.load(open(p))
    except OSError:
        print(f"{i} missing")
        continue
    print(i, s["member"], repr(s["eval_return"]), s["agent_sha256"])
EOF
}

check_pool() {  # all iterations with both deposits, selected on a complete barrier; status agrees
    local d="$1" out
    out="$("$PY" - "$d" "$ITERS" <<'EOF'
import json, os, sys
d, n = sys.argv[1], int(sys.argv[2])
for i in range(1, n + 1):
    it = os.path.join(d, "iterations", f"{i:06d}")
    for m in (0, 1):
        if not os.path.exists(os.path.join(it, f"member-{m:03d}.json")):
            print(f"iteration {i} lacks member {m}'s deposit")
    try:
        s = json.load(open(os.path.join(it, "selected.json")))
    except OSError:
        print(f"iteration {i} has no selected.json")
        continue
    if s.get("skipped") or s.get("quorum_reason") != "complete":
        print(f"iteration {i} was selected without every deposit: {s.get('quorum_reason')}, skipped {s.get('skipped')}")
EOF
)"
    [ -z "$out" ] || fail "pool $d: $out"
    local n_done
    n_done="$(pool_done "$d")"
    [ "$n_done" = "$ITERS" ] || fail "rl-pool status --json $d: iterations_completed $n_done, expected $ITERS"
}

pool_done() { "$RL_POOL" status "$1" --json | "$PY" -c 'import json,sys; print(json.load(sys.stdin)["iterations_completed"])'; }

same_history() {
    local got
    got="$(pool_history "$1")"
    if [ "$got" != "$REF_HISTORY" ]; then
        diff <(echo "$REF_HISTORY") <(echo "$got") | head -n 20
        fail "$2: selection history differs from the rl-pool launch reference"
    fi
}

wait_gone() {  # wait_gone TIMEOUT JOBID...: until squeue lists none of them (1: timeout or squeue failed)
    local limit="$1" t out; shift
    for ((t = 0; t < limit * 10; t++)); do
        out="$(squeue -h -o %i -j "$(IFS=,; echo "$*")" 2>&1)" || { echo "squeue failed: $out"; return 1; }
        [ -z "$out" ] && return 0
        sleep 0.1
    done
    squeue
    return 1
}

job_states() { scontrol -o show job "$1" 2>/dev/null | sed -n 's/.*JobState=\([A-Z_]*\).*/\1/p' | sort | uniq -c | xargs; }

json_field() { "$PY" -c 'import json,sys
try: print(json.load(open(sys.argv[1])).get(sys.argv[2]))
except (OSError, ValueError): print("")' "$1" "$2"; }

first_deposit_time() {
    "$PY" -c 'import glob,json,sys
print(min(json.load(open(p))["time"] for p in glob.glob(sys.argv[1] + "/iterations/000001/member-[0-9][0-9][0-9].json")))' "$1"
}

member_log_tail() { for m in 000 001; do tail_file "$1/logs/member-$m.log" 5; done; }

# ------------------------------------------------------------------ (a) reference: rl-pool launch
say "(a) reference: rl-pool launch, 2 members, $ITERS iterations"
REF="$WORK/pools/reference"
t0=$(now)
"$RL_POOL" launch --pool-dir "$REF" --pool-size 2 --learning-rates "$LRS_COMMA" "${SETTINGS[@]}" --quiet \
    >"$WORK/launch.out" 2>&1 &
LAUNCH_PID=$!
for ((t = 0; t < 3000; t++)); do kill -0 "$LAUNCH_PID" 2>/dev/null || break; sleep 0.1; done   # 300 s
kill -0 "$LAUNCH_PID" 2>/dev/null && { cat "$WORK/launch.out"; fail "rl-pool launch still running after 300s"; }
wait "$LAUNCH_PID"; rc=$?; LAUNCH_PID=""
LAUNCH_WALL=$(secs "$t0" "$(now)")
[ "$rc" -eq 0 ] || { cat "$WORK/launch.out"; fail "rl-pool launch exited $rc"; }
check_pool "$REF"
REF_HISTORY="$(pool_history "$REF")"
say "    done in ${LAUNCH_WALL}s; final selection: $(tail -n 1 <<< "$REF_HISTORY" | cut -c1-40)..."

# ------------------------------------------------------------------ (b) the job array
say "(b) job array: shell/slurm_submit.sh 2 (sbatch --array=0-1 shell/slurm_pool.sbatch)"
ARR="$WORK/pools/array"
cd "$WORK/submit" || fail "cd $WORK/submit"
t_submit=$(now)
JOB="$(POOL_DIR="$ARR" LEARNING_RATES="$LRS_SPACE" RL_POOL="$RL_POOL" \
       "$ROOT/shell/slurm_submit.sh" 2 "${SETTINGS[@]}")" || fail "sbatch failed: $JOB"
JOB="${JOB%%;*}"
JOBS+=("$JOB")
say "    array job $JOB submitted"
wait_gone 180 "$JOB" || { member_log_tail "$ARR"; fail "array job $JOB not done within 180s"; }
ARRAY_WALL=$(secs "$t_submit" "$(now)")
for a in 0 1; do
    out="$WORK/submit/slurm-logs/rl-pool-${JOB}_$a.out"
    [ -f "$out" ] || fail "no SLURM output file $out"
    grep -q "member $a of 2, lr" "$out" || { cat "$out"; fail "$out does not show member $a starting"; }
done
states="$(job_states "$JOB")"
[ "$states" = "2 COMPLETED" ] || { cat "$WORK"/submit/slurm-logs/*; fail "array tasks ended as: $states"; }
check_pool "$ARR"
same_history "$ARR" "job array"
FIRST_DEPOSIT=$(secs "$t_submit" "$(first_deposit_time "$ARR")")
say "    OK: 2 tasks COMPLETED, $ITERS iterations with both deposits, history identical to (a)"

# ------------------------------------------------------------------ (c) cancel one task, resubmit it
say "(c) job array with task 1 cancelled mid-run and resubmitted alone"
CAN="$WORK/pools/cancel"
JOB="$(POOL_DIR="$CAN" LEARNING_RATES="$LRS_SPACE" RL_POOL="$RL_POOL" \
       sbatch --parsable --array=0-1 "$ROOT/shell/slurm_pool.sbatch" "${SETTINGS[@]}")" || fail "sbatch failed: $JOB"
JOB="${JOB%%;*}"
JOBS+=("$JOB")
HB1="$CAN/members/member-001.json"
at=""
for ((t = 0; t < 3000; t++)); do   # 150 s
    it="$(sed -n 's/^ *"iteration": *\([0-9][0-9]*\).*/\1/p' "$HB1" 2>/dev/null)"
    if [ -n "$it" ] && [ "$it" -ge 3 ]; then at="$it"; break; fi
    [ -z "$(squeue -h -o %i -j "$JOB" 2>/dev/null)" ] && break
    sleep 0.05
done
[ -n "$at" ] || { member_log_tail "$CAN"; fail "member 1 never reached iteration 3"; }
scancel "${JOB}_1" || fail "scancel ${JOB}_1 failed"
t_cancel=$(now)
say "    member 1 at iteration $at: scancel ${JOB}_1"
wait_gone 60 "${JOB}_1" || fail "array task ${JOB}_1 not gone within 60s of scancel"
state1="$(json_field "$HB1" state)"
for ((t = 0; t < 100; t++)); do [ "$state1" = stopped ] && break; sleep 0.1; state1="$(json_field "$HB1" state)"; done
[ "$state1" = stopped ] || { member_log_tail "$CAN"; fail "member 1's heartbeat says '$state1' after scancel, expected 'stopped'"; }
grep -q "stopped by SIGTERM" "$CAN/logs/member-001.log" || fail "member 1's log does not say it was stopped by SIGTERM"
[ "$(job_states "${JOB}_1")" = "1 CANCELLED" ] || fail "task ${JOB}_1 is $(job_states "${JOB}_1"), expected CANCELLED"
sleep 2   # member 0 must now hold at the barrier (quorum 2 of 2), not go on alone
done_at_cancel="$(pool_done "$CAN")"
[ "$done_at_cancel" -lt "$ITERS" ] || fail "the pool finished before the cancel landed (raise ITERS)"
[ -n "$(squeue -h -o %i -j "${JOB}_0")" ] || fail "task ${JOB}_0 ended while member 1 was cancelled (it should wait)"
HB0="$CAN/members/member-000.json"
[ "$(json_field "$HB0" state) $(json_field "$HB0" iteration)" = "waiting $((done_at_cancel + 1))" ] ||
    fail "member 0 is not waiting at iteration $((done_at_cancel + 1)): $(cat "$HB0")"
say "    task 1 CANCELLED, heartbeat 'stopped', pool at iteration $done_at_cancel, task 0 waiting; resubmitting task 1"
t_resubmit=$(now)
JOB2="$(POOL_DIR="$CAN" LEARNING_RATES="$LRS_SPACE" RL_POOL="$RL_POOL" \
        sbatch --parsable --array=1 "$ROOT/shell/slurm_pool.sbatch" "${SETTINGS[@]}")" || fail "sbatch failed: $JOB2"
JOB2="${JOB2%%;*}"
JOBS+=("$JOB2")
wait_gone 180 "$JOB" "$JOB2" || { member_log_tail "$CAN"; fail "jobs $JOB and $JOB2 not done within 180s"; }
[ -f "$WORK/submit/slurm-logs/rl-pool-${JOB2}_1.out" ] || fail "no SLURM output for the resubmitted task"
[ "$(job_states "${JOB}_0")" = "1 COMPLETED" ] || fail "task ${JOB}_0 ended as $(job_states "${JOB}_0")"
[ "$(job_states "$JOB2")" = "1 COMPLETED" ] || fail "resubmitted task $JOB2 ended as $(job_states "$JOB2")"
check_pool "$CAN"
same_history "$CAN" "cancelled and resubmitted array"
WAITS="$("$PY" - "$CAN" "$at" <<'EOF'
import json, sys
d, at = sys.argv[1], int(sys.argv[2])
w = {}
for i in range(max(1, at - 1), at + 2):
    try:
        w[i] = json.load(open(f"{d}/iterations/{i:06d}/member-000.wait.json"))["wait_seconds"]
    except (OSError, ValueError, KeyError):
        pass
print(f"{sum(w.values()):.1f}", " ".join(f"{i}:{s:.2f}s" for i, s in w.items()))
EOF
)"
say "    OK: both tasks COMPLETED, $ITERS iterations with both deposits, history identical to (a)"

# ------------------------------------------------------------------ figures
echo
echo "figures ($ITERS iterations of 2 members, ${SETTINGS[*]:0:8}):"
echo "  submit -> first deposit (array):           ${FIRST_DEPOSIT}s"
echo "  wall: 2-task job array (submit -> done):   ${ARRAY_WALL}s   vs rl-pool launch: ${LAUNCH_WALL}s"
echo "  member 1 cancelled -> resubmitted:         $(secs "$t_cancel" "$t_resubmit")s"
echo "  pool waited while member 1 was cancelled:  ${WAITS%% *}s (member 0's wait_seconds, iterations ${WAITS#* })"
echo "PASS"
exit 0
