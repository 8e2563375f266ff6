"""Hostile files in a pool: every read is bounded, never blocks and never follows a link.

Unit tests on tmp_path for the bounded reader and the protocol's read sites, the commands'
one-line refusals, then two real pools: one full of special files under the names the
protocol reads, and one whose members are SIGKILLed at random moments.
"""

import errno
import json
import os
import random
import resource
import signal
import socket
import stat
import subprocess
import sys
import threading
import time

import pytest

from rl_pool import fsutil
from rl_pool.errors import UnsafeFile
from rl_pool.protocol import claim, deposits, heartbeat, layout, pool

from .conftest import ROOT, SHORT, rl_pool
from .helpers import agent, history, make_pool, run_pool

#: The random-kill test's own pool length: longer than the shared reference's, so 20 kills spread
#: over it with room to spare.
CHAOS_ITERS = 16


def _in_time(fn, seconds=5.0):
    """``fn()``'s result or exception, failing the test if it takes longer than ``seconds``
    (a read that blocks must fail the test, not hang it)."""
    out = {}

    def target():
        try:
            out["value"] = fn()
        except BaseException as exc:
            out["error"] = exc

    t = threading.Thread(target=target, daemon=True)
    t0 = time.monotonic()
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"read still blocked after {seconds}s"
    out["seconds"] = time.monotonic() - t0
    return out


def _refused(fn, seconds=5.0) -> UnsafeFile:
    out = _in_time(fn, seconds)
    assert isinstance(out.get("error"), UnsafeFile), f"not refused: {out}"
    return out["error"]


def make_socket(path) -> socket.socket:
    """A UNIX socket bound at ``path`` (bound under a short name, then renamed: sun_path holds 108 bytes)."""
    short = f"/tmp/rlpool-sock-{os.getpid()}-{random.getrandbits(32):08x}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(short)
    s.listen(1)
    os.rename(short, path)
    return s


def make_device(path) -> bool:
    """A character device like /dev/zero at ``path`` (root only); False, and a FIFO there instead,
    where devices cannot be made."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 5))
        return True
    except PermissionError:
        os.mkfifo(path)
        return False


# ---------------------------------------------------------------- the bounded reader
def test_fifo_is_refused_at_once_even_with_no_writer(tmp_path):
    p = tmp_path / "x.json"
    os.mkfifo(p)
    exc = _refused(lambda: fsutil.read_json(p))
    assert "FIFO" in exc.strerror and exc.filename == str(p)
    # a FIFO the user names (links followed) is refused all the same
    assert "FIFO" in _refused(lambda: fsutil.read_bytes(p, follow=True)).strerror


def test_links_are_never_followed_and_devices_never_read(tmp_path):
    link = tmp_path / "zero.npz"
    link.symlink_to("/dev/zero")
    assert "symbolic link" in _refused(lambda: fsutil.read_bytes(link)).strerror
    # followed only where the user named the file; it still must be a regular file
    assert "character device" in _refused(lambda: fsutil.read_bytes(link, follow=True)).strerror
    dev = tmp_path / "dev.json"
    if make_device(dev):  # a /dev/zero of our own
        assert "character device" in _refused(lambda: fsutil.read_json(dev)).strerror
    # a link to a perfectly good file is refused too: a pool never follows one
    good = tmp_path / "good.json"
    good.write_text("{}")
    (tmp_path / "alias.json").symlink_to(good)
    assert fsutil.read_json(good) == {}
    assert "symbolic link" in _refused(lambda: fsutil.read_json(tmp_path / "alias.json")).strerror


def test_directories_sockets_and_paths_out_of_the_pool_are_refused(tmp_path):
    (tmp_path / "d.json").mkdir()
    assert "directory" in _refused(lambda: fsutil.read_json(tmp_path / "d.json")).strerror
    s = make_socket(tmp_path / "s.json")
    try:
        assert "socket" in _refused(lambda: fsutil.read_json(tmp_path / "s.json")).strerror
    finally:
        s.close()
    root = tmp_path / "pool"
    root.mkdir()
    (tmp_path / "outside.json").write_text("{}")
    assert "outside the pool" in _refused(
        lambda: fsutil.read_json(root / ".." / "outside.json", root=root)).strerror


_POOL = "/tmp/some/pool"


@pytest.mark.parametrize("path", [_POOL + "/" + rel for rel in [
    "iterations/000007", "", "/", "a/../b", "./a", "/a", "a/", "../pool/a", "a/..",
    "iterations/000007/.selected.json.once", ".hidden/x", "../outside", "a/../../x", "../pool2/x"]]
    + [_POOL, _POOL + "2/x", _POOL + "x", "/tmp/some", "/tmp/some/poo", "pool/a", "/tmp/some//pool/a"])
def test_paths_below_a_pool_split_as_the_general_rule_says(path):
    """The quick split of an already normal path below a pool's root agrees with the general
    rule (normalise, then relative to the root) on every spelling, "." and ".." included, and
    a sibling whose name starts with the pool's is outside it."""
    root = fsutil.Root(_POOL)
    want = os.path.relpath(os.path.abspath(path), root).split(os.sep)
    want = [p for p in want if p not in ("", ".")]
    if ".." in want:
        assert "outside the pool" in _refused(lambda: fsutil._parts(path, root)).strerror
    else:
        assert fsutil._parts(path, root) == want


