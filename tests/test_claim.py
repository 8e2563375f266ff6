"""The create-once decision (rl_pool/protocol/claim.py): one winner, complete content, nothing to wedge."""

import errno
import json
import multiprocessing as mp
import os

import pytest

from rl_pool.protocol import claim

from .helpers import racer


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
    assert claim.create_once(p, b"decided", wait=5) == (b"decided", True)
    assert claim.read_once(p) == b"decided"
    assert not os.path.exists(claim.decision_dir(p, 1))  # decided in the first slot itself


@pytest.mark.parametrize("raw, why", [
    (b"no header at all", "no header line"),
    (b"rl-pool-once 1 sha256=00 size=3 by=x\nabc", "does not match"),
    (b"something-else 1 sha256=00 size=3 by=x\nabc", "not an rl-pool decision"),
    (claim.envelope(b"abcdef", "x")[:-2], "does not match"),  # truncated
])
def test_a_decision_that_does_not_verify_decides_nothing_and_the_next_slot_decides(tmp_path, raw, why,
                                                                                  caplog):
    p = tmp_path / "selected.json"
    d = claim.decision_dir(p)
    os.mkdir(d)
    with open(os.path.join(d, "data"), "wb") as fh:
        fh.write(raw)
    assert claim.read_once(p) is None
    assert claim.create_once(p, b"mine") == (b"mine", True)
    assert why in caplog.text
    assert claim.read_once(p) == b"mine" and p.read_bytes() == b"mine"
    assert os.path.isdir(claim.decision_dir(p, 1))
    with open(os.path.join(d, "data"), "rb") as fh:
        assert fh.read() == raw  # never removed: only passed over


def test_hostile_things_at_the_decision_are_passed_over_without_blocking(tmp_path):
    p = tmp_path / "selected.json"
    d = claim.decision_dir(p)
    os.mkdir(d)
    os.mkfifo(os.path.join(d, "data"))
    assert claim.read_once(p, root=tmp_path) is None
    assert "FIFO" in claim.why_undecided(p, root=tmp_path)
    assert claim.create_once(p, b"one", root=tmp_path) == (b"one", True)
    assert claim.why_undecided(p, root=tmp_path) is None
    q = tmp_path / "other.json"
    e = claim.decision_dir(q)
    os.mkdir(e)
    os.symlink("/etc/passwd", os.path.join(e, "data"))
    assert claim.create_once(q, b"two", root=tmp_path) == (b"two", True)
    assert claim.read_once(q, root=tmp_path) == b"two"


def test_a_file_link_or_fifo_at_the_decision_name_is_passed_over(tmp_path):
    for k, make in enumerate((lambda d: open(d, "wb").write(b"junk"), lambda d: os.symlink("/tmp", d),
                              os.mkfifo)):
        p = tmp_path / f"selected-{k}.json"
        make(claim.decision_dir(p))
        assert claim.read_once(p, root=tmp_path) is None
        assert claim.create_once(p, b"decided", root=tmp_path) == (b"decided", True)
        assert claim.read_once(p, root=tmp_path) == b"decided"
        assert claim.create_once(p, b"late", root=tmp_path) == (b"decided", False)


def test_a_decision_the_callers_check_rejects_is_passed_over(tmp_path):
    """A forger with write access but without the pool's key: a well-formed decision, badly signed."""
    p = tmp_path / "selected.json"
    forged = claim.decision_dir(p)
    os.mkdir(forged)
    with open(os.path.join(forged, "data"), "wb") as fh:
        fh.write(claim.envelope(b'{"signed": false}', "stranger"))

    def signed(payload):
        return None if json.loads(payload)["signed"] else "not signed with the pool key"

    assert claim.read_once(p, accept=signed) is None
    assert claim.read_once(p) == b'{"signed": false}'  # without the check it would count
    honest = b'{"signed": true}'
    assert claim.create_once(p, honest, accept=signed) == (honest, True)
    assert claim.create_once(p, b'{"signed": true, "x": 1}', accept=signed) == (honest, False)
    assert claim.read_once(p, accept=signed) == honest
    with pytest.raises(ValueError, match="own check"):
        claim.create_once(tmp_path / "y", b'{"signed": false}', accept=signed)


