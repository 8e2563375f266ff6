"""Create-once decisions that hold across clients of a shared filesystem.

A pool decides three kinds of thing exactly once, with no coordinator: its
config (``pool.json``), the initial agent (``iterations/000000/initial.npz``)
and, per iteration, the selection (``selected.json``). Several members may
propose at the same moment, from different hosts; exactly one proposal must
win, and every member must end up reading the winner's bytes.

How a decision is made
----------------------
A proposer writes its complete proposal into a private directory
``.NAME.once.tmp-HOST-PID-RANDOM/data`` (fsynced), then renames that
directory to the decision's name ``.NAME.once``::

    rename(".selected.json.once.tmp-node7-4711-9f3a", ".selected.json.once")

``rename(2)`` of a directory onto an existing, non-empty directory fails
(``ENOTEMPTY`` or ``EEXIST``; POSIX), and the check and the rename are one
step where the namespace lives: one RENAME call on an NFS server, the
metadata server on Lustre, GPFS/Spectrum Scale, CephFS and BeeGFS, and on
SeaweedFS the filer, which holds a lock on both paths while it renames (and
in our measurement 6 racers on two FUSE mounts had exactly one winner in each
of 230 rounds). So exactly one proposal becomes the decision, **and its
content arrives with it**: there is never a moment when the name is taken
but empty, so a proposer that dies at any point leaves either nothing (its
private directory is a temp name, never read) or a complete decision.

Why not the obvious primitives
------------------------------
* ``link(2)`` of a complete temp file, or ``open(O_CREAT|O_EXCL)``: exclusive
  on local disks and NFS, but **not** across SeaweedFS 4.48 FUSE mounts (a
  mount creates a file in its own metadata cache and tells the filer only
  on close: both racers succeed and each mount keeps seeing its own file).
  A 3-member pool on two mounts made two different "first" selections in 3
  of 4 runs.
* ``mkdir`` as the claim, then the content written inside: ``mkdir`` is
  exclusive everywhere we looked, but it is only a test-and-set; the value
  must follow in a second step. A claimer that dies (or stalls: SIGSTOP,
  swapping, a hung NFS server) between the two steps leaves a claim without
  content, and the others cannot tell dead from slow. Completing it for the
  claimer works only when the content is a pure function of files every
  member can read, which a selection made by a quorum that went on without
  a member is not (which deposits count depends on when each member looked),
  nor ``pool.json`` (the creating member's arguments). Taking a claim over
  after a deadline lets a slow claimer wake up and write a second decision.
  (Test-and-set cannot give agreement among three or more processes that
  may crash; an operation that installs a value in the same step, as this
  rename does, can.)

Readers accept only a complete, verified decision: ``data`` starts with one
line ``rl-pool-once 1 sha256=HEX size=N by=TOKEN`` and the payload must
match it, and pass the caller's own check (``accept``: the pool's HMAC
signature, :mod:`rl_pool.protocol.keys`). ``TOKEN`` names the proposal, so a proposer
whose rename reply was lost (an NFS retransmission answers ``ENOENT`` or
``ENOTEMPTY`` for a rename that happened) still learns that it won.

Things that decide nothing never wedge a decision, and are never removed
(an honest member may be reading them, and only the server can say what it
holds now): a decision has ordered slots ``.NAME.once``, ``.NAME.once.1``,
... up to :data:`MAX_SLOTS`. The decision is the first valid slot. A slot
held by something invalid (a file, a link, a FIFO, a bad header, a forged
signature) is passed over by everyone, and proposals go to the next slot;
so is a directory that stays without readable ``data`` for ``wait``
seconds. Proposers walk the slots in the same order and never pass over an
empty one, so every member stops at the same slot. An empty ``.NAME.once``
directory (a stray ``mkdir``; a SeaweedFS filer that died in the middle of
moving a directory's entries) is simply replaced by the next proposal's
rename (renaming onto an empty directory is allowed).

After the decision, the plain file ``NAME`` is published: the winner writes
it (temp file, fsync, ``os.replace``), and anyone who finds it missing writes
it too (:func:`publish_missing`: a member does so for its last iterations
when it starts). Every write of ``NAME`` carries the decided bytes, so
replacing it is harmless; people and tools (``status``, ``jq``, the SLURM script) read
``NAME``, while members decide from ``.NAME.once``.

Costs: a decision is one ``mkdir``, one file written and fsynced, one
``rename``, and the published copy; reading one is one file open (plus the
directory walk that :func:`rl_pool.fsutil.read_bytes` does with ``root``).
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import shutil
import stat
import time

from rl_pool import fsutil
from rl_pool.errors import UnsafeFile

log = logging.getLogger("rl_pool")

SUFFIX = ".once"
DATA = "data"
MAGIC = "rl-pool-once"
VERSION = "1"
#: Cap on a decision's payload (an agent is the largest thing decided: the initial agent).
MAX_BYTES = fsutil.AGENT_MAX_BYTES
_HEADER_MAX = 512
#: Rename errors after which the decision may exist (someone else's, or ours with a lost reply).
_MAYBE_DECIDED = {errno.ENOTEMPTY, errno.EEXIST, errno.ENOENT, errno.EIO, errno.ESTALE, errno.ETIMEDOUT}


class InvalidDecision(ValueError):
    """A decision whose ``data`` does not verify (or that ``accept`` rejects): it decides nothing."""


class ClaimError(RuntimeError):
    """No decision could be made or read: every slot is occupied by things that decide nothing,
    or a slot stayed unreadable for longer than the wait."""


#: Ordered slots of one decision: ``.NAME.once``, then ``.NAME.once.1``, ... (see below).
MAX_SLOTS = 16


def decision_dir(path, slot: int = 0) -> str:
    """``DIR/.NAME.once`` (slot 0) or ``DIR/.NAME.once.K``: where the decision about ``DIR/NAME`` is."""
    d, base = os.path.split(os.path.abspath(os.fspath(path)))
    return os.path.join(d, f".{base}{SUFFIX}" + (f".{slot}" if slot else ""))


def is_decision_dir(name: str) -> bool:
    """True for ``.NAME.once`` and ``.NAME.once.K`` (not for a proposal ``....tmp-...``)."""
    if not name.startswith(".") or fsutil.is_tmp(name):
        return False
    head, _, tail = name.rpartition(".")
    return name.endswith(SUFFIX) or (tail.isdigit() and head.endswith(SUFFIX))




def envelope(data: bytes, token: str) -> bytes:
    """``data`` with its header line: what ``.NAME.once/data`` holds."""
    head = f"{MAGIC} {VERSION} sha256={hashlib.sha256(data).hexdigest()} size={len(data)} by={token}\n"
    return head.encode("ascii") + data


def unwrap(raw: bytes, where: str = "decision") -> tuple[bytes, str]:
    """``(payload, token)`` of an envelope; :class:`InvalidDecision` unless it verifies."""
    nl = raw.find(b"\n", 0, _HEADER_MAX)
    if nl < 0:
        raise InvalidDecision(f"{where}: no header line")
    try:
        magic, version, *fields = raw[:nl].decode("ascii").split(" ")
        kv = dict(f.split("=", 1) for f in fields)
        sha, size, token = kv["sha256"], int(kv["size"]), kv["by"]
    except (UnicodeDecodeError, ValueError, KeyError):
        raise InvalidDecision(f"{where}: malformed header") from None
    if magic != MAGIC or version != VERSION:
        raise InvalidDecision(f"{where}: not an rl-pool decision (format {magic} {version})")
    payload = raw[nl + 1:]
    if len(payload) != size or hashlib.sha256(payload).hexdigest() != sha:
        raise InvalidDecision(f"{where}: content does not match its header (size or sha256)")
    return payload, token


# What one slot holds: ("absent",), ("pending",) (a directory without readable data yet),
# ("invalid", reason) or ("valid", payload, token).
def _slot(path: str, k: int, root, cap: int, accept) -> tuple:
    d = decision_dir(path, k)
    f = os.path.join(d, DATA)
    # One lookup answers the common case of a waiting member (nothing decided yet).
    try:
        st = fsutil.lstat(d, root)
    except FileNotFoundError:
        return ("absent",)
    except UnsafeFile as exc:
        return ("invalid", f"{d}: {exc.strerror}")
    except OSError as exc:
        return ("invalid", f"{d}: {exc.strerror or exc}")
    if not stat.S_ISDIR(st.st_mode):
        return ("invalid", f"{d} is not a directory")
    try:
        raw = fsutil.read_bytes(f, cap + _HEADER_MAX, root=root)
    except (FileNotFoundError, NotADirectoryError):
        return ("pending",)  # SeaweedFS still moving a renamed directory's entries; or junk
    except UnsafeFile as exc:
        return ("invalid", f"{f}: {exc.strerror}")
    try:
        payload, token = unwrap(raw, f)
    except InvalidDecision as exc:
        return ("invalid", str(exc))
    why = accept(payload) if accept is not None else None
    if why:
        return ("invalid", f"{f}: {why}")
    return ("valid", payload, token)


def read_once(path, root=None, cap: int = MAX_BYTES, accept=None) -> bytes | None:
    """The decided bytes for ``path``, or None while nothing is decided.

    ``root``: the pool directory, so the read never goes through a symbolic link
    (:func:`rl_pool.fsutil.read_bytes`). ``accept(payload) -> reason or None``: the
    caller's own check (a signature); a decision it rejects counts as invalid.
    Slots are read in order: the first valid one is the decision; invalid ones (and
    ones still being written) are passed over; an absent one ends the search.
    """
    path = os.fspath(path)
    for k in range(MAX_SLOTS):
        got = _slot(path, k, root, cap, accept)
        if got[0] == "valid":
            return got[1]
        if got[0] == "absent":
            return None
    return None


def why_undecided(path, root=None, cap: int = MAX_BYTES, accept=None) -> str | None:
    """Why :func:`read_once` finds no decision although something occupies the first slot
    (for error messages: "a FIFO, not a regular file"), or None."""
    path = os.fspath(path)
    first = None
    for k in range(MAX_SLOTS):
        got = _slot(path, k, root, cap, accept)
        if got[0] == "valid":
            return None
        if got[0] == "absent":
            return first
        if got[0] == "invalid" and first is None:
            first = got[1]
    return first


def create_once(path, data: bytes, root=None, wait: float = 120.0, cap: int = MAX_BYTES,
                accept=None) -> tuple[bytes, bool]:
    """Decide ``path`` once: ``(the decided bytes, whether this call decided them)``.

    If a decision exists, it is returned (and the plain copy ``path`` published if
    missing); else ``data`` is proposed, and either it wins or the winner's bytes
    are returned. ``accept`` as for :func:`read_once`. ``wait``: how long a slot
    that exists may stay unreadable here before it counts as invalid (SeaweedFS
    shows a rename to another mount in milliseconds; an NFS client that cached
    "no such file" may take up to ``acdirmax``, see docs/cluster.md). Raises
    :class:`ClaimError` when all :data:`MAX_SLOTS` slots decide nothing.
    """
    path = os.fspath(path)
    if len(data) > cap:
        raise ValueError(f"{len(data)} bytes is more than the {cap}-byte cap of a decision")
    own = accept(data) if accept is not None else None
    if own:
        raise ValueError(f"the proposal for {path} fails its own check: {own}")
    reasons, k, tries = [], 0, 0
    while k < MAX_SLOTS:
        got = _slot(path, k, root, cap, accept)
        token = None
        if got[0] in ("absent", "pending"):
            # A rename replaces an empty directory (a stray mkdir, a SeaweedFS filer that died
            # mid-rename) and fails on one with entries (an honest decision still arriving).
            token = fsutil.writer_token(12)
            err = _propose(decision_dir(path, k), envelope(data, token))
            if err is None:
                fsutil._fsync_dir(os.path.dirname(os.path.abspath(path)))
                _publish(path, data, root=root)
                return data, True
            if err.errno not in _MAYBE_DECIDED | {errno.ENOTDIR}:
                raise OSError(err.errno, err.strerror, path)
            got = _await(path, k, root, cap, accept, wait)  # someone else's (or ours, reply lost)
        if got[0] == "valid":
            _publish(path, got[1], missing_only=True, root=root)
            return got[1], token is not None and got[2] == token
        if got[0] == "absent":
            # Never pass over an absent slot (readers stop there): propose in it again.
            tries += 1
            if tries > 3:
                raise ClaimError(f"no decision for {path}: renames into {decision_dir(path, k)} fail "
                                 "but nothing shows there")
            continue
        reasons.append(got[1] if got[0] == "invalid" else f"{decision_dir(path, k)} unreadable for {wait:.0f}s")
        log.warning("%s: %s; deciding in the next slot", path, reasons[-1])
        k += 1
    raise ClaimError(f"no decision for {path}: all {MAX_SLOTS} slots hold things that decide nothing "
                     f"(first: {reasons[0]})")


def _propose(final: str, content: bytes) -> OSError | None:
    """Rename a complete proposal onto ``final``; None if this rename made the decision."""
    prop = fsutil.tmp_name(final)
    try:
        os.mkdir(prop, 0o755)
    except OSError as exc:  # a full or read-only disk: name the decision, not the temp directory
        raise fsutil._named(exc, _plain_name(final)) from None
    try:
        try:
            _write_new(os.path.join(prop, DATA), content)
        except OSError as exc:
            raise fsutil._named(exc, _plain_name(final)) from None
        fsutil._fsync_dir(prop)
        try:
            os.rename(prop, final)
            return None
        except OSError as exc:
            return exc
    finally:
        remove_proposal(prop)


def _plain_name(final: str) -> str:
    """``DIR/NAME`` for a decision directory ``DIR/.NAME.once[.K]`` (what a person knows it as)."""
    d, base = os.path.split(final)
    name = base[1:] if base.startswith(".") else base
    name = name.split(".once")[0]
    return os.path.join(d, name)


def _await(path: str, k: int, root, cap: int, accept, wait: float) -> tuple:
    """Poll slot ``k`` until it is valid or invalid here (1 ms .. 100 ms apart), at most ``wait``
    seconds. An absent slot is polled too: this client may not see yet what the server refused
    our rename for (a cached "no such file")."""
    deadline = time.monotonic() + wait
    delay = 0.001
    while True:
        got = _slot(path, k, root, cap, accept)
        if got[0] in ("valid", "invalid") or time.monotonic() >= deadline:
            return got
        time.sleep(delay)
        delay = min(delay * 2, 0.1)


def publish_missing(path, root=None, cap: int = MAX_BYTES, accept=None) -> bool:
    """Write the plain copy ``path`` of a decision that lacks it (its winner stopped, or found the
    disk full, between deciding and publishing); True if a decision was there to copy."""
    path = os.fspath(path)
    data = read_once(path, root=root, cap=cap, accept=accept)
    if data is None:
        return False
    _publish(path, data, missing_only=True, root=root)
    return True


def _publish(path: str, payload: bytes, missing_only: bool = False, root=None) -> None:
    """Write the plain copy ``path`` of a decided payload (any number of writers: same bytes).

    A rename replaces a file, a link or a FIFO at ``path``, not a directory: a directory
    there (never written by a member) is moved aside first (:func:`rl_pool.fsutil.set_aside`).
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    except OSError:
        return
    if st is not None and missing_only and stat.S_ISREG(st.st_mode):
        return
    try:
        if st is not None and stat.S_ISDIR(st.st_mode):
            log.warning("removing the directory at %s", path)
            fsutil.set_aside(path, (st.st_dev, st.st_ino), root=root)
        fsutil.atomic_write(path, payload)
    except OSError as exc:
        # The decision stands without its copy; members never read the copy.
        log.warning("could not publish %s: %s", path, exc.strerror or exc)


def _write_new(path: str, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_tree(path: str, tries: int = 5) -> None:
    """Remove a directory tree, quiet if it is gone or goes while this runs.

    ``shutil.rmtree(ignore_errors=True)`` alone can still raise in Python 3.11: the ``fstat`` of a
    subdirectory it has just opened is not covered, and on a FUSE mount (SeaweedFS) that ``fstat``
    fails with ENOENT when another client removes the same tree at the same moment. Each try
    removes what is left; what another client removed counts as removed."""
    for _ in range(tries):
        try:
            shutil.rmtree(path, ignore_errors=True)
        except FileNotFoundError:
            continue
        return


def remove_proposal(path: str) -> None:
    """Remove a proposal directory (or a temp file) and what it holds; quiet if it is gone."""
    try:
        st = os.lstat(path)
    except OSError:
        return
    if stat.S_ISDIR(st.st_mode):
        remove_tree(path)
    else:
        try:
            os.unlink(path)
        except OSError:
            pass