def test_size_cap_is_checked_before_reading(tmp_path):
    p = tmp_path / "big.npz"
    with open(p, "wb") as fh:
        fh.truncate(1 << 40)  # a sparse terabyte: reading it would take the machine down
    exc = _refused(lambda: fsutil.read_bytes(p))
    assert exc.errno == errno.EFBIG and "cap" in exc.strerror
    q = tmp_path / "exact"
    q.write_bytes(b"x" * 1000)
    assert fsutil.read_bytes(q, cap=1000) == b"x" * 1000
    assert "cap" in _refused(lambda: fsutil.read_bytes(q, cap=999)).strerror
    r = tmp_path / "big.json"
    r.write_bytes(b" " * (fsutil.JSON_MAX_BYTES + 1))
    assert "cap" in _refused(lambda: fsutil.read_json(r)).strerror


def test_a_file_that_grows_while_read_is_refused(tmp_path, monkeypatch):
    p = tmp_path / "grows.json"
    p.write_bytes(b"[" + b"0," * 100)
    # Another writer appends between every two reads of ours: never at EOF, so only the cap stops it.
    real_read = os.read
    writer = open(p, "ab", buffering=0)

    def read_while_appending(fd, n):
        writer.write(b"1," * 5000)
        return real_read(fd, n)

    monkeypatch.setattr(fsutil, "_CHUNK", 4096)
    monkeypatch.setattr(fsutil.os, "read", read_while_appending)
    try:
        exc = _refused(lambda: fsutil.read_bytes(p, cap=1 << 20))
    finally:
        monkeypatch.undo()
        writer.close()
    assert "grew past" in exc.strerror


def test_a_file_appended_to_by_a_live_thread_is_never_read_past_its_cap(tmp_path):
    p = tmp_path / "live.json"
    p.write_bytes(b"x" * 1000)
    stop = threading.Event()

    def append():
        with open(p, "ab", buffering=0) as fh:
            while not stop.is_set() and fh.tell() < (256 << 20):
                fh.write(b"y" * 65536)

    t = threading.Thread(target=append, daemon=True)
    t.start()
    try:
        for _ in range(20):
            out = _in_time(lambda: fsutil.read_bytes(p, cap=1 << 20))
            # whichever moment it is read at: all of it under the cap, or refused
            assert isinstance(out.get("error"), UnsafeFile) or len(out["value"]) <= 1 << 20
    finally:
        stop.set()
        t.join()


