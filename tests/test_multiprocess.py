"""Real pools: members are separate OS processes on one real directory; kills are real SIGKILLs."""

import itertools
import json
import os
import signal
import time

import numpy as np
import pytest

from rl_pool import Agent
from rl_pool.protocol import heartbeat, selection

from .conftest import SHORT, past_its_deposit, rl_pool, spawn
from .helpers import ITERS, history, run_pool

pytestmark = pytest.mark.multiprocess


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("ref") / "pool"
    return d, run_pool(d)


def test_two_member_pool_end_to_end(reference):
    d, hist = reference
    hist = hist[:-1]  # the last entry is best.json
    assert len(hist) == ITERS
    best = (None, float("-inf"))
    for i, (member, ret, sha, deps, winner) in enumerate(hist, start=1):
        assert set(deps) == {0, 1}, f"iteration {i} lacks a deposit"
        # both members re-scored the parent on the same episodes, and agree
        parent = deps[0][4]
        assert deps[1][4] == parent
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        # the bar: the parent's score, and after a merge the fallback's (re-scored beside it); the
        # branches at or above it are merged, one alone wins, none leaves the better of the two
        fallback = (sel.get("fallback") or {}).get("eval_return")
        bar = parent if fallback is None else max(parent, fallback)
        above = sorted((m for m in deps if deps[m][0] >= bar), key=lambda m: (-deps[m][0], m))
        if not above:
            won = "fallback" if fallback is not None and fallback > parent else "parent"
            assert (winner, member, ret) == (won, None, max(parent, fallback or parent))
            if won == "parent":
                assert sha == hist[i - 2][2] if i > 1 else True
        elif len(above) == 1:
            assert (winner, member, ret) == ("branch", above[0], deps[above[0]][0])
        else:  # a merge: scored next iteration; the best evaluated branch stands for it meanwhile
            assert (winner, member, ret) == ("merge", None, deps[above[0]][0])
            assert sel["merge"]["members"] == above and sha not in (deps[0][2], deps[1][2])
        if i == 1:
            assert deps[0][3] == 0.003 and deps[1][3] == 0.03
        else:  # --lr-adapt 2: the loser of i-1 takes the winner's rate x2 or /2, the winner keeps its own
            prev_winner, prev_deps = hist[i - 2][0], hist[i - 2][3]
            for m in (0, 1):
                if prev_winner is None or m == prev_winner:  # the parent won: nobody lost to a branch, rates stay
                    assert deps[m][3] == prev_deps[m][3]
                else:
                    assert deps[m][3] / prev_deps[prev_winner][3] in (pytest.approx(2.0), pytest.approx(0.5))
        assert sel["quorum_reason"] == "complete" and sel["skipped"] == []
        if ret > best[1]:
            best = (i, ret)
    # the run covers every outcome, so the kill/restart tests below replay merges and parent wins too
    assert {h[4] for h in hist} >= {"branch", "parent", "merge"}, {h[4] for h in hist}
    b = json.loads((d / "best.json").read_text())
    assert (b["iteration"], b["eval_return"]) == best
    Agent.load(d / "best.npz")
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert st["iterations_completed"] == ITERS
    assert {m["state"] for m in st["members"]} == {"finished"}
    # Member 1 continued from the selection: its iteration-2 parent is iteration 1's winner.
    dep = json.loads((d / "iterations/000002/member-001.json").read_text())
    assert dep["parent"] == {"iteration": 1, "member": hist[0][0]}


def test_same_settings_twice_give_the_same_history(reference, tmp_path):
    _, hist = reference
    assert run_pool(tmp_path / "again") == hist


@pytest.mark.parametrize("sig, state", [(signal.SIGKILL, "training"), (signal.SIGKILL, "waiting"),
                                        (signal.SIGTERM, "training")])
