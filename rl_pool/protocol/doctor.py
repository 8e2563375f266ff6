"""``rl-pool doctor DIR [--peer]``: can a pool live on the filesystem that holds DIR?

A pool needs three things from its filesystem (docs/cluster.md):

1. atomic replace: ``rename(2)`` of a complete temp file over a name;
2. an exclusive create-once that holds across clients: rl-pool decides with a
   rename of a complete directory onto a name that may already hold one
   (:mod:`rl_pool.protocol.claim`);
3. visibility after close: a file written and closed on one host is read
   whole by another that opens it afterwards, and shows in listings.

One client can check what one client sees (``quick_check``, and the first part
of ``doctor``). Whether a primitive is exclusive *across* clients needs two:
run the same command with ``--peer`` on two hosts (or two mounts of the same
filesystem) against the same directory at about the same time. The two runs
find each other through files in ``DIR/.rl-pool-doctor/SESSION/``, then race
``link``, ``O_EXCL``, ``mkdir``, a directory ``rename`` and a shared-file
``rename`` on the same names, round after round, and both print how many
winners each round had and whether both clients read the same winner.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import sys
import time

from rl_pool import fsutil
from rl_pool.protocol import claim
from rl_pool.protocol.peer_race import PeerTimeout, peer_race

#: FUSE filesystems over object stores: a directory rename is a copy then a delete, not one step.
OBJECT_STORE_FUSE = ("s3fs", "gcsfuse", "goofys", "rclone", "mountpoint-s3", "s3backer", "blobfuse",
                     "blobfuse2", "geesefs", "juicefs-s3")
DESCRIBE = {
    "link": "link(2) of a complete file onto a name",
    "excl": "open(O_CREAT|O_EXCL)",
    "mkdir": "mkdir(2)",
    "rename-dir": "rename(2) of a complete directory (rl-pool's decisions)",
    "rename-take": "rename(2) of one shared file to a private name",
}


# ---------------------------------------------------------------- what is mounted there
def filesystem(path) -> dict:
    """The mount holding ``path``: ``{"mount_point", "type", "source", "options"}`` from
    ``/proc/self/mountinfo`` (``type`` ``"unknown"`` where it cannot be read)."""
    real = os.path.realpath(os.fspath(path))
    best = {"mount_point": "/", "type": "unknown", "source": "", "options": ""}
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="replace") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return best
    longest = -1
    for line in lines:
        left, _, right = line.partition(" - ")
        f, g = left.split(), right.split()
        if len(f) < 6 or len(g) < 2:
            continue
        mp = f[4].encode().decode("unicode_escape")  # \040 for spaces
        inside = real == mp or real.startswith(mp.rstrip("/") + "/")
        if inside and len(mp) >= longest:
            longest = len(mp)
            opts = f[5] + ("," + g[2] if len(g) > 2 else "")
            best = {"mount_point": mp, "type": g[0], "source": g[1], "options": opts}
    return best


def mount_notes(fs: dict) -> tuple[list[str], list[str]]:
    """``(problems, notes)`` read from the filesystem type and mount options alone."""
    problems, notes = [], []
    kind, opts = fs["type"], set(fs["options"].split(","))
    sub = kind.split(".", 1)[1] if kind.startswith("fuse.") else ""
    if sub in OBJECT_STORE_FUSE:
        problems.append(f"{kind} maps an object store: a directory rename is a copy then a delete, "
                        "so create-once decisions are not atomic; put the pool on a POSIX filesystem")
    if kind.startswith("nfs"):
        if "soft" in opts or "softerr" in opts:
            notes.append("NFS mounted 'soft': a slow server turns into EIO/ETIMEDOUT errors that stop "
                         "a member; mount 'hard' (the default)")
        if "nocto" in opts:
            problems.append("NFS mounted 'nocto': a file closed on one host may be read stale on "
                            "another; remount without nocto")
        if not any(o.startswith("lookupcache=") and o.split("=", 1)[1] in ("none", "pos", "positive")
                   for o in opts):
            notes.append("NFS caches failed lookups (lookupcache=all): a name another host creates "
                         "may stay invisible here until the directory's attributes expire (acdirmin/"
                         "acdirmax, 30-60 s by default), which delays barriers; mount with "
                         "lookupcache=positive for pools with short iterations")
    if kind == "fuse.seaweedfs":
        notes.append("SeaweedFS FUSE mount: link and O_EXCL are decided by each mount alone (not "
                     "exclusive across mounts; rl-pool does not use them); directory renames are "
                     "decided by the filer under a path lock; use one filer for a pool, and run "
                     "`rl-pool doctor DIR --peer` on two mounts to confirm")
    if kind in ("tmpfs", "ramfs", "overlay"):
        notes.append(f"{kind} is local to this host: members on other hosts cannot share it")
    return problems, notes


# ---------------------------------------------------------------- one client
def _scratch(d: str) -> str:
    path = fsutil.tmp_name(os.path.join(d, "rl-pool-check"))
    os.mkdir(path)
    return path


def _expect_exists_error(op) -> bool:
    """True if ``op()`` fails because the target exists (EEXIST/ENOTEMPTY)."""
    try:
        op()
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            return True
        raise
    return False


def local_checks(d: str, required_only: bool = False) -> list[dict]:
    """What one client can check in ``d``: ``[{"check", "ok", "required", "detail", "ms"}]``
    (``required_only``: only what a pool needs)."""
    out = []
    s = _scratch(d)

    def check(name, required, fn):
        if required_only and not required:
            return
        t0 = time.perf_counter()
        try:
            ok, detail = fn()
        except OSError as exc:
            ok, detail = False, f"{type(exc).__name__}: {exc.strerror or exc}"
        out.append({"check": name, "ok": ok, "required": required, "detail": detail,
                    "ms": round(1000 * (time.perf_counter() - t0), 2)})

    def write_read():
        p = os.path.join(s, "a.json")
        fsutil.atomic_write(p, b"first\n")
        ok = fsutil.read_bytes(p, 64) == b"first\n"  # bounded, no links: the directory is shared
        return ok, "written, fsynced, renamed into place and read back whole" if ok else "read back differs"

    def replace():
        p = os.path.join(s, "a.json")
        fsutil.atomic_write(p, b"second\n")
        got = fsutil.read_bytes(p, 64)
        left = [n for n in os.listdir(s) if fsutil.is_tmp(n)]
        ok = got == b"second\n" and not left
        return ok, "os.replace over an existing file" if ok else f"read {got!r}, leftovers {left}"

    def listing():
        p = os.path.join(s, "listed.json")
        fsutil.atomic_write(p, b"{}\n")
        ok = "listed.json" in os.listdir(s)
        return ok, "a file just closed shows in the listing" if ok else "missing from the listing"

    def hard_link():
        src, dst = os.path.join(s, "l1"), os.path.join(s, "l2")
        fsutil.atomic_write(src, b"x")
        os.link(src, dst)
        n = os.stat(src).st_nlink
        return n == 2, f"link count {n} (rl-pool does not need hard links)"

    def link_once():
        src = os.path.join(s, "l1")
        return _expect_exists_error(lambda: os.link(src, os.path.join(s, "l2"))), \
            "second link onto the name fails (this client only)"

    def excl_once():
        p = os.path.join(s, "x")
        os.close(os.open(p, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
        return _expect_exists_error(lambda: os.close(os.open(p, os.O_CREAT | os.O_EXCL | os.O_WRONLY))), \
            "second O_EXCL create fails (this client only)"

    def mkdir_once():
        p = os.path.join(s, "m")
        os.mkdir(p)
        return _expect_exists_error(lambda: os.mkdir(p)), "second mkdir fails (this client only)"

    def rename_dir():
        a, b, target = os.path.join(s, "pa"), os.path.join(s, "pb"), os.path.join(s, "claimed")
        for x in (a, b):
            os.mkdir(x)
            fsutil.atomic_write(os.path.join(x, "data"), x.encode())
        os.rename(a, target)
        refused = _expect_exists_error(lambda: os.rename(b, target))
        kept = fsutil.read_bytes(os.path.join(target, "data"), 4096) == a.encode()  # bounded, no links
        empty = os.path.join(s, "empty")
        os.mkdir(empty)
        os.rename(b, empty)  # onto an empty directory: allowed (an empty decision is replaced)
        ok = refused and kept
        return ok, ("a second directory rename onto a non-empty one fails and the first stays"
                    if ok else "a directory rename replaced a non-empty directory")

    def create_once():
        p = os.path.join(s, "decided.json")
        first = claim.create_once(p, b"first")
        second = claim.create_once(p, b"second")
        ok = first == (b"first", True) and second == (b"first", False) and claim.read_once(p) == b"first"
        return ok, "rl_pool.protocol.claim.create_once: the second proposal reads the first's bytes" \
            if ok else f"got {first} then {second}"

    def fsync_dir():
        fd = os.open(s, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        return True, "fsync of a file and of a directory"

    try:
        check("write, fsync, read back after close", True, write_read)
        check("atomic replace", True, replace)
        check("listing shows a just-written file", True, listing)
        check("fsync", True, fsync_dir)
        check("directory rename onto a non-empty directory fails", True, rename_dir)
        check("create-once decision (mkdir + write + directory rename)", True, create_once)
        check("mkdir create-once", False, mkdir_once)
        check("hard links", False, hard_link)
        check("link create-once", False, link_once)
        check("O_EXCL create-once", False, excl_once)
    finally:
        claim.remove_tree(s)
    return out


def quick_check(d) -> list[str]:
    """Problems that make a pool in ``d`` unsafe, as one line each; empty if none was found.

    Cheap (a dozen small files in a temp directory, removed again): meant for pool
    creation. It cannot see cross-host races; ``rl-pool doctor DIR --peer`` can.
    """
    d = os.fspath(d)
    problems, _ = mount_notes(filesystem(d))
    try:
        results = local_checks(d, required_only=True)
    except OSError as exc:
        return [*problems, f"cannot write test files in {d}: {exc.strerror or exc}"]
    problems += [f"{r['check']}: {r['detail']}" for r in results if r["required"] and not r["ok"]]
    return problems


def diagnose(d: str, peer: bool = False, rounds: int = 50, session: str = "default",
             timeout: float = 120.0) -> dict:
    fs = filesystem(d)
    problems, notes = mount_notes(fs)
    checks = local_checks(d)
    problems += [f"{c['check']}: {c['detail']}" for c in checks if c["required"] and not c["ok"]]
    race = None
    if peer:
        race = peer_race(d, rounds=rounds, session=session, timeout=timeout)
        if not race["primitives"]["rename-dir"]["exclusive"]:
            problems.append("directory renames were not exclusive across the two clients: two "
                            "members could both decide an iteration")
        for prim in ("link", "excl"):
            if not race["primitives"][prim]["exclusive"]:
                notes.append(f"{DESCRIBE[prim]} is not exclusive across these clients; rl-pool "
                             "does not rely on it (other tools that do would break here)")
    return {"dir": d, "filesystem": fs, "checks": checks, "race": race, "problems": problems,
            "notes": notes, "safe": not problems}


def format_report(r: dict) -> str:
    fs = r["filesystem"]
    lines = [f"rl-pool doctor {r['dir']}",
             f"filesystem: {fs['type']} {fs['source']} mounted at {fs['mount_point']}",
             f"  options: {fs['options'] or '(not readable)'}",
             "checks on this client:"]
    for c in r["checks"]:
        mark = "ok  " if c["ok"] else ("FAIL" if c["required"] else "no  ")
        lines.append(f"  {mark} {c['check']:<56} {c['ms']:7.2f} ms  {c['detail']}")
    race = r["race"]
    if race is not None:
        lines.append(f"race with {race['peer']} ({race['rounds']} rounds per primitive, same names, "
                     "both clients at once):")
        for prim, p in race["primitives"].items():
            verdict = "exclusive" if p["exclusive"] else "NOT exclusive"
            lines.append(f"  {DESCRIBE[prim]:<56} one winner {p['exactly_one']:>3}, both won "
                         f"{p['both_won']:>3}, none {p['none_won']:>3}; clients read different "
                         f"winners in {p['clients_disagree']:>3}  -> {verdict}")
    elif r["safe"]:
        lines.append("cross-client races: not checked (run `rl-pool doctor DIR --peer` on two hosts "
                     "or mounts at the same time)")
    for n in r["notes"]:
        lines.append(f"note: {n}")
    for p in r["problems"]:
        lines.append(f"PROBLEM: {p}")
    if r["safe"]:
        lines.append("verdict: a pool can live here" +
                     (" (from this client; cross-client races not checked)" if race is None else "") + ".")
    else:
        lines.append("verdict: NOT safe for a pool. Use a local disk (members on one host), an NFS "
                     "mount (hard, with close-to-open), Lustre, GPFS or CephFS, and run this check "
                     "again.")
    return "\n".join(lines)


def add_parser(subparsers) -> argparse.ArgumentParser:
    """``rl-pool doctor``: ``doctor.add_parser(sub)`` in :func:`rl_pool.commands.cli.build_parser`."""
    p = subparsers.add_parser(
        "doctor", help="check that a directory's filesystem can hold a pool",
        description="Check the filesystem holding DIR for what a pool needs (atomic replace, "
                    "exclusive create-once, visibility after close). With --peer, run the same "
                    "command on a second host or mount against the same DIR at the same time: the "
                    "two race each other and both print the result.")
    p.add_argument("dir", help="a directory on the filesystem to check (e.g. where the pool will live)")
    p.add_argument("--peer", action="store_true",
                   help="race a second `rl-pool doctor DIR --peer` run on another host or mount")
    p.add_argument("--rounds", type=int, default=50, help="races per primitive with --peer (default 50)")
    p.add_argument("--session", default="default",
                   help="name of the meeting place under DIR/.rl-pool-doctor (default 'default')")
    p.add_argument("--peer-timeout", type=float, default=120.0, metavar="S",
                   help="seconds to wait for the peer (default 120)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """0: a pool can live there; 1: it cannot (or the peer never came); 2: DIR is not a directory."""
    d = os.path.abspath(args.dir)
    if not os.path.isdir(d):
        sys.stderr.write(f"rl-pool doctor: {d} is not a directory\n")
        return 2
    try:
        r = diagnose(d, peer=args.peer, rounds=args.rounds, session=args.session,
                     timeout=args.peer_timeout)
    except PeerTimeout as exc:
        sys.stderr.write(f"rl-pool doctor: {exc}\n")
        return 1
    except OSError as exc:
        sys.stderr.write(f"rl-pool doctor: cannot test {d}: {exc.strerror or exc}\n")
        return 1
    print(json.dumps(r, indent=1) if args.json else format_report(r))
    return 0 if r["safe"] else 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rl_pool.protocol.doctor")
    sub = p.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = p.parse_args(["doctor", *(sys.argv[1:] if argv is None else argv)])
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