def test_a_symlinked_iteration_directory_is_neither_listed_nor_read_through(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=2)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    good = deposits.deposit(layout.Paths(tmp_path / "other"), 1, 0, agent(1), {"eval_return": 5.0})  # a real deposit
    for name in os.listdir(tmp_path / "other/iterations/000001"):
        os.rename(tmp_path / "other/iterations/000001" / name, elsewhere / name)
    (elsewhere / "selected.json").write_text(json.dumps({"iteration": 3, "member": 0, "agent": "x"}))
    os.symlink(elsewhere, paths.iteration(3))
    os.symlink("/dev", paths.iteration(4))
    assert deposits.iterations_on_disk(paths) == [0]
    assert deposits.read_selected(paths, 3) is None and deposits.last_selected(paths) == 0
    assert deposits.present(paths, 3, 2) == set()
    exc = _refused(lambda: paths.read_json(paths.deposit_json(3, 0)))
    assert "000003, which is a symbolic link" in exc.strerror
    with pytest.raises(ValueError, match="symbolic link"):
        deposits.read_deposit(paths, 3, 0)
    assert good["eval_return"] == 5.0  # what was refused was a valid deposit: only the link is wrong
    # an iteration "directory" that is a file, and an iterations/ that is a link
    open(paths.iteration(5), "w").close()
    assert deposits.present(paths, 5, 2) == set() and deposits.read_selected(paths, 5) is None
    os.rename(paths.iterations, tmp_path / "real-iterations")
    os.symlink(tmp_path / "real-iterations", paths.iterations)
    with pytest.raises(UnsafeFile, match="symbolic link"):
        deposits.iterations_on_disk(paths)


def test_hostile_deposits_are_skipped_with_their_reason(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=6)
    like = deposits.load_selected_agent(paths, 0)
    deposits.deposit(paths, 1, 0, agent(0), {"eval_return": 1.0})
    # 1: valid metrics, but the agent is a link to a valid agent outside the pool
    elsewhere = layout.Paths(tmp_path / "q")
    elsewhere.key = paths.key  # a key holder's valid deposit, only in the wrong place
    doc = deposits.deposit(elsewhere, 1, 1, agent(1), {"eval_return": 9.0})
    (tmp_path / "p/iterations/000001/member-001.json").write_text(json.dumps(doc))
    os.symlink(tmp_path / "q/iterations/000001/member-001.npz", paths.deposit_npz(1, 1))
    # 2: metrics are a FIFO; 3: a socket; 4: a huge sparse agent; 5: metrics are a directory
    os.mkfifo(paths.deposit_json(1, 2))
    s = make_socket(paths.deposit_json(1, 3))
    doc = deposits.deposit(paths, 1, 4, agent(4), {"eval_return": 9.0})
    with open(paths.deposit_npz(1, 4), "r+b") as fh:
        fh.truncate(1 << 36)
    os.mkdir(paths.deposit_json(1, 5))
    try:
        out = _in_time(lambda: pool.select(paths, 1, cfg, like, deposits.present(paths, 1, 6), "complete",
                                           deposits.read_selected(paths, 0)))
    finally:
        s.close()
    sel = out["value"]
    assert sel["member"] == 0
    why = {s["member"]: s["reason"] for s in sel["skipped"]}
    assert "symbolic link" in why[1] and "FIFO" in why[2] and "socket" in why[3]
    assert "cap" in why[4] and "directory" in why[5]


def test_special_files_on_create_once_and_replaced_names_are_cleared(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=1)
    like = deposits.load_selected_agent(paths, 0)
    for i, plant in ((1, os.mkfifo), (2, os.mkdir), (3, lambda p: os.symlink("/dev/zero", p))):
        deposits.deposit(paths, i, 0, agent(i), {"eval_return": float(i)})
        plant(paths.selected(i))
        if i == 2:
            open(os.path.join(paths.selected(i), "junk"), "w").close()  # not even empty
        assert deposits.read_selected(paths, i) is None
        sel = pool.select(paths, i, cfg, like, {0}, "complete", deposits.read_selected(paths, i - 1))
        doc, created = _in_time(lambda sel=sel: pool.publish_selection(paths, sel, by=0))["value"]
        assert created and deposits.read_selected(paths, i) == doc
    # best.json a directory, best.npz a FIFO: update_best still writes the best
    os.mkdir(paths.best_json)
    os.mkfifo(paths.best_npz)
    assert pool.update_best(paths, deposits.read_selected(paths, 3))
    assert paths.read_json(paths.best_json)["iteration"] == 3
    assert paths.read_bytes(paths.best_npz) == agent(3).to_bytes()
    # a file the protocol wrote is never removed: a refusal names the exact thing it refused
    st = os.stat(paths.selected(1))
    assert fsutil.set_aside(paths.selected(1), (st.st_dev, st.st_ino + 1), root=paths.root) is False
    assert deposits.read_selected(paths, 1) is not None