def test_kill_and_restart_reproduces_the_uninterrupted_history(reference, tmp_path, sig, state):
    _, hist = reference
    d = tmp_path / "killed"
    args = ["--pool-size", 2, "--iterations", ITERS, *SHORT, "--quiet", "--lr-adapt", 2, "--seed", 3, "--merge", "sum"]
    m0 = spawn("train", "--pool-dir", d, "--member", 0, "--learning-rate", 0.003, *args)
    m1 = spawn("train", "--pool-dir", d, "--member", 1, "--learning-rate", 0.03, *args)
    hb = d / "members/member-001.json"
    deadline = time.time() + 120
    killed_at = None
    while time.time() < deadline:
        if state == "waiting":
            at = past_its_deposit(d, 1, since=3, at_latest=ITERS - 1)
        else:
            try:
                doc = json.loads(hb.read_text())
            except (OSError, ValueError):
                doc = {}
            at = doc["iteration"] if doc.get("state") == state and (doc.get("iteration") or 0) >= 3 else None
        if at is not None:
            m1.send_signal(sig)
            killed_at = at
            break
        time.sleep(0.001)
    assert killed_at is not None, f"member 1 never was {state} in iteration >= 3"
    m1.wait()
    if sig == signal.SIGTERM:  # a clean stop: exit 143, heartbeat says so
        assert m1.returncode == 128 + signal.SIGTERM
        hb_doc = json.loads(hb.read_text())
        assert hb_doc["state"] == "stopped" and "SIGTERM" in hb_doc["error"]
    else:
        assert m1.returncode == -signal.SIGKILL
    assert m0.poll() is None  # member 0 waits for it: quorum 2 of 2
    # a killed writer may leave a temp file: plant one too, it must be ignored and cleaned
    host = heartbeat.HOST.split(".")[0]
    (d / f"iterations/{killed_at:06d}/.member-001.npz.tmp-{host}-{m1.pid}-deadbeef").write_bytes(b"half")
    m1 = spawn("train", "--pool-dir", d, "--member", 1, "--learning-rate", 0.03, *args)
    for p in (m0, m1):
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    assert history(d) == hist
    leftovers = [n for dp, _, fs in os.walk(d) for n in fs if ".tmp-" in n]
    assert leftovers == []


def test_member_that_never_comes_back_quorum_lets_the_other_go_on(tmp_path):
    d = tmp_path / "alone"
    proc = rl_pool("train", "--pool-dir", d, "--pool-size", 2, "--member", 0, "--iterations", 3, *SHORT,
                   "--quorum", 1, "--heartbeat-timeout", 1, "--quiet", check=0)
    assert proc.returncode == 0
    for i in (1, 2, 3):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert [c["member"] for c in sel["considered"]] == [0] and sel["winner"] in ("branch", "parent")
        assert sel["member"] == (0 if sel["winner"] == "branch" else None)
        assert sel["skipped"] == [{"member": 1, "reason": "missing"}]
        assert "stale" in sel["quorum_reason"] and "member 1 heartbeat unchanged" in sel["quorum_reason"]
    assert "went on without stale members" in (d / "logs/member-000.log").read_text()


def test_member_left_behind_rejoins_where_the_pool_is(tmp_path):
    d = tmp_path / "catchup"
    args = ["--pool-size", 2, *SHORT, "--quorum", 1, "--heartbeat-timeout", 1, "--quiet"]
    # member 1 runs alone (quorum 1) to iteration 1 and stops; member 0 then goes on to 5 without it
    rl_pool("train", "--pool-dir", d, "--member", 1, *args, "--iterations", 1, check=0)
    rl_pool("train", "--pool-dir", d, "--member", 0, *args, "--iterations", 5, check=0)
    sel = json.loads((d / "iterations/000003/selected.json").read_text())
    assert sel["skipped"] == [{"member": 1, "reason": "missing"}]
    assert "member 1 finished" in sel["quorum_reason"]
    # now member 1 comes back with a larger target and rejoins where the pool is
    rl_pool("train", "--pool-dir", d, "--member", 1, *args, "--iterations", 6, check=0)
    dep = json.loads((d / "iterations/000006/member-001.json").read_text())
    assert dep["parent"]["iteration"] == 5
    assert not (d / "iterations/000004/member-001.json").exists()


