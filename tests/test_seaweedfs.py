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

import pytest

from rl_pool import claim

from .conftest import ROOT, SHORT, spawn
from .seaweed import Seaweed, unavailable
from .test_claim import _racer

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
        got = fn()
        if got or time.time() > deadline:
            return got
        time.sleep(0.02)


def test_doctor_on_both_mounts_at_once_finds_the_link_race_and_exclusive_renames(seaweed):
    a, b = _same_dir(seaweed, "doctor")
    cmd = [sys.executable, "-m", "rl_pool.doctor", "--peer", "--rounds", "30", "--json",
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


def test_claims_racing_from_both_mounts_have_one_winner_that_both_mounts_read(seaweed):
    a, b = _same_dir(seaweed, "claims")
    names, per_mount = 30, 2
    roots = [a, b] * per_mount
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(len(roots)), ctx.Queue()
    procs = [ctx.Process(target=_racer, args=(root, names, me, barrier, out))
             for me, root in enumerate(roots)]
    for p in procs:
        p.start()
    got = dict(out.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0
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
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
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
