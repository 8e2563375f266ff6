"""The create-once decision (rl_pool/claim.py): one winner, complete content, nothing to wedge."""

import errno
import json
import multiprocessing as mp
import os

import pytest

from rl_pool import claim
from rl_pool.errors import UnsafeFile


def test_first_proposal_wins_and_later_ones_get_its_bytes(tmp_path):
    p = tmp_path / "selected.json"
    assert claim.read_once(p) is None
    assert claim.create_once(p, b'{"member": 1}\n') == (b'{"member": 1}\n', True)
    assert claim.create_once(p, b'{"member": 0}\n') == (b'{"member": 1}\n', False)
    assert claim.read_once(p) == b'{"member": 1}\n'
    # the plain copy people and tools read carries the decided bytes
    assert p.read_bytes() == b'{"member": 1}\n'
    # nothing else is left: the decision and the copy
    assert sorted(os.listdir(tmp_path)) == [".selected.json.once", "selected.json"]
    assert os.listdir(tmp_path / ".selected.json.once") == ["data"]


def test_a_missing_plain_copy_is_published_again_by_the_next_member(tmp_path):
    p = tmp_path / "pool.json"
    claim.create_once(p, b"config")
    p.unlink()  # the winner died between its rename and publishing the copy
    assert claim.create_once(p, b"other config") == (b"config", False)
    assert p.read_bytes() == b"config"


def test_a_plain_file_alone_decides_nothing(tmp_path):
    """Only the decision directory counts: a stray or planted plain file is overwritten by the winner."""
    p = tmp_path / "selected.json"
    p.write_bytes(b"planted")
    assert claim.read_once(p) is None
    assert claim.create_once(p, b"real") == (b"real", True)
    assert p.read_bytes() == b"real"


def test_a_proposer_killed_before_its_rename_leaves_nothing_that_counts(tmp_path):
    p = tmp_path / "selected.json"
    # what a proposer killed after writing its proposal leaves behind: a temp-named directory
    dead = tmp_path / "..selected.json.once.tmp-somehost-99999-deadbeef"
    dead.mkdir()
    (dead / "data").write_bytes(claim.envelope(b"never decided", "somehost-99999-x"))
    assert claim.read_once(p) is None
    assert claim.create_once(p, b"decided") == (b"decided", True)
    claim.remove_proposal(str(dead))
    assert not dead.exists()


def test_an_empty_decision_directory_is_undecided_and_gets_replaced(tmp_path):
    """A stray mkdir, or a filer that crashed mid-rename, leaves an empty directory: it must not wedge."""
    p = tmp_path / "selected.json"
    os.mkdir(claim.decision_dir(p))
    assert claim.read_once(p) is None
    assert claim.create_once(p, b"decided") == (b"decided", True)
    assert claim.read_once(p) == b"decided"


@pytest.mark.parametrize("raw, why", [
    (b"no header at all", "no header line"),
    (b"rl-pool-once 1 sha256=00 size=3 by=x\nabc", "does not match"),
    (b"something-else 1 sha256=00 size=3 by=x\nabc", "not an rl-pool decision"),
    (claim.envelope(b"abcdef", "x")[:-2], "does not match"),  # truncated
])
def test_a_decision_that_does_not_verify_is_refused_with_its_reason(tmp_path, raw, why):
    p = tmp_path / "selected.json"
    d = claim.decision_dir(p)
    os.mkdir(d)
    with open(os.path.join(d, "data"), "wb") as fh:
        fh.write(raw)
    with pytest.raises(claim.InvalidDecision, match=why):
        claim.read_once(p)
    with pytest.raises(claim.InvalidDecision, match=why):
        claim.create_once(p, b"mine")
    assert not p.exists()  # nothing was published from it


