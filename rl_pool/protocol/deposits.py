"""Deposits and selections on disk: a member's agent and metrics written, the iteration's
deposits found, read and verified, and the decided selections read back. How the pool uses them
is described in ``docs/protocol.md``.
"""

from __future__ import annotations

import collections
import errno
import json
import logging
import os
import stat

from rl_pool import fsutil
from rl_pool.errors import AgentFileError, UnsafeFile
from rl_pool.fsutil import why as _why
from rl_pool.maths.agent import Agent, max_file_bytes
from rl_pool.protocol import selection
from rl_pool.protocol.layout import DEPOSIT_RE, ITER_RE, Paths, member_name, sha256

log = logging.getLogger("rl_pool")


_warned: set = set()


def _warn_once(key, msg: str, *args) -> None:
    """Log a refused file once per process, not on every barrier poll."""
    if key not in _warned:
        if len(_warned) > 10_000:
            _warned.clear()
        _warned.add(key)
        log.warning(msg, *args)


def iterations_on_disk(paths: Paths) -> list[int]:
    """The iteration directories (real directories only: a symbolic link named like one is ignored)."""
    return sorted(int(n) for n in fsutil.subdirs(paths.iterations, root=paths.root) if ITER_RE.match(n))


def read_selected(paths: Paths, i: int) -> dict | None:
    """The selection of iteration ``i`` (its decision, signed by a key holder) or None if not (yet,
    or readably) there."""
    try:
        data = paths.decision(paths.selected(i))
        if data is None:
            return None
        doc = json.loads(data.decode("utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        _warn_once((paths.selected(i), str(exc)), "unreadable %s: %s", paths.selected(i), _why(exc))
        return None
    if not isinstance(doc, dict) or doc.get("iteration") != i:
        return None
    why = paths.why_unsigned(doc)
    if why:
        _warn_once((paths.selected(i), why), "ignoring %s: %s (not written by a key holder)",
                   paths.selected(i), why)
        return None
    return doc




def last_selected(paths: Paths) -> int:
    """The highest iteration whose selection is on disk (0: only the initial agent)."""
    for i in reversed(iterations_on_disk(paths)):
        if read_selected(paths, i) is not None:
            return i
    return -1


def load_selected_agent(paths: Paths, i: int, sel: dict | None = None, like: Agent | None = None) -> Agent:
    """The agent selected in iteration ``i``, checked against the hash in ``selected.json``
    (``sel``: that file's content, if the caller has already read it; ``like``: an agent of
    this pool, whose shapes cap the file's size)."""
    sel = sel if sel is not None else read_selected(paths, i)
    if sel is None:
        raise RuntimeError(f"iteration {i} has no selection")
    return load_named_agent(paths, sel, f"selected in iteration {i}", paths.selected(i), like)


def load_named_agent(paths: Paths, ref: dict, what: str, where: str, like: Agent | None = None) -> Agent:
    """The agent a signed record ``ref`` names (``agent``: its path in the pool, ``agent_sha256``),
    checked against that hash; ``what`` and ``where`` (the record's file) word the errors."""
    known = _parsed.get(ref.get("agent_sha256"))
    if known is not None:  # parsed from bytes with that hash already (the parent kept, the winner we checked)
        _parsed.move_to_end(ref["agent_sha256"])
        return known
    path = paths.resolve(ref["agent"])
    cap = max_file_bytes(like.meta) if like is not None else fsutil.AGENT_MAX_BYTES
    try:
        data = paths.read_bytes(path, cap)
    except UnsafeFile as exc:
        raise RuntimeError(f"{path} ({what}) is refused: {exc.strerror}") from None
    digest = sha256(data)
    if digest != ref.get("agent_sha256"):
        raise RuntimeError(f"{path} does not match the hash recorded in {where}")
    return parse_agent(data, digest, path)


#: Agents parsed from pool files, by the SHA-256 of their bytes, most recent last. The member
#: that selects reads the winner's agent and trains from it next; equal bytes parse to equal
#: agents, so the second parse (about a millisecond) is skipped. Their arrays are read-only,
#: so no holder can change an agent another holder uses (training makes new agents; nothing
#: assigns into an agent's dictionaries of arrays, and nothing may).
_parsed: collections.OrderedDict[str, Agent] = collections.OrderedDict()
PARSED_KEEP = 4


def parse_agent(data: bytes, digest: str, source: str) -> Agent:
    """``Agent.from_bytes(data)`` (``digest``: ``sha256(data)``), parsed once per distinct file."""
    agent = _parsed.get(digest)
    if agent is not None:
        _parsed.move_to_end(digest)
        return agent
    agent = Agent.from_bytes(data, source=source)
    for tree in (agent.params, agent.opt_m, agent.opt_v):
        for a in tree.values():
            a.flags.writeable = False
    agent.norm.mean.flags.writeable = agent.norm.m2.flags.writeable = False
    _parsed[digest] = agent
    while len(_parsed) > PARSED_KEEP:
        _parsed.popitem(last=False)
    return agent


# ---------------------------------------------------------------- deposits
def make_iteration_dir(paths: Paths, i: int) -> str:
    """``iterations/00000i`` as a real directory: anything else a stranger put at that name (a
    symlink out of the pool, a file, a FIFO) is set aside first, so no write leaves the pool."""
    d = paths.iteration(i)
    os.makedirs(paths.iterations, exist_ok=True)
    for _ in range(3):
        try:
            os.mkdir(d)
            return d
        except FileExistsError:
            st = os.lstat(d)
            if stat.S_ISDIR(st.st_mode):
                return d
            log.warning("%s is not a directory (%s): set aside", d, fsutil._kind(st.st_mode))
            fsutil.set_aside(d, (st.st_dev, st.st_ino), root=paths.root)
        except FileNotFoundError:  # the vanishing race with set_aside of a stranger's link
            continue
    raise UnsafeFile(errno.EEXIST, "cannot make it a directory", d)


def deposit(paths: Paths, i: int, m: int, agent: Agent, metrics: dict) -> dict:
    """Write agent then metrics, each atomically; the metrics file marks the deposit done."""
    make_iteration_dir(paths, i)
    data = agent.to_bytes()
    fsutil.atomic_write(paths.deposit_npz(i, m), data, sync_dir=False)  # the metrics' directory fsync covers it
    # Non-finite numbers are written as null (JSON has no NaN); selection then skips the deposit.
    doc = paths.sign(fsutil.finite_or_null({"iteration": i, "member": m, "agent_sha256": sha256(data), **metrics}))
    fsutil.write_json(paths.deposit_json(i, m), doc)
    return doc


def present(paths: Paths, i: int, pool_size: int) -> set[int]:
    """Members whose deposit marker exists; anything else in the directory is ignored."""
    try:
        names = fsutil.listdir(paths.iteration(i), root=paths.root)
    except UnsafeFile as exc:
        # A symlinked iteration directory counts nothing: no deposit is read through it.
        _warn_once((paths.iteration(i), "listing"), "iteration %d: %s", i, _why(exc))
        return set()
    out = set()
    for name in names:
        mm = DEPOSIT_RE.match(name)
        # exact names only: "member-0001.json" is a stray, not member 1
        if mm and int(mm.group(1)) < pool_size and name == member_name(int(mm.group(1))) + ".json":
            out.add(int(mm.group(1)))
    return out


def read_metrics(paths: Paths, i: int, m: int) -> dict:
    """A deposit's metrics, or raise ValueError with the reason they are invalid: the JSON parses,
    carries the pool key's signature, names this iteration and member, and has a finite return."""
    try:
        doc = paths.read_json(paths.deposit_json(i, m), missing_retries=5)
    except UnsafeFile as exc:
        raise ValueError(f"metrics refused ({exc.strerror})") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"metrics unreadable ({type(exc).__name__})") from None
    if not isinstance(doc, dict):
        raise ValueError("metrics are not a JSON object")
    why = paths.why_unsigned(doc)
    if why:
        raise ValueError(f"metrics {why} (not written by a key holder)")
    if doc.get("iteration") != i or doc.get("member") != m:
        raise ValueError("metrics name another iteration or member")
    ret = doc.get("eval_return")
    if not selection.finite(ret):
        raise ValueError(f"eval_return is not a finite number ({str(ret)[:40]})")
    return doc


def read_agent(paths: Paths, i: int, m: int, doc: dict, like: Agent | None = None) -> Agent:
    """The agent of a deposit whose metrics are ``doc``, or raise ValueError: the ``.npz`` matches
    the hash in the metrics, loads without pickle, holds finite arrays of the right shapes, and
    fits the pool's env and policy (``like``)."""
    cap = max_file_bytes(like.meta) if like is not None else fsutil.AGENT_MAX_BYTES
    try:
        data = paths.read_bytes(paths.deposit_npz(i, m), cap, missing_retries=5)
    except UnsafeFile as exc:
        raise ValueError(f"agent refused ({exc.strerror})") from None
    except OSError as exc:
        raise ValueError(f"agent unreadable ({exc.strerror or exc})") from None
    digest = sha256(data)
    if digest != doc.get("agent_sha256"):
        raise ValueError("agent does not match the hash in its metrics")
    try:
        agent = parse_agent(data, digest, member_name(m) + ".npz")
    except AgentFileError as exc:
        raise ValueError(str(exc)) from None
    if like is not None and (agent.meta != like.meta):
        raise ValueError("agent was made for another environment or policy shape")
    return agent


def read_deposit(paths: Paths, i: int, m: int, like: Agent | None = None):
    """``(metrics, agent)`` of a deposit, or raise ValueError with the reason it is invalid
    (:func:`read_metrics`, then :func:`read_agent`)."""
    doc = read_metrics(paths, i, m)
    return doc, read_agent(paths, i, m, doc, like)
