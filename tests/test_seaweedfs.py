"""A real distributed filesystem: SeaweedFS with two FUSE mounts standing in for two hosts.

One ``weed server`` (master, volume server, filer) and two ``weed mount``s of its root
(tests/seaweed.py). On SeaweedFS 4.48, ``link`` and ``O_EXCL`` are decided by each mount
alone, so they are not exclusive across mounts; directory renames are decided by the
filer. Skipped, with the reason, without root, /dev/fuse, fusermount or the weed binary.
"""

import json
import multiprocessing as mp
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rl_pool.protocol import claim

from .conftest import ROOT, SHORT, spawn
from .helpers import racer, tree_remover
from .seaweed import Seaweed, unavailable

# real processes on a real cluster: out of the fast tiers (-m 'not multiprocess'); -m seaweedfs runs it alone
pytestmark = [pytest.mark.seaweedfs, pytest.mark.multiprocess]


@pytest.fixture(scope="module")
def seaweed(tmp_path_factory):
    why = unavailable()
    if why:
        pytest.skip(why)
    sw = Seaweed(tmp_path_factory.mktemp("seaweed"), mounts=2)
    try:
        sw.start()
        yield sw
    finally:
        sw.stop()


def _same_dir(sw, name):
    """``name`` created through mount A, and its paths through mounts A and B."""
    a, b = (os.path.join(m, name) for m in sw.mounts)
    os.makedirs(a)
    deadline = time.time() + 10
    while not os.path.isdir(b) and time.time() < deadline:
        time.sleep(0.01)
    return a, b


def _read(path) -> bytes | None:
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError:
        return None


def _eventually(fn, timeout=5.0):
    deadline = time.time() + timeout
    while True:
        try:
            got = fn()
        except OSError:  # a name just replaced through the other mount can vanish here for a moment
            got = None
        if got or time.time() > deadline:
            return got
        time.sleep(0.02)


def test_doctor_on_both_mounts_at_once_finds_the_link_race_and_exclusive_renames(seaweed):
    a, b = _same_dir(seaweed, "doctor")
    cmd = [sys.executable, "-m", "rl_pool.protocol.doctor", "--peer", "--rounds", "30", "--json",
           "--peer-timeout", "60"]
    procs = [subprocess.Popen([*cmd, d], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=ROOT) for d in (a, b)]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err + out
    ra, rb = (json.loads(out) for out, _ in outs)
    assert ra["filesystem"]["type"] == rb["filesystem"]["type"] == "fuse.seaweedfs"
    assert ra["race"]["primitives"] == rb["race"]["primitives"]  # both report the same race
    prims = ra["race"]["primitives"]
    # what rl-pool decides with: one winner in every round, both mounts read it
    for p in ("rename-dir", "mkdir"):
        assert prims[p]["exclusive"] and prims[p]["exactly_one"] == 30, (p, prims[p])
    # what it no longer uses: both mounts "create" the same name
    assert prims["link"]["both_won"] + prims["excl"]["both_won"] > 0, prims
    assert any("not exclusive" in n for n in ra["notes"])
    assert ra["safe"] and rb["safe"]
    assert _eventually(lambda: os.listdir(a) == []), os.listdir(a)  # the meeting place is gone


def _race(target, args: list[tuple]) -> list:
    """Run ``target(*a, barrier, out)`` for each ``a`` in spawned processes sharing one barrier and
    one queue; what they put on the queue, in the order it came."""
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(len(args)), ctx.Queue()
    procs = [ctx.Process(target=target, args=(*a, barrier, out)) for a in args]
    for p in procs:
        p.start()
    got = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0
    return got


def _tree(root: str, dirs: int = 8, files: int = 3) -> str:
    """A tree of ``dirs`` nested directories of ``files`` files under ``root``; its last directory,
    relative to ``root``."""
    for k in range(dirs):
        sub = os.path.join(f"d{k}", "inner")
        os.makedirs(os.path.join(root, sub))
        for j in range(files):
            with open(os.path.join(root, sub, f"f{j}"), "wb") as fh:
                fh.write(b"x")
    return sub