def test_hostile_things_at_the_decision_are_refused_without_blocking(tmp_path):
    p = tmp_path / "selected.json"
    d = claim.decision_dir(p)
    os.mkdir(d)
    os.mkfifo(os.path.join(d, "data"))
    with pytest.raises(UnsafeFile, match="FIFO"):
        claim.read_once(p, root=tmp_path)
    os.unlink(os.path.join(d, "data"))
    os.symlink("/etc/passwd", os.path.join(d, "data"))
    with pytest.raises(UnsafeFile):
        claim.read_once(p, root=tmp_path)


def test_a_file_or_link_occupying_the_decision_name_is_moved_aside(tmp_path):
    p = tmp_path / "selected.json"
    for make in (lambda d: open(d, "wb").write(b"junk"), lambda d: os.symlink("/tmp", d),
                 lambda d: os.mkfifo(d)):
        d = claim.decision_dir(p)
        make(d)
        data, won = claim.create_once(p, b"decided", root=tmp_path)
        assert (data, won) == (b"decided", True)
        assert claim.read_once(p, root=tmp_path) == b"decided"
        import shutil

        shutil.rmtree(d)
        p.unlink()


def test_a_lost_rename_reply_still_reports_the_win(tmp_path, monkeypatch):
    """NFS: the first RENAME happened, its reply was lost, the retransmission says ENOENT."""
    real = os.rename

    def rename_then_fail(src, dst):
        real(src, dst)
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", src)

    monkeypatch.setattr(claim.os, "rename", rename_then_fail)
    p = tmp_path / "selected.json"
    assert claim.create_once(p, b"mine") == (b"mine", True)
    assert p.read_bytes() == b"mine"


def test_payload_too_large_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match="cap"):
        claim.create_once(tmp_path / "x", b"x" * 11, cap=10)
    assert os.listdir(tmp_path) == []


def _racer(root: str, names: int, me: int, barrier, out) -> None:
    results = []
    for k in range(names):
        barrier.wait()
        data = json.dumps({"racer": me, "name": k}).encode()
        results.append(claim.create_once(os.path.join(root, f"d{k:03d}.json"), data))
    out.put((me, results))


@pytest.mark.parametrize("racers", [2, 4])
def test_processes_racing_for_the_same_names_have_exactly_one_winner_each_time(tmp_path, racers):
    names = 60
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(racers), ctx.Queue()
    procs = [ctx.Process(target=_racer, args=(str(tmp_path), names, me, barrier, out))
             for me in range(racers)]
    for p in procs:
        p.start()
    got = dict(out.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0
    wins = {me: 0 for me in range(racers)}
    for k in range(names):
        results = [got[me][k] for me in range(racers)]
        winners = [me for me, (_, won) in enumerate(results) if won]
        assert len(winners) == 1, f"name {k}: winners {winners}"
        wins[winners[0]] += 1
        decided = json.dumps({"racer": winners[0], "name": k}).encode()
        assert all(data == decided for data, _ in results), f"name {k}: racers saw different bytes"
        path = tmp_path / f"d{k:03d}.json"
        assert claim.read_once(path) == decided and path.read_bytes() == decided
    assert not [n for n in os.listdir(tmp_path) if ".tmp-" in n], "a proposal was left behind"
    # a real race, not a relay: more than one process won some names
    assert sum(1 for w in wins.values() if w) >= 2, wins


def test_special_things_at_the_plain_name_are_replaced_by_the_decided_copy(tmp_path):
    p = tmp_path / "selected.json"
    p.mkdir()
    (p / "junk").write_text("x")  # a directory a rename cannot replace: moved aside
    assert claim.create_once(p, b"decided", root=tmp_path) == (b"decided", True)
    assert p.read_bytes() == b"decided"
    q = tmp_path / "other.json"
    claim.create_once(q, b"first", root=tmp_path)
    q.unlink()
    os.mkfifo(q)  # a FIFO where the copy was: the next member writes the copy again
    assert claim.create_once(q, b"second", root=tmp_path) == (b"first", False)
    assert q.read_bytes() == b"first"