def test_a_directory_that_never_gets_its_data_is_passed_over_after_the_wait(tmp_path):
    p = tmp_path / "selected.json"
    d = claim.decision_dir(p)
    os.mkdir(d)
    (tmp_path / ".selected.json.once" / "junk").write_bytes(b"x")  # not empty: no rename replaces it
    assert claim.read_once(p) is None
    assert claim.create_once(p, b"decided", wait=0.2) == (b"decided", True)
    assert claim.read_once(p) == b"decided"


def test_when_every_slot_is_taken_by_junk_the_error_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(claim, "MAX_SLOTS", 3)
    p = tmp_path / "selected.json"
    for k in range(3):
        open(claim.decision_dir(p, k), "wb").close()
    with pytest.raises(claim.ClaimError, match="all 3 slots"):
        claim.create_once(p, b"x")


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


@pytest.mark.parametrize("racers", [2, 4])
def test_processes_racing_for_the_same_names_have_exactly_one_winner_each_time(tmp_path, racers):
    names = 60
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(racers), ctx.Queue()
    procs = [ctx.Process(target=racer, args=(str(tmp_path), names, me, barrier, out))
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


# ---------------------------------------------------------------- doctor: the checks behind the decision
def test_quick_check_finds_nothing_wrong_on_a_local_disk_and_leaves_nothing(tmp_path):
    from rl_pool.protocol import doctor

    assert doctor.quick_check(tmp_path) == []
    assert os.listdir(tmp_path) == []


def test_quick_check_refuses_a_filesystem_whose_directory_renames_replace(tmp_path, monkeypatch):
    """What an object-store FUSE adapter does: a directory rename is a delete and a copy."""
    import shutil

    from rl_pool.protocol import doctor

    real = os.rename

    def clobbering_rename(src, dst, **kw):
        if os.path.isdir(src) and os.path.isdir(dst):
            shutil.rmtree(dst)
        return real(src, dst, **kw)

    monkeypatch.setattr(os, "rename", clobbering_rename)
    problems = doctor.quick_check(tmp_path)
    assert any("directory rename onto a non-empty directory" in p for p in problems), problems


@pytest.mark.parametrize("fs, problem, note", [
    ({"type": "fuse.s3fs", "options": "rw"}, "object store", None),
    ({"type": "nfs4", "options": "rw,nocto,hard"}, "nocto", "lookupcache"),
    ({"type": "nfs", "options": "rw,soft,lookupcache=positive"}, None, "'soft'"),
    ({"type": "fuse.seaweedfs", "options": "rw"}, None, "SeaweedFS"),
    ({"type": "ext4", "options": "rw"}, None, None),
])
def test_mount_options_that_matter_are_named(fs, problem, note):
    from rl_pool.protocol import doctor

    problems, notes = doctor.mount_notes(fs)
    assert [p for p in problems if problem in p] if problem else problems == []
    assert [n for n in notes if note in n] if note else notes == []


def _doctor_peer(d: str, out) -> None:
    from rl_pool.protocol import peer_race

    out.put(peer_race.peer_race(d, rounds=10, timeout=60, settle=0.05))


def test_doctor_peers_meet_race_and_agree_on_a_local_disk(tmp_path):
    """Two doctor runs on one directory find each other, race, and print the same result: on a
    local disk every primitive has exactly one winner."""
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=_doctor_peer, args=(str(tmp_path), out)) for _ in range(2)]
    for p in procs:
        p.start()
    a, b = out.get(timeout=120), out.get(timeout=120)
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0
    assert {a["me"], a["peer"]} == {b["me"], b["peer"]} and a["primitives"] == b["primitives"]
    assert all(p["exclusive"] and p["exactly_one"] == 10 for p in a["primitives"].values()), a
    assert os.listdir(tmp_path) == []  # the meeting place is removed


def test_doctor_command_prints_a_verdict(tmp_path, capsys):
    from rl_pool.protocol import doctor

    assert doctor.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "verdict: a pool can live here" in out and "directory rename onto a non-empty" in out
    assert doctor.main([str(tmp_path / "missing")]) == 2