def test_heartbeats_that_are_special_files_read_as_absent(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=3)
    os.mkfifo(paths.heartbeat(1))
    os.symlink("/dev/zero", paths.heartbeat(2))
    assert _in_time(lambda: heartbeat.read_heartbeat(paths, 1))["value"] is None
    assert heartbeat.read_heartbeat(paths, 2) is None
    live = heartbeat.Liveness(paths, timeout=0.05)
    assert live.stale(1) is None
    time.sleep(0.1)
    assert "unchanged" in live.stale(1)


# ---------------------------------------------------------------- commands: one line, exit 2
def _cli(capsys, *args):
    from rl_pool.commands.cli import main

    code = _in_time(lambda: main([str(a) for a in args]), 60)["value"]
    err = capsys.readouterr().err
    return code, err


def test_commands_refuse_special_files_in_one_line(tmp_path, capsys):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=1)
    os.symlink("/dev/zero", paths.best_npz)
    for cmd in (["evaluate", paths.root, "--episodes", 1], ["replay", paths.root, "--out", tmp_path / "r.gif"]):
        code, err = _cli(capsys, *cmd)
        assert code == 2 and err.count("\n") == 1 and "symbolic link" in err, err
    os.unlink(paths.best_npz)
    os.mkfifo(paths.best_npz)
    code, err = _cli(capsys, "evaluate", paths.best_npz)  # named by the user: still never blocks
    assert code == 2 and err.count("\n") == 1 and "FIFO" in err, err
    os.rename(paths.iterations, tmp_path / "it")
    os.symlink(tmp_path / "it", paths.iterations)
    for cmd in (["status", paths.root], ["plot", paths.root, "--out", tmp_path / "x.png"]):
        code, err = _cli(capsys, *cmd)
        assert code == 2 and err.count("\n") == 1 and "symbolic link" in err, err
    os.unlink(os.path.join(claim.decision_dir(paths.pool_json), "data"))
    os.mkfifo(os.path.join(claim.decision_dir(paths.pool_json), "data"))
    for cmd in (["status", paths.root],
                ["launch", "--pool-dir", paths.root, "--pool-size", 1, "--iterations", 1],
                ["train", "--pool-dir", paths.root, "--pool-size", 1, "--iterations", 1]):
        code, err = _cli(capsys, *cmd)
        assert code == 2 and err.count("\n") == 1 and "FIFO" in err, err
    assert not os.path.exists(tmp_path / "x.png") and not os.path.exists(tmp_path / "r.gif")


# ---------------------------------------------------------------- real pools
#: A member's address space: it needs about 1.5 GiB (JAX and XLA reserve much more than they touch;
#: measured: 1.2 GiB fails, 1.5 GiB runs). Twice that is room to run, and far too little to read
#: a /dev/zero or a sparse terabyte whole.
MEMBER_AS_LIMIT = 3 << 30


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEMBER_AS_LIMIT, MEMBER_AS_LIMIT))


def _member(d, m, *args, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rl_pool", "train", "--pool-dir", str(d), "--member", str(m),
                             *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, **kw)


def _plant(d, tmp_path) -> list:
    """Special files under the names the protocol reads, before the pool exists (a pool's
    directory may already hold iterations/, members/ and logs/)."""
    it = [d / f"iterations/{i:06d}" for i in range(8)]
    for p in (*it[1:6], d / "members", d / "logs"):
        p.mkdir(parents=True)
    os.mkfifo(d / "members/member-002.json")  # the absent member's heartbeat
    # 1: metrics a FIFO, agent a link to /dev/zero, wait file a link to /dev/zero
    os.mkfifo(it[1] / "member-002.json")
    (it[1] / "member-002.npz").symlink_to("/dev/zero")
    (it[1] / "member-002.wait.json").symlink_to("/dev/zero")
    # 2: valid-looking metrics without the key's signature, agent a sparse terabyte (a signed deposit
    # with such an agent is refused by its size cap: test_hostile_deposits_are_skipped_with_their_reason);
    # its selection's name taken by a directory
    (it[2] / "member-002.json").write_text(json.dumps(
        {"iteration": 2, "member": 2, "eval_return": 1e12, "agent_sha256": "0" * 64}))
    with open(it[2] / "member-002.npz", "wb") as fh:
        fh.truncate(1 << 40)
    (it[2] / "selected.json").mkdir()
    (it[2] / "selected.json/junk").write_text("x")
    # 3: no deposit from member 2 (the barrier waits until its FIFO heartbeat is stale);
    # its selection's name a FIFO, its wait file a socket
    os.mkfifo(it[3] / "selected.json")
    sockets = [make_socket(it[3] / "member-002.wait.json")]
    # 4: metrics a directory, agent a device, selection a link to /dev/zero, wait file a device
    (it[4] / "member-002.json").mkdir()
    make_device(it[4] / "member-002.npz")
    (it[4] / "selected.json").symlink_to("/dev/zero")
    make_device(it[4] / "member-002.wait.json")
    # 5: metrics a socket; the agent grows for as long as the pool runs (see the test)
    sockets.append(make_socket(it[5] / "member-002.json"))
    # 6, 7: iterations beyond the target that are links: to a selection outside the pool, and to /dev
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "selected.json").write_text(json.dumps({"iteration": 6, "member": 2, "agent": "x"}))
    os.symlink(outside, it[6])
    os.symlink("/dev", it[7])
    return sockets


