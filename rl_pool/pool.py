"""The shared-directory protocol: init, deposit, barrier, selection, resume, GC.

There is no coordinator: every member reads and writes files in ``POOL/`` and
all members reach the same decisions because the decisions are pure functions
of immutable, atomically written files::

    pool.json                        pool-wide config (create-once)
    iterations/000000/initial.npz    the initial agent; selected.json points at it
    iterations/000007/member-002.npz member 2's agent after training in iteration 7
    iterations/000007/member-002.json its metrics: written last, marks the deposit done
    iterations/000007/member-002.wait.json  its time at the barrier (known only after it)
    iterations/000007/selected.json  the winner and why (create-once: the first decision stands)
    best.npz, best.json              best selected agent so far
    members/member-002.json          heartbeat
    logs/member-002.log              log

``pool.json``, ``initial.npz`` and each ``selected.json`` are decided once with
:func:`rl_pool.claim.create_once`: the decision is ``.NAME.once/data`` (a
complete directory renamed into place: exclusive on local disks, NFS, Lustre,
GPFS and SeaweedFS alike, where ``link`` is not) and ``NAME`` its published
copy for people and tools. If two members ever disagree (one went on with a
quorum while a late deposit landed) the first decision stands and everyone
adopts it; members read decisions, never the copies.
"""

from __future__ import annotations

import collections
import errno
import hashlib
import json
import logging
import os
import stat
import time

from . import claim, fsutil, layout, merge, selection
from .agent import Agent, max_file_bytes
from .config import PROTOCOL, READABLE_PROTOCOLS, OldProtocol, PoolConfig
from .errors import AgentFileError, UnsafeFile, UsageError
from .heartbeat import HOST, pid_alive
from .layout import DEPOSIT_RE, ITER_RE, member_name

log = logging.getLogger("rl_pool")



def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class Paths:
    """Where each file of a pool lives."""

    def __init__(self, root):
        self.root = fsutil.Root(root)
        self.pool_json = os.path.join(self.root, "pool.json")
        self.lock = os.path.join(self.root, ".init.lock")
        self.iterations = os.path.join(self.root, "iterations")
        self.members = os.path.join(self.root, "members")
        self.logs = os.path.join(self.root, "logs")
        self.best_npz = os.path.join(self.root, "best.npz")
        self.best_json = os.path.join(self.root, "best.json")
        self._legacy: bool | None = None

    def iteration(self, i: int) -> str:
        return os.path.join(self.iterations, f"{i:06d}")

    def initial(self) -> str:
        return os.path.join(self.iteration(0), "initial.npz")

    def deposit_npz(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".npz")

    def deposit_json(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".json")

    def wait_json(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".wait.json")

    def selected(self, i: int) -> str:
        return os.path.join(self.iteration(i), "selected.json")

    def heartbeat(self, m: int) -> str:
        return os.path.join(self.members, member_name(m) + ".json")

    def log(self, m: int) -> str:
        return os.path.join(self.logs, member_name(m) + ".log")

    def holding(self, d: str):
        """Reads below directory ``d`` start from one descriptor while the block runs (fsutil.Root)."""
        return self.root.holding(d)

    def rel(self, path: str) -> str:
        return os.path.relpath(path, self.root)

    #: The pool's key (:mod:`rl_pool.keys`) once :func:`open_pool` or :func:`attach_key` found it.
    #: With a key every decision file is signed when written and checked when read; without one
    #: (a reader such as ``status`` that cannot find the key) files are read unverified.
    key = None

    def sign(self, doc: dict) -> dict:
        return self.key.sign(doc) if self.key is not None else doc

    def why_unsigned(self, doc) -> str | None:
        """None if ``doc`` may decide something here, else why not (unsigned, bad signature)."""
        return None if self.key is None else self.key.why_invalid(doc)

    def signed(self, payload: bytes) -> str | None:
        """``accept`` for :mod:`rl_pool.claim`: why a decided JSON document may not decide here."""
        try:
            doc = json.loads(payload.decode("utf-8"))
        except ValueError:
            return "not JSON"
        return self.why_unsigned(doc)

    def decision(self, path: str, cap: int = fsutil.JSON_MAX_BYTES, signed: bool = True) -> bytes | None:
        """The decided bytes of ``path`` (``pool.json``, ``initial.npz``, ``selected.json``), or None.
        In a pool made before decisions (protocol 2: ``pool.json`` without ``.pool.json.once``),
        the plain file, for readers such as ``status`` (members refuse such pools)."""
        data = claim.read_once(path, root=self.root, cap=cap, accept=self.signed if signed else None)
        if data is None and self.legacy():
            try:
                data = self.read_bytes(path, cap)
            except FileNotFoundError:
                return None
        return data

    def legacy(self) -> bool:
        if self._legacy is None:
            self._legacy = os.path.exists(self.pool_json) and not os.path.isdir(claim.decision_dir(self.pool_json))
        return self._legacy

    def read_json(self, path: str, missing_retries: int = 0):
        """A JSON file of this pool, read bounded and never through a link (:mod:`rl_pool.fsutil`)."""
        return fsutil.read_json(path, missing_retries=missing_retries, root=self.root)

    def read_bytes(self, path: str, cap: int = fsutil.AGENT_MAX_BYTES, missing_retries: int = 0) -> bytes:
        """A file of this pool (an agent), read bounded and never through a link."""
        return fsutil.read_bytes(path, cap, missing_retries=missing_retries, root=self.root)

    def resolve(self, rel: str) -> str:
        """A path named inside a pool file, refused if it points outside the pool."""
        full = os.path.normpath(os.path.join(self.root, rel))
        if os.path.isabs(rel) or not full.startswith(self.root + os.sep):
            raise ValueError(f"path {rel!r} points outside the pool")
        return full