def test_both_mounts_removing_one_tree_at_once_neither_fails_and_it_is_gone(seaweed):
    # The doctor's two runs both remove their meeting place when they are done; on these mounts
    # plain rmtree(ignore_errors=True) raised FileNotFoundError in Python 3.11 when the other
    # mount removed the same tree under it.
    a, b = _same_dir(seaweed, "trees")
    rounds = 12
    last = [_tree(os.path.join(a, f"t{r}")) for r in range(rounds)]
    assert _eventually(lambda: all(os.path.isdir(os.path.join(b, f"t{r}", last[r])) for r in range(rounds)),
                       timeout=10)
    removers = [([os.path.join(root, f"t{r}") for r in range(rounds)],) for root in (a, b, a, b)]
    assert _race(tree_remover, removers) == [None] * len(removers)
    assert _eventually(lambda: os.listdir(a) == [] and os.listdir(b) == [], timeout=10), (os.listdir(a),
                                                                                         os.listdir(b))


def test_claims_racing_from_both_mounts_have_one_winner_that_both_mounts_read(seaweed):
    a, b = _same_dir(seaweed, "claims")
    names, per_mount = 30, 2
    roots = [a, b] * per_mount
    got = dict(_race(racer, [(root, names, me) for me, root in enumerate(roots)]))
    mounts_won = set()
    for k in range(names):
        results = [got[me][k] for me in range(len(roots))]
        winners = [me for me, (_, won) in enumerate(results) if won]
        assert len(winners) == 1, f"name {k}: winners {winners}"
        decided = results[winners[0]][0]
        assert all(data == decided for data, _ in results), f"name {k}: racers hold different bytes"
        mounts_won.add(roots[winners[0]])
        for root in (a, b):
            path = os.path.join(root, f"d{k:03d}.json")
            assert _eventually(lambda p=path, x=decided: claim.read_once(p) == x), f"{path}: decision"
            assert _eventually(lambda p=path, x=decided: _read(p) == x), f"{path}: plain copy"
    assert mounts_won == {a, b}, "one mount won every race: no real contention"


def test_pool_with_members_on_two_mounts_makes_one_decision_per_iteration(seaweed):
    a, b = _same_dir(seaweed, "pool")
    iters = 4
    mounts = {0: a, 1: b, 2: a}
    procs = [spawn("train", "--pool-dir", mounts[m], "--pool-size", 3, "--member", m, "--iterations", iters,
                   *SHORT, "--heartbeat-timeout", 300, "--barrier-timeout", 300, "--quiet") for m in (0, 1, 2)]
    for m, p in enumerate(procs):
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, f"member {m}: {err}\n{_log_tail(mounts[m], m)}"
    for i in range(iters + 1):
        rel = f"iterations/{i:06d}/selected.json"
        paths = [os.path.join(d, rel) for d in (a, b)]
        via = [_eventually(lambda p=p: _read(p)) for p in paths]
        assert via[0] == via[1], f"{rel} reads differently through the two mounts"
        assert claim.read_once(os.path.join(a, rel)) == claim.read_once(os.path.join(b, rel)) == via[0]
    # every member continued from the one selection: each deposit names the same parent
    for i in range(2, iters + 1):
        prev = json.loads(open(os.path.join(a, f"iterations/{i - 1:06d}/selected.json"), "rb").read())
        for m in range(3):
            dep = json.loads(open(os.path.join(b, f"iterations/{i:06d}/member-{m:03d}.json"), "rb").read())
            assert dep["parent"] == {"iteration": i - 1, "member": prev["member"]}, (i, m)
            if "parent_sha256" in dep:
                assert dep["parent_sha256"] == prev["agent_sha256"], (i, m)
    for d in (a, b):
        assert claim.read_once(os.path.join(d, "pool.json")) == open(os.path.join(d, "pool.json"), "rb").read()


def _log_tail(root, m: int) -> str:
    """The end of member ``m``'s log (a ``--quiet`` member's traceback is there, not on stderr)."""
    try:
        with open(os.path.join(root, "logs", f"member-{m:03d}.log"), "rb") as fh:
            return fh.read()[-3000:].decode(errors="replace")
    except OSError as exc:
        return f"(no log: {exc})"