@pytest.mark.multiprocess
def test_special_files_everywhere_in_a_live_pool(tmp_path):
    """Members 0 and 1 of a pool of 3 run; "member 2" is every special file root can make.
    Every iteration is selected, both members exit 0, under a memory limit that reading any
    of those files whole would break."""
    d = tmp_path / "pool"
    sockets = _plant(d, tmp_path)
    grows = d / "iterations/000005/member-002.npz"
    stop = threading.Event()

    def grow():
        with open(grows, "ab", buffering=0) as fh:
            while not stop.wait(0.001):
                if fh.tell() > (8 << 20):
                    fh.truncate(0)
                    fh.seek(0)
                fh.write(b"\0" * 16384)

    grower = threading.Thread(target=grow, daemon=True)
    grower.start()
    args = ["--pool-size", 3, "--iterations", 5, *SHORT, "--quorum", 2, "--heartbeat-timeout", 1, "--quiet"]
    procs = [_member(d, m, *args, preexec_fn=_limit_memory) for m in (0, 1)]
    try:
        # best.json and best.npz cannot be there before the pool is (a directory with them is foreign)
        deadline = time.time() + 60
        while not (d / "iterations/000000/selected.json").exists() and time.time() < deadline:
            time.sleep(0.01)
        os.mkdir(d / "best.json")
        (d / "best.json/junk").write_text("x")
        (d / "best.npz").symlink_to("/dev/zero")
        for p in procs:
            _, err = p.communicate(timeout=180)
            assert p.returncode == 0, err
    finally:
        stop.set()
        grower.join()
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
        for s in sockets:
            s.close()
    reasons = {1: "FIFO", 2: "unsigned", 3: "missing", 4: "directory", 5: "socket"}
    for i in range(1, 6):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert sel["winner"] in ("branch", "parent", "merge", "fallback") and sel["member"] in (0, 1, None)
        if sel["winner"] == "merge":  # nothing of member 2 has weight in it
            assert set(sel["merge"]["members"]) | set(sel["merge"]["statistics_from"]) <= {0, 1}
        assert {c["member"] for c in sel["considered"]} <= {0, 1} and sel["considered"]
        skipped = {s["member"]: s["reason"] for s in sel["skipped"]}
        assert reasons[i] in skipped.pop(2), sel["skipped"]
        assert set(skipped.values()) <= {"missing"}  # a live member is judged stale only on a very busy host
    sel3 = json.loads((d / "iterations/000003/selected.json").read_text())
    assert "member 2 heartbeat unchanged" in sel3["quorum_reason"]
    best = json.loads((d / "best.json").read_text())
    assert (d / "best.npz").read_bytes() == (d / best["agent"]).read_bytes()
    # the commands that read everything a person looks at: no hang, no traceback
    st = rl_pool("status", d, "--json", timeout=60, check=0)
    doc = json.loads(st.stdout)
    assert doc["iterations_completed"] == 5 and doc["members"][2]["state"] == "absent"
    assert st.stderr == ""