def test_in_a_larger_pool_three_members_in_turn_re_score_the_parent(tmp_path):
    """N = 4: each iteration exactly the members ``scores_parent`` names report the parent's score,
    their reports agree (same agent, same episodes), and the selection compares with it."""
    d = tmp_path / "four"
    n, iters = 4, 4
    procs = [spawn("train", "--pool-dir", d, "--pool-size", n, "--member", m, "--learning-rate", 0.05,
                   "--iterations", iters, *SHORT, "--quiet", "--merge", "sum") for m in range(n)]
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    for i in range(1, iters + 1):
        docs = [json.loads((d / f"iterations/{i:06d}/member-{m:03d}.json").read_text()) for m in range(n)]
        scorers = [m for m, doc in enumerate(docs) if "parent_eval_return" in doc]
        assert scorers == [m for m in range(n) if selection.scores_parent(i, m, n)] and len(scorers) == 3
        assert len({docs[m]["parent_eval_return"] for m in scorers}) == 1
        assert all(docs[m]["parent_eval_steps"] > 0 for m in scorers)
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert sel["parent"]["eval_return"] == docs[scorers[0]]["parent_eval_return"]
        prev = json.loads((d / f"iterations/{i - 1:06d}/selected.json").read_text())
        bar = sel["parent"]["eval_return"]
        if prev.get("winner") == "merge":  # the same scorers re-scored the merge's fallback, and agree
            assert len({docs[m]["fallback_eval_return"] for m in scorers}) == 1
            assert sel["fallback"]["eval_return"] == docs[scorers[0]]["fallback_eval_return"]
            bar = max(bar, sel["fallback"]["eval_return"])
        above = sorted((m for m in range(n) if docs[m]["eval_return"] >= bar), key=lambda m: -docs[m]["eval_return"])
        assert sel["winner"] in ({"merge"} if len(above) > 1 else {"branch"} if above else {"parent", "fallback"})
        assert sel["winner"] != "merge" or sel["merge"]["members"] == above


def test_an_adaptive_pool_merges_with_the_scale_its_selections_carry(tmp_path):
    """N = 4 with the default merge: each selection's merge scale follows from its parent's and the
    verdict on the parent (a merge) against its fallback, and three or more branches at the bar are
    merged with that scale capped at their number."""
    d = tmp_path / "adaptive"
    n, iters = 4, 6
    procs = [spawn("train", "--pool-dir", d, "--pool-size", n, "--member", m, "--learning-rate", 0.3,
                   "--iterations", iters, *SHORT, "--quiet") for m in range(n)]
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    winners = []
    for i in range(1, iters + 1):
        prev = json.loads((d / f"iterations/{i - 1:06d}/selected.json").read_text())
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        verdict = sel.get("fallback", {}).get("score")
        if prev.get("winner") == "merge" and verdict is not None:
            want = selection.next_scale(prev, sel["parent"]["score"], verdict, n)
        else:
            want = selection.carried_scale(prev, n)
        assert sel["merge_scale"] == want
        if sel["winner"] == "merge":
            assert sel["merge"]["kind"] == "adaptive" and len(sel["merge"]["members"]) >= 3
            assert sel["merge"]["scale"] == min(sel["merge_scale"], len(sel["merge"]["members"]))
        winners.append(sel["winner"])
    assert "merge" in winners, winners