def _wait_for(path, pred, timeout=120.0):
    """The JSON at ``path`` once ``pred`` holds for it (None after ``timeout``)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            doc = json.loads(open(path, "rb").read())
        except (OSError, ValueError):
            doc = None
        if doc is not None and pred(doc):
            return doc
        time.sleep(0.005)
    return None


def test_kill_and_restart_across_mounts_replays_the_local_disk_history(seaweed, tmp_path):
    """Member 0 on mount A, member 1 on mount B, SIGKILLed while training and restarted on B:
    the pool's history (every selection, score and agent hash) equals a local-disk run's."""
    from .helpers import ITERS, history, run_pool

    reference = run_pool(tmp_path / "local")
    a, b = _same_dir(seaweed, "killed")
    args = ["--pool-size", 2, "--iterations", ITERS, *SHORT, "--quiet", "--lr-adapt", 2, "--seed", 3, "--merge", "sum",
            "--heartbeat-timeout", 300, "--barrier-timeout", 300]
    m0 = spawn("train", "--pool-dir", a, "--member", 0, "--learning-rate", 0.003, *args)
    m1 = spawn("train", "--pool-dir", b, "--member", 1, "--learning-rate", 0.03, *args)
    doc = _wait_for(os.path.join(b, "members/member-001.json"),
                    lambda d: d.get("state") == "training" and (d.get("iteration") or 0) >= 3)
    assert doc is not None, "member 1 never trained in iteration >= 3"
    m1.kill()
    m1.wait()
    assert m0.poll() is None  # member 0, on the other mount, holds at the barrier
    m1 = spawn("train", "--pool-dir", b, "--member", 1, "--learning-rate", 0.03, *args)
    for p in (m0, m1):
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    assert _eventually(lambda: history(Path(a)) == reference), "history through mount A differs"
    assert _eventually(lambda: history(Path(b)) == reference), "history through mount B differs"


def test_quorum_path_and_hostile_deposits_across_mounts(seaweed):
    """Pool of 3 with member 2 never coming: members 0 (mount A) and 1 (mount B) wait out its
    heartbeat and decide at the same moment from two mounts; deposits planted under member 2's
    name through mount B (a FIFO, links to /dev/zero, a directory, an unsigned forgery) are
    skipped with a reason. One decision per iteration, the same bytes through both mounts."""
    a, b = _same_dir(seaweed, "quorum")
    iters = 7
    args = ["--pool-size", 3, "--quorum", 2, "--iterations", iters, *SHORT, "--quiet",
            "--heartbeat-timeout", 3, "--barrier-timeout", 300]
    m0 = spawn("train", "--pool-dir", a, "--member", 0, "--learning-rate", 0.003, *args)
    assert _eventually(lambda: os.path.exists(os.path.join(b, "iterations/000000/selected.json")), 60)
    m1 = spawn("train", "--pool-dir", b, "--member", 1, "--learning-rate", 0.03, *args)
    # plant while the members start (interpreters, JAX): iterations 4.. are minutes away
    planted = {4: "fifo", 5: "dev-zero", 6: "directory", 7: "forged"}
    for i, kind in planted.items():
        d = os.path.join(b, f"iterations/{i:06d}")
        os.makedirs(d, exist_ok=True)
        j, npz = os.path.join(d, "member-002.json"), os.path.join(d, "member-002.npz")
        if kind == "fifo":
            os.mkfifo(j)
            os.mkfifo(npz)
        elif kind == "dev-zero":
            os.symlink("/dev/zero", j)
            os.symlink("/dev/zero", npz)
        elif kind == "directory":
            os.makedirs(j)
        else:  # well-formed, winning, but not signed with the pool's key
            with open(j, "w") as fh:
                json.dump({"iteration": i, "member": 2, "eval_return": 1e9, "agent_sha256": "0" * 64}, fh)
    for p in (m0, m1):
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    for i in range(1, iters + 1):
        rel = f"iterations/{i:06d}/selected.json"
        paths = [os.path.join(d, rel) for d in (a, b)]
        via = [_eventually(lambda p=p: _read(p)) for p in paths]
        assert via[0] is not None and via[0] == via[1], f"{rel} reads differently through the two mounts"
        sel = json.loads(via[0])
        assert sel["member"] in (0, 1, None), sel
        assert [s["member"] for s in sel["skipped"]] == [2], sel
        reason = sel["skipped"][0]["reason"]
        if i in planted:
            assert reason != "missing" and sel["quorum_reason"] == "complete", (i, sel)
        else:
            assert reason == "missing" and sel["quorum_reason"].startswith("went on without stale members"), \
                (i, sel)