@pytest.mark.multiprocess
def test_random_sigkills_and_restarts_lose_nothing(tmp_path):
    """Both members of a real pool are SIGKILLed at random moments 20 times and restarted each
    time: the pool ends with exactly the uninterrupted run's history.

    About one kill in six lands a random 0.05-1.5 s after a start (start-up: creating the pool,
    imports); the others a random 0-300 ms after the member's heartbeat says it is training,
    evaluating or waiting, so they fall on every step of an iteration (training, deposit, barrier,
    selection, best). Kill k waits for iteration 1 + k(CHAOS_ITERS - 2)/20 at least, so the kills
    are spread over the whole run instead of all hitting iteration 1 again and again; the last
    two iterations are slack for a pool that runs ahead of the kills on a loaded machine. A member
    that exits 0 (the pool is complete) is not started again: start-up kills of a finished pool
    would only pad the count.
    """
    hist = run_pool(tmp_path / "ref", iters=CHAOS_ITERS)
    d = tmp_path / "chaos"
    rng = random.Random(9)
    args = ["--pool-size", 2, "--iterations", CHAOS_ITERS, *SHORT, "--quiet", "--lr-adapt", 2, "--seed", 3, "--merge", "sum"]
    lrs = (0.003, 0.03)
    paths = layout.Paths(d)
    kills = []

    def start(m):
        at = time.monotonic() + rng.uniform(0.05, 1.5) if rng.random() < 0.15 else None
        return {"p": _member(d, m, *args, "--learning-rate", lrs[m]), "at": at, "delay": rng.uniform(0, 0.3)}

    procs = {m: start(m) for m in (0, 1)}
    done = set()  # members that exited 0: the pool is complete
    deadline = time.monotonic() + 180
    try:
        while len(kills) < 20 and len(done) < 2:
            assert time.monotonic() < deadline, f"only {len(kills)} kills in time: {kills}"
            for m in set(procs) - done:
                s, now = procs[m], time.monotonic()
                if s["p"].poll() is not None:
                    _, err = s["p"].communicate()
                    assert s["p"].returncode == 0, err
                    done.add(m)
                    continue
                hb = heartbeat.read_heartbeat(paths, m) or {}
                at_work = hb.get("pid") == s["p"].pid and hb.get("state") in ("training", "evaluating", "waiting")
                due = 1 + len(kills) * (CHAOS_ITERS - 2) // 20
                if s["at"] is None and at_work and (hb.get("iteration") or 0) >= due:
                    s["at"] = now + s["delay"]
                if s["at"] is not None and now >= s["at"]:
                    s["p"].send_signal(signal.SIGKILL)
                    s["p"].communicate()
                    mine = hb.get("pid") == s["p"].pid  # else its heartbeat is not written yet
                    kills.append((m, hb.get("state"), hb.get("iteration")) if mine else (m, "start-up"))
                    procs[m] = start(m)
            time.sleep(0.002)
        for s in procs.values():
            _, err = s["p"].communicate(timeout=180)
            assert s["p"].returncode == 0, err
    finally:
        for s in procs.values():
            if s["p"].poll() is None:
                s["p"].kill()
                s["p"].communicate()
    print(f"{len(kills)} kills (member, state, iteration as the heartbeat said just before): {kills}")
    assert history(d) == hist
    at_work = [k for k in kills if len(k) == 3 and k[1] in ("training", "evaluating", "waiting")]
    assert len(kills) >= 15 and len({k[2] for k in at_work}) >= 4, f"too few kills, or not spread over the run: {kills}"


def test_log_names_and_agent_paths_taken_by_special_files(tmp_path):
    """A FIFO at a member's log or launcher output is set aside, never opened blocking; a FIFO or a
    link to /dev/zero named as an agent is refused at once."""
    from rl_pool import Agent
    from rl_pool.errors import AgentFileError

    paths, _cfg = make_pool(tmp_path / "p", pool_size=1)
    os.mkfifo(paths.log(0))
    out = _in_time(lambda: fsutil.open_append(paths.log(0), root=paths.root))["value"]
    out.write(b"a line\n")
    out.close()
    assert stat.S_ISREG(os.lstat(paths.log(0)).st_mode) and open(paths.log(0), "rb").read() == b"a line\n"
    os.symlink("/dev/zero", tmp_path / "zero.npz")
    os.mkfifo(tmp_path / "fifo.npz")
    for name in ("zero.npz", "fifo.npz"):
        got = _in_time(lambda n=name: Agent.load(tmp_path / n))
        assert isinstance(got.get("error"), AgentFileError) and "cannot read agent" in str(got["error"])