def test_best_score_mean_with_branches_re_scores_each_new_best_and_revert(tmp_path):
    """Real members, branches only, ``--best-score mean``: they re-score the parent exactly in the
    iterations after it became the best or was reverted to, and the best's mean is its first score
    and those re-scores."""
    d = tmp_path / "mean"
    iters = 10
    procs = [spawn("train", "--pool-dir", d, "--pool-size", 2, "--member", m, "--learning-rate", lr,
                   "--iterations", iters, *SHORT, "--quiet", "--selection", "branches", "--revert-after", 2,
                   "--best-score", "mean") for m, lr in enumerate((0.1, 1.0))]
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    sels = [json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for i in range(iters + 1)]
    scores = {}  # every score of each agent that was the best: first, then re-scores
    for i in range(1, iters + 1):
        prev, sel = sels[i - 1], sels[i]
        docs = [json.loads((d / f"iterations/{i:06d}/member-{m:03d}.json").read_text()) for m in range(2)]
        rescored = isinstance(prev.get("best"), dict) and prev["best"]["agent_sha256"] == prev["agent_sha256"]
        assert [("parent_eval_return" in doc) for doc in docs] == [rescored] * 2
        if rescored:
            assert docs[0]["parent_eval_return"] == docs[1]["parent_eval_return"] == sel["parent"]["eval_return"]
            scores[prev["agent_sha256"]].append(sel["parent"]["eval_return"])
        assert sel["winner"] in ("branch", "revert")  # a re-score never competes
        if sel["best"]["iteration"] == i:
            scores[sel["agent_sha256"]] = [sel["eval_return"]]
        mine = scores[sel["best"]["agent_sha256"]]
        assert sel["best"]["scores"] == len(mine) and sel["best"]["mean_score"] == pytest.approx(np.mean(mine))
    assert sum(len(v) - 1 for v in scores.values()) >= 1
    assert any(sel["winner"] == "revert" for sel in sels[1:])


def test_hostile_deposits_in_a_live_pool_are_skipped_and_never_run(tmp_path):
    import io

    d = tmp_path / "hostile"
    marker = tmp_path / "code-ran"
    # Members 0 and 1 are real; "member 2" is an attacker who pre-plants its deposits.
    procs = [spawn("train", "--pool-dir", d, "--pool-size", 3, "--member", m, "--iterations", 4, *SHORT,
                   "--quiet") for m in (0, 1)]
    deadline = time.time() + 60
    while not (d / "iterations/000000/selected.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    from .helpers import Evil, agent

    with np.load(io.BytesIO(agent().to_bytes())) as z:
        arrays = {k: z[k] for k in z.files}
    buf = io.BytesIO()
    np.savez(buf, **(arrays | {"param.w": np.array([Evil(marker)], dtype=object)}))
    import hashlib

    data = buf.getvalue()
    for i in range(1, 5):
        it = d / f"iterations/{i:06d}"
        it.mkdir(parents=True, exist_ok=True)
        if i % 2:
            (it / "member-002.npz").write_bytes(data)
            (it / "member-002.json").write_text(json.dumps(
                {"iteration": i, "member": 2, "eval_return": 1e12, "agent_sha256": hashlib.sha256(data).hexdigest()}))
        else:
            (it / "member-002.json").write_text("{\"eval_return\": 1e300,")
        (it / "member-099.json").write_text("{}")  # a stray: ignored
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    for i in range(1, 5):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert sel["member"] in ((0, 1) if sel["winner"] == "branch" else (None,))
        (skip,) = sel["skipped"]
        assert skip["member"] == 2 and skip["reason"] != "missing"
    assert not marker.exists()


def test_launch_runs_the_pool_and_reports(tmp_path):
    d = tmp_path / "launched"
    proc = rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--iterations", 3, *SHORT,
                   "--learning-rate", 0.02, check=0)
    assert "iterations completed 3" in proc.stdout
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    lrs = {m["member"]: m["learning_rate"] for h in st["history"] for m in h["members"]}
    assert lrs == {0: pytest.approx(0.002), 1: 0.02}


def test_a_resumed_launch_keeps_the_rates_the_pool_ran_with(tmp_path):
    d = tmp_path / "resumed"
    rl_pool("launch", "--pool-dir", d, "--iterations", 2, *SHORT, "--learning-rates", "0.003,0.02", "--quiet",
            check=0)
    again = rl_pool("launch", "--pool-dir", d, "--iterations", 3, "--quiet", check=0)  # no rates given
    assert "m0=0.003, m1=0.02 (as the pool ran" in again.stdout
    rl_pool("launch", "--pool-dir", d, "--iterations", 4, "--learning-rates", "0.001,0.01", "--quiet", check=0)
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    lrs = [{m["member"]: m["learning_rate"] for m in h["members"]} for h in st["history"]]
    assert lrs == [{0: 0.003, 1: 0.02}] * 3 + [{0: 0.001, 1: 0.01}]  # rates given on a resume still win