# ---------------------------------------------------------------- pool.json
def read_config(paths: Paths, readonly: bool = False) -> PoolConfig:
    """The saved pool config; UsageError if the directory is not an rl-pool pool. ``readonly``
    (status, plot, evaluate) also reads pools of the older protocols members no longer run."""
    if not os.path.isdir(paths.root):
        raise UsageError(f"no pool directory at {paths.root}")
    try:
        data = paths.decision(paths.pool_json, signed=False)
    except (OSError, ValueError) as exc:
        raise UsageError(f"{paths.pool_json} is not a valid rl-pool pool config ({_why(exc)})") from None
    if data is None:
        why = claim.why_undecided(paths.pool_json, root=paths.root, cap=fsutil.JSON_MAX_BYTES)
        if why:
            raise UsageError(f"{paths.pool_json} is not a valid rl-pool pool config ({why})")
        raise UsageError(f"{paths.root} is not an rl-pool pool (no pool.json)")
    try:
        protocols = READABLE_PROTOCOLS if readonly else (PROTOCOL,)
        return PoolConfig.from_json(json.loads(data.decode("utf-8")), protocols).validate()
    except OldProtocol as exc:
        raise UsageError(
            f"{paths.root} was made by another rl-pool version (pool protocol {exc.protocol!r}, this one "
            f"speaks {PROTOCOL}); start a new --pool-dir or finish this one with the rl-pool that made it "
            "(its agents still work with evaluate and replay)") from None
    except UsageError as exc:
        raise UsageError(f"{paths.pool_json} holds invalid settings ({exc})") from None
    except (OSError, ValueError, TypeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise UsageError(f"{paths.pool_json} is not a valid rl-pool pool config ({why})") from None


def attach_key(paths: Paths, key_file: str | None = None, required: bool = True) -> bool:
    """Find the pool's key (``--key-file``, ``RL_POOL_KEY_FILE``/``RL_POOL_KEY``, or the default
    path named by ``pool.json``'s pool id), check it against the fingerprint and ``pool.json``'s
    signature, and keep it in ``paths.key``. Members need it (``required``); readers such as
    ``status`` go on without it and say so (``False``)."""
    from . import keys

    try:
        data = paths.decision(paths.pool_json, signed=False)
        doc = json.loads(data.decode("utf-8")) if data is not None else None
        if not isinstance(doc, dict) or "pool_id" not in doc or "key_fingerprint" not in doc:
            raise UsageError(f"{paths.pool_json} names no pool key")
        key = keys.load(str(doc["pool_id"]), str(doc["key_fingerprint"]), key_file)
        why = key.why_invalid(doc)
        if why:
            raise UsageError(f"{paths.pool_json} is not this pool's ({why}): someone without the key "
                             "changed it; refusing to run on it")
    except (UsageError, OSError, ValueError) as exc:
        if required:
            raise UsageError(str(exc)) from None
        return False
    paths.key = key
    return True


def open_pool(paths: Paths, requested: dict, initial_agent, lock_timeout: float = 60.0,
              key_file: str | None = None) -> PoolConfig:
    """Create the pool (once) or check that ``requested`` agrees with it.

    ``initial_agent(config) -> (Agent, resolved config)`` builds the iteration-0
    agent; it must be deterministic in the config, since any member may build it.
    Creation is a create-once decision (:mod:`rl_pool.claim`), safe without
    working locks; the file lock (with a timeout) only keeps racing members on
    one host from building the environment twice. A new pool's directory is
    first checked with :func:`rl_pool.doctor.quick_check`.
    """
    from filelock import FileLock, Timeout

    if os.path.exists(paths.root) and not os.path.isdir(paths.root):
        raise UsageError(f"{paths.root} exists and is not a directory")
    if os.path.exists(paths.pool_json):
        cfg = PoolConfig.merged(requested, read_config(paths), where=f"pool {paths.root}")
        attach_key(paths, key_file)
        _ensure_initial(paths, cfg, initial_agent)
        return cfg
    if os.path.isdir(paths.root):
        foreign = [n for n in fsutil.listdir(paths.root)
                   if n not in ("iterations", "members", "logs", ".init.lock", "pool.json")
                   and not fsutil.is_tmp(n) and not claim.is_decision_dir(n)]
        if foreign:
            raise UsageError(
                f"{paths.root} is not empty and is not an rl-pool pool (found {foreign[0]!r}); use a new --pool-dir")
    # Check everything (arguments, environment) before anything is written.
    cfg = PoolConfig.merged(requested, None)
    _, cfg = initial_agent(cfg)
    os.makedirs(paths.root, exist_ok=True)
    from .doctor import quick_check

    problems = quick_check(paths.root)
    if problems:
        raise UsageError(f"{paths.root} cannot hold a pool: {problems[0]} (`rl-pool doctor {paths.root}` "
                         "says more)")
    for d in (paths.iterations, paths.members, paths.logs):
        os.makedirs(d, exist_ok=True)
    from . import keys

    pool_id = keys.new_pool_id()
    key, where = keys.create(pool_id, key_file)
    versions = {}
    try:
        from .versions import versions as _versions

        versions = _versions()
    except Exception:  # versions are a record, never a reason to fail
        pass
    doc = fsutil.dumps(key.sign(cfg.to_json() | {"created": time.time(), "pool_id": pool_id,
                                                 "key_fingerprint": key.fingerprint(), "versions": versions}))
    try:
        with FileLock(paths.lock, timeout=lock_timeout):
            if not os.path.exists(paths.pool_json):
                claim.create_once(paths.pool_json, doc, root=paths.root, cap=fsutil.JSON_MAX_BYTES)
    except (Timeout, OSError, NotImplementedError) as exc:
        # The lock only saves duplicate work; the atomic create is what counts. On NFS
        # without a lock daemon flock fails (ENOLCK/ENOSYS): go on without it.
        log.warning("init lock %s unavailable (%s); going on without it", paths.lock, type(exc).__name__)
        claim.create_once(paths.pool_json, doc, root=paths.root, cap=fsutil.JSON_MAX_BYTES)
    cfg = PoolConfig.merged(requested, read_config(paths), where=f"pool {paths.root}")
    attach_key(paths, key_file)
    if paths.key.fingerprint() == key.fingerprint():
        log.info("pool %s created; its key is %s (mode 0600, outside the pool)", paths.root, where)
    _ensure_initial(paths, cfg, initial_agent)
    return cfg


def _ensure_initial(paths: Paths, cfg: PoolConfig, initial_agent) -> None:
    if read_selected(paths, 0) is not None:
        return
    os.makedirs(paths.iteration(0), exist_ok=True)
    agent, _ = initial_agent(cfg)
    mine = agent.to_bytes()
    # Every member builds the same agent, byte for byte (a function of the signed config); one
    # file is decided (and published as initial.npz). Bytes that differ were not made from this
    # pool's settings (a stranger's planted "initial agent"): such a slot decides nothing.
    on_disk, _ = claim.create_once(
        paths.initial(), mine, root=paths.root, cap=max_file_bytes(agent.meta),
        accept=lambda payload: None if payload == mine else "not the initial agent of this pool's settings")
    doc = {"iteration": 0, "member": None, "eval_return": None, "initial": True,
           "agent": paths.rel(paths.initial()), "agent_sha256": sha256(on_disk),
           "considered": [], "skipped": []}
    claim.create_once(paths.selected(0), fsutil.dumps(paths.sign(doc)), root=paths.root,
                      cap=fsutil.JSON_MAX_BYTES, accept=paths.signed)


# ---------------------------------------------------------------- iterations
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


def _why(exc: Exception) -> str:
    """A refused or unreadable file's reason, for logs and ``skipped`` entries."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


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


def select(paths: Paths, i: int, cfg: PoolConfig, like: Agent, members: set[int], reason: str,
           previous: dict) -> dict:
    """The selection of iteration ``i``: the deposits of ``members`` read and verified, the rule
    (:func:`rl_pool.selection.decide`) applied to them and ``previous`` (the selection of
    ``i - 1``), and, when the rule merges, the merged agent written (``merged-<hash>.npz``).

    Only the agents the rule uses are read and checked (hash, format, shapes): the winner's, or
    with a merge every valid branch's. One that fails its check is skipped with the reason (its
    reports too) and the rule is applied again without it, so the result is still a pure function
    of the files.
    """
    reports, skipped = [], []
    for m in range(cfg.pool_size):
        if m not in members:
            skipped.append({"member": m, "reason": "missing"})
            continue
        try:
            doc = read_metrics(paths, i, m)
            selection.score_of(cfg, doc)
        except ValueError as exc:
            skipped.append({"member": m, "reason": str(exc)})
            continue
        reports.append(doc)
    agents: dict[int, Agent] = {}
    while True:
        out, needs = selection.decide(cfg, i, previous, reports, skipped, reason)
        bad = None
        for m in needs:
            if m in agents:
                continue
            doc = next(d for d in reports if d["member"] == m)
            try:
                agents[m] = read_agent(paths, i, m, doc, like)
            except ValueError as exc:
                bad = (m, str(exc))
                break
        if bad is None:
            break
        reports = [d for d in reports if d["member"] != bad[0]]
        skipped.append({"member": bad[0], "reason": bad[1]})
    if out["winner"] == "merge":
        spec = out["merge"]
        parent = load_selected_agent(paths, i - 1, previous, like=like)
        merged = merge.merge_agents(parent, [agents[m] for m in spec["members"]], spec["weights"],
                                    spec["scale"], [agents[m] for m in spec["statistics_from"]])
        data = merged.to_bytes()
        digest = sha256(data)
        path = os.path.join(paths.iteration(i), layout.merged_name(digest))
        make_room(paths, path)
        fsutil.atomic_write(path, data)
        parse_agent(data, digest, path)  # every member trains from it next: parsed once
        out |= {"agent": paths.rel(path), "agent_sha256": digest}
    return out


def publish_selection(paths: Paths, selection: dict, by: int) -> tuple[dict, bool]:
    """Create ``selected.json`` unless it exists; return what is on disk and whether we wrote it."""
    i = selection["iteration"]
    doc = paths.sign(selection | {"selected_by": by, "time": time.time()})
    try:
        # Decisions that are not a key holder's (forged, unsigned, garbage) are passed over by
        # create_once: a stranger can delay a decision (denial of service), never make it.
        data, created = claim.create_once(paths.selected(i), fsutil.dumps(doc), root=paths.root,
                                          cap=fsutil.JSON_MAX_BYTES, accept=paths.signed)
    except claim.ClaimError as exc:
        raise RuntimeError(str(exc)) from None
    if created:
        return doc, True
    # Someone else decided first: adopt their decision, never our own.
    on_disk = json.loads(data.decode("utf-8"))
    if not isinstance(on_disk, dict) or on_disk.get("iteration") != i:
        raise RuntimeError(f"{paths.selected(i)} is decided but is not a selection of iteration {i}")
    return on_disk, False


def update_best(paths: Paths, selection: dict | None) -> bool:
    """Replace ``best.npz`` if this selection beats the best so far.

    Idempotent, so every member calls it after every barrier: a member killed
    right after writing ``selected.json`` cannot make the pool lose its best.
    """
    if selection is not None and isinstance(selection.get("evaluated"), dict):
        # a merge is scored in the next iteration; the best agent its iteration evaluated counts now
        selection = selection | selection["evaluated"]
    ret = None if selection is None else selection.get("eval_return")
    if ret is None:
        return False
    try:
        best = paths.read_json(paths.best_json)
    except (OSError, ValueError):
        best = None
    if paths.why_unsigned(best):
        best = None  # not a key holder's: replace it
    # Ties keep the earlier iteration, as status's best does.
    if isinstance(best, dict) and isinstance(best.get("eval_return"), (int, float)) and \
            (best["eval_return"], -best.get("iteration", 0)) >= (ret, -selection["iteration"]):
        return False
    data = paths.read_bytes(paths.resolve(selection["agent"]))
    make_room(paths, paths.best_npz, paths.best_json)
    fsutil.atomic_write(paths.best_npz, data)
    fsutil.write_json(paths.best_json, paths.sign({
        "iteration": selection["iteration"], "member": selection["member"], "winner": selection.get("winner"),
        "eval_return": ret, "agent": selection["agent"], "agent_sha256": sha256(data)}))
    return True


def make_room(paths: Paths, *targets: str) -> None:
    """Before replacing pool files such as ``best.npz``: a rename replaces a FIFO, a link or a
    file, not a directory, so a directory at a target's name (never a member's) is set aside."""
    for target in targets:
        try:
            st = os.lstat(target)
        except OSError:
            continue
        if stat.S_ISDIR(st.st_mode):
            log.warning("removing the directory at %s", target)
            fsutil.set_aside(target, (st.st_dev, st.st_ino), root=paths.root)


def _remove_matching(d: str, doomed) -> int:
    removed = 0
    for name in fsutil.listdir(d):
        if doomed(name):
            # a file, or a proposal directory of a killed member (rl_pool.claim)
            claim.remove_proposal(os.path.join(d, name))
            removed += 1
    return removed


def collect_garbage(paths: Paths, i: int) -> int:
    """Remove non-selected agents and temp leftovers of iteration ``i``; keep every JSON."""
    sel = read_selected(paths, i)
    if sel is None:
        return 0
    # the selected agent, and after a merge the best evaluated one (the fallback, perhaps the best)
    keep = {os.path.basename(str(d.get("agent") or "")) for d in (sel, sel.get("evaluated") or {})}
    removed = _remove_matching(paths.iteration(i), lambda name: (
        name.endswith(".npz") and name.startswith(("member-", layout.MERGED_PREFIX)) and name not in keep))
    return removed + remove_dead_temps(paths.iteration(i))


def publish_missing_selections(paths: Paths, iterations) -> None:
    """Write the plain ``selected.json`` of decided ``iterations`` that lack it: its writer stopped,
    or found the disk full, between deciding and publishing, and members (which decide from the
    decision, not the copy) would never write it again; people and tools read the copy."""
    for k in iterations:
        try:
            claim.publish_missing(paths.selected(k), root=paths.root, cap=fsutil.JSON_MAX_BYTES,
                                  accept=paths.signed)
        except (OSError, ValueError) as exc:
            log.warning("cannot check the decision of iteration %d: %s", k, _why(exc))


def remove_dead_temps(*dirs: str) -> int:
    """Temp files in ``dirs`` whose writer (named in the temp file's name) is a dead process on this host.

    Temp files are never read, so leftovers of a killed writer are only clutter;
    a live writer's temp file, or one from another host, is left alone.
    """
    def dead(name: str) -> bool:
        owner = fsutil.tmp_owner(name)
        return owner is not None and owner[0] == HOST.split(".")[0] and not pid_alive(owner[1])

    return sum(_remove_matching(d, dead) for d in dirs)