def test_member_that_falls_behind_rejoins_the_current_iteration(tmp_path):
    """A member frozen (SIGSTOP) while the pool goes on skips the decided iterations when it wakes."""
    d = tmp_path / "frozen"
    args = ["--pool-size", 2, "--iterations", 10, *SHORT, "--quorum", 1, "--heartbeat-timeout", 1, "--quiet"]
    m0 = spawn("train", "--pool-dir", d, "--member", 0, *args)
    m1 = spawn("train", "--pool-dir", d, "--member", 1, *args)
    hb = d / "members/member-001.json"
    deadline = time.time() + 120
    while time.time() < deadline:
        try:
            doc = json.loads(hb.read_text())
        except (OSError, ValueError):
            doc = {}
        if doc.get("state") == "training" and doc.get("iteration") == 2:
            break
        time.sleep(0.001)
    m1.send_signal(signal.SIGSTOP)
    while not (d / "iterations/000006/selected.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    m1.send_signal(signal.SIGCONT)
    for p in (m0, m1):
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    dep = sorted(i for i in range(1, 11) if (d / f"iterations/{i:06d}/member-001.json").exists())
    # it finishes the iteration it was in, then rejoins where the pool is: no deposits in between
    assert dep[:2] == [1, 2] and dep[-1] == 10
    gap = set(range(3, 6)) & set(dep)
    assert not gap, f"member 1 redid decided iterations {sorted(gap)}"
    assert "rejoining at iteration" in (d / "logs/member-001.log").read_text()


@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGINT, signal.SIGINT)], ids=["term", "int-twice"])
def test_launch_forwards_sigterm_to_its_members(tmp_path, signals):
    """One signal, or two at once (a double Ctrl-C; GNU timeout signals the process and its group):
    the members are stopped either way, never left training unattended."""
    d = tmp_path / "term"
    launcher = spawn("launch", "--pool-dir", d, "--pool-size", 2, "--iterations", 500, *SHORT)
    deadline = time.time() + 120
    while not (d / "iterations/000002/selected.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    pids = [json.loads((d / f"members/member-{m:03d}.json").read_text())["pid"] for m in (0, 1)]
    for sig in signals:
        launcher.send_signal(sig)
    launcher.communicate(timeout=60)
    assert launcher.returncode == 130
    for m, pid in enumerate(pids):
        assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()
        assert json.loads((d / f"members/member-{m:03d}.json").read_text())["state"] == "stopped"


@pytest.mark.parametrize("output", ["pipe", "closed"])
def test_launch_surfaces_a_failed_member(tmp_path, output):
    """Also when its output has closed (`launch | head`): the launcher keeps watching and still
    exits 1, where a failed print of its summary once made it exit 0 or 2."""
    import subprocess
    import sys

    from .conftest import ROOT

    d = tmp_path / "failing"
    rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--iterations", 1, *SHORT, check=0)
    # Corrupt the selected agent's file: every member needs it to train the next iteration.
    sel = json.loads((d / "iterations/000001/selected.json").read_text())
    (d / sel["agent"]).write_bytes(b"garbage")
    r, w = os.pipe()
    if output == "closed":
        os.close(r)  # the reader is gone before the launcher writes a byte
    try:
        proc = subprocess.run([sys.executable, "-m", "rl_pool", "launch", "--pool-dir", str(d), "--iterations", "3",
                               "--barrier-timeout", "30"], stdout=w, stderr=subprocess.PIPE, text=True,
                              timeout=180, cwd=ROOT)
    finally:
        os.close(w)
        if output == "pipe":
            os.close(r)
    assert proc.returncode == 1, proc.stderr
    assert "failed" in proc.stderr and "does not match the hash" in proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr


def test_shell_pool_script_stops_on_signal_and_resumes(tmp_path):
    """shell/pool.sh: per-member learning rates from its bash array, TERM stops all, re-running resumes."""
    import subprocess

    from .conftest import ROOT

    d = tmp_path / "shell"
    env = dict(os.environ, POOL_DIR=str(d), N="2", LEARNING_RATES="0.02 0.2", ITERATIONS="500")
    script = os.path.join(ROOT, "shell", "pool.sh")
    proc = subprocess.Popen(["bash", script, *map(str, SHORT)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (d / "iterations/000002/selected.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    for m in (0, 1):
        assert json.loads((d / f"members/member-{m:03d}.json").read_text())["state"] == "stopped"
    done = json.loads(rl_pool("status", d, "--json", check=0).stdout)["iterations_completed"]
    env["ITERATIONS"] = str(done + 2)
    again = subprocess.run(["bash", script, *map(str, SHORT)], env=env, capture_output=True, text=True,
                           timeout=120)
    assert again.returncode == 0, again.stderr
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    assert st["iterations_completed"] == done + 2
    lrs = {m["member"]: m["learning_rate"] for h in st["history"] for m in h["members"]}
    assert lrs == {0: 0.02, 1: 0.2}


def _run_with_a_kill(d, lrs, args, victim, kill_at):
    """Members at rates ``lrs`` in the pool ``d``; with ``kill_at``, member ``victim`` is killed with
    SIGKILL while it trains in an iteration >= ``kill_at`` and started again. Returns when all are done."""

    def start(m):
        return spawn("train", "--pool-dir", d, "--member", m, "--learning-rate", lrs[m], *args)

    procs = [start(m) for m in range(len(lrs))]
    if kill_at is not None:
        _kill_while_training(d, victim, procs[victim], kill_at)
        procs[victim] = start(victim)
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err


def _kill_while_training(d, m, proc, kill_at):
    """SIGKILL member ``m`` (process ``proc``) of the pool in ``d`` while its heartbeat says it trains in an
    iteration >= ``kill_at``."""
    hb = d / f"members/member-{m:03d}.json"
    deadline, killed = time.time() + 120, False
    while time.time() < deadline and not killed:
        try:
            doc = json.loads(hb.read_text())
        except (OSError, ValueError):
            doc = {}
        if doc.get("state") == "training" and (doc.get("iteration") or 0) >= kill_at:
            proc.send_signal(signal.SIGKILL)
            killed = True
        time.sleep(0.001)
    assert killed, f"member {m} never trained in a late enough iteration"
    proc.wait()
    assert proc.returncode == -signal.SIGKILL


def _momentum_pool(d, kill_at=None):
    """A 4-member pool with ``--merge momentum``; with ``kill_at``, member 2 is killed with SIGKILL
    while it trains in an iteration >= ``kill_at`` and started again."""
    n, iters = 4, 6
    args = ["--pool-size", n, "--iterations", iters, *SHORT, "--quiet", "--seed", 0, "--merge", "momentum",
            "--quorum", n]  # the others wait for a killed member: the uninterrupted history

    _run_with_a_kill(d, [0.03] * n, args, 2, kill_at)
    return [json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for i in range(1, iters + 1)]


def test_a_momentum_pool_killed_and_restarted_replays_its_merges(tmp_path):
    """N = 4 with --merge momentum: a merge right after a merge takes beta times the pool's last step
    (named by its file and hash), and a member killed with SIGKILL mid-iteration and started again
    gives the same selections, merged agents' hashes included."""
    sels = _momentum_pool(tmp_path / "whole")
    with_momentum = [s for s in sels if s["winner"] == "merge" and "beta" in s["merge"].get("momentum", {})]
    assert with_momentum, [s["winner"] for s in sels]
    for prev, sel in itertools.pairwise(sels):
        if sel["winner"] == "merge":
            if prev["winner"] == "merge":
                assert sel["merge"]["momentum"] == {"beta": 0.5, "from": {
                    "iteration": prev["parent"]["iteration"], "agent": prev["parent"]["agent"],
                    "agent_sha256": prev["parent"]["agent_sha256"]}}
            else:
                assert "momentum" not in sel["merge"]
    again = _momentum_pool(tmp_path / "killed", kill_at=3)
    keys = ("winner", "member", "eval_return", "agent_sha256", "merge", "considered", "parent", "fallback")
    assert [{k: s.get(k) for k in keys} for s in again] == [{k: s.get(k) for k in keys} for s in sels]


def _rate_pool(d, kill_at=None):
    """A 2-member pool whose rates follow its progress (``--rate-patience 1``): every iteration
    without a new best halves them, and a linear decay over 10 iterations (``--rate-anneal 10``) scales
    them further. With ``kill_at``, member 1 is killed with SIGKILL while it trains in an iteration >=
    ``kill_at`` and started again."""
    iters = 8
    args = ["--pool-size", 2, "--iterations", iters, *SHORT, "--quiet", "--seed", 1, "--rate-patience", 1,
            "--rate-anneal", 10]

    _run_with_a_kill(d, [0.03, 0.3], args, 1, kill_at)
    return [json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for i in range(iters + 1)]


def test_rates_that_follow_the_pool_train_every_branch_and_replay_after_a_kill(tmp_path):
    """``--rate-patience``: each selection's rate follows from the one before and whether it found a new
    best; each member trains at its rate times the scale its parent selection carries and the
    iteration's share under ``--rate-anneal`` (retraining a branch in this process at that rate gives
    its deposit's parameters exactly, at the rate given other ones); a member killed mid-iteration and
    started again replays the same selections."""
    from rl_pool.config import PoolConfig
    from rl_pool.learning import envs, trainer

    d = tmp_path / "whole"
    sels = _rate_pool(d)
    cfg = PoolConfig.from_json(json.loads((d / "pool.json").read_text()))
    scales = []
    for prev, sel in itertools.pairwise(sels):
        assert sel["rate"] == selection.next_rate(prev, sel, 1, 0.5)
        i = sel["iteration"]
        for m in range(2):
            doc = json.loads((d / f"iterations/{i:06d}/member-{m:03d}.json").read_text())
            assert doc["learning_rate"] == (0.03, 0.3)[m]
            assert doc["rate_scale"] == selection.rate_scale(prev) * (1.0 - (i - 1) / 10)
        scales.append(doc["rate_scale"])
    # retrain a branch where the patience had halved the rates, so both shares enter the rate checked
    patience = [selection.rate_scale(prev) for prev in sels[:-1]]
    assert min(patience) < 1.0, patience
    i = next(k for k, s in enumerate(patience, start=1) if s < 1.0)
    parent = Agent.load(d / sels[i - 1]["agent"])
    dep = Agent.load(d / f"iterations/{i:06d}/member-001.npz")
    env_list = [envs.make(cfg.env, dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps))[0]
                for _ in range(max(cfg.batch_episodes, cfg.eval_episodes))]
    scaled = trainer.train(parent, env_list, cfg, 0.3 * scales[i - 1], 1, i).agent
    given = trainer.train(parent, env_list, cfg, 0.3, 1, i).agent
    for name in dep.params:
        np.testing.assert_array_equal(scaled.params[name], dep.params[name])
    assert any(not np.array_equal(given.params[n], dep.params[n]) for n in dep.params)
    again = _rate_pool(tmp_path / "killed", kill_at=3)
    keys = ("winner", "member", "eval_return", "agent_sha256", "rate", "considered", "parent")
    assert [{k: s.get(k) for k in keys} for s in again] == [{k: s.get(k) for k in keys} for s in sels]


def _check_sharpened_starts(d, sels, n, want, member):
    """Each deposit of the pool ``d`` records the factor ``want(previous selection)`` gives its member
    (a list of n), and retraining ``member`` at rate 0.3 from its iteration's start sharpened that much,
    in the first iteration that sharpens, gives its deposit's parameters exactly. Returns the
    iterations that sharpened."""
    from rl_pool.config import PoolConfig
    from rl_pool.learning import envs, trainer
    from rl_pool.maths import policy

    cfg = PoolConfig.from_json(json.loads((d / "pool.json").read_text()))
    sharpened = []
    for prev, sel in itertools.pairwise(sels):
        i = sel["iteration"]
        got = [json.loads((d / f"iterations/{i:06d}/member-{m:03d}.json").read_text())["sharpen"] for m in range(n)]
        assert got == pytest.approx(want(prev), rel=1e-12), i
        if got != [1.0] * n:
            sharpened.append(i)
    assert sharpened, [s.get("winner") for s in sels]
    i = sharpened[0]
    start = Agent.load(d / sels[i - 1]["agent"])
    dep = Agent.load(d / f"iterations/{i:06d}/member-{member:03d}.npz")
    env_list = [envs.make(cfg.env, dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps))[0]
                for _ in range(max(cfg.batch_episodes, cfg.eval_episodes))]
    sharp = start.evolve(params=policy.sharpened(start.params, start.spec, want(sels[i - 1])[member]))
    for name, value in trainer.train(sharp, env_list, cfg, 0.3, member, i).agent.params.items():
        np.testing.assert_array_equal(value, dep.params[name])
    return sharpened


def _revert_sharpen_pool(d, kill_at=None):
    """A 2-member pool of competing branches that goes back to its best after every iteration without
    a new one (``--revert-after 1``) with less action noise (``--revert-sharpen 4``); with ``kill_at``, member 1
    is killed with SIGKILL while it trains in an iteration >= ``kill_at`` and started again."""
    iters = 8
    args = ["--pool-size", 2, "--iterations", iters, *SHORT, "--quiet", "--seed", 1, "--selection", "branches",
            "--revert-after", 1, "--revert-sharpen", 4]
    _run_with_a_kill(d, [0.03, 0.3], args, 1, kill_at)
    return [json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for i in range(iters + 1)]


def test_a_revert_with_less_noise_trains_every_branch_from_the_sharpened_best_and_replays_after_a_kill(tmp_path):
    """``--revert-sharpen``: after a revert every member starts from the best agent with its Beta shapes'
    excess over 1 times 4 and says so in its deposit (retraining member 1 here from the sharpened best
    gives its deposit's parameters exactly); after other iterations no member sharpens; a member killed
    mid-iteration and started again replays the same selections."""
    d = tmp_path / "whole"
    sels = _revert_sharpen_pool(d)
    reverted = _check_sharpened_starts(d, sels, 2, lambda prev: [4.0, 4.0] if prev.get("winner") == "revert"
                                       else [1.0, 1.0], member=1)
    i = reverted[0]
    assert sels[i - 1]["winner"] == "revert" and sels[i - 1]["agent"] == sels[i - 1]["best"]["agent"]
    again = _revert_sharpen_pool(tmp_path / "killed", kill_at=reverted[0])
    keys = ("winner", "member", "eval_return", "agent_sha256", "best", "considered")
    assert [{k: s.get(k) for k in keys} for s in again] == [{k: s.get(k) for k in keys} for s in sels]


def _sharpen_pool(d, kill_at=None):
    """A 3-member pool that sharpens its branches after the parent is kept (``--sharpen 4``); with
    ``kill_at``, member 2 is killed with SIGKILL while it trains in an iteration >= ``kill_at``."""
    n, iters = 3, 8
    args = ["--pool-size", n, "--iterations", iters, *SHORT, "--quiet", "--seed", 2, "--merge", "momentum",
            "--sharpen", 4, "--quorum", n]
    _run_with_a_kill(d, [0.03, 0.3, 0.3], args, 2, kill_at)
    return [json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for i in range(iters + 1)]


def test_sharper_branches_after_a_kept_parent_train_from_the_files_and_replay_after_a_kill(tmp_path):
    """``--sharpen``: after an iteration that kept the parent, member m of 3 starts from it with its Beta
    shapes' excess over 1 times 4^(m/2) and says so in its deposit (retraining member 2 here from the
    sharpened parent gives its deposit's parameters exactly); after other iterations no member
    sharpens; a member killed mid-iteration and started again replays the same selections."""
    d = tmp_path / "whole"
    sels = _sharpen_pool(d)
    kept = _check_sharpened_starts(d, sels, 3, lambda prev: [1.0, 2.0, 4.0]
                                   if prev.get("winner") in ("parent", "fallback") else [1.0, 1.0, 1.0], member=2)
    again = _sharpen_pool(tmp_path / "killed", kill_at=kept[0])
    keys = ("winner", "member", "eval_return", "agent_sha256", "merge", "considered", "parent")
    assert [{k: s.get(k) for k in keys} for s in again] == [{k: s.get(k) for k in keys} for s in sels]
