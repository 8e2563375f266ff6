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
:func:`rl_pool.protocol.claim.create_once`: the decision is ``.NAME.once/data`` (a
complete directory renamed into place: exclusive on local disks, NFS, Lustre,
GPFS and SeaweedFS alike, where ``link`` is not) and ``NAME`` its published
copy for people and tools. If two members ever disagree (one went on with a
quorum while a late deposit landed) the first decision stands and everyone
adopts it; members read decisions, never the copies.
"""

from __future__ import annotations

import json
import logging
import os
import stat
import time

from rl_pool import fsutil
from rl_pool.config import PROTOCOL, READABLE_PROTOCOLS, OldProtocol, PoolConfig
from rl_pool.errors import UsageError
from rl_pool.fsutil import why as _why
from rl_pool.maths import merge
from rl_pool.maths.agent import Agent, max_file_bytes
from rl_pool.protocol import claim, layout, selection
from rl_pool.protocol.deposits import (
    load_named_agent,
    load_selected_agent,
    parse_agent,
    read_agent,
    read_metrics,
    read_selected,
)
from rl_pool.protocol.heartbeat import HOST, pid_alive
from rl_pool.protocol.layout import Paths, sha256

log = logging.getLogger("rl_pool")


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
    from rl_pool.protocol import keys

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
    Creation is a create-once decision (:mod:`rl_pool.protocol.claim`), safe without
    working locks; the file lock (with a timeout) only keeps racing members on
    one host from building the environment twice. A new pool's directory is
    first checked with :func:`rl_pool.protocol.doctor.quick_check`.
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
    from rl_pool.protocol.doctor import quick_check

    problems = quick_check(paths.root)
    if problems:
        raise UsageError(f"{paths.root} cannot hold a pool: {problems[0]} (`rl-pool doctor {paths.root}` "
                         "says more)")
    for d in (paths.iterations, paths.members, paths.logs):
        os.makedirs(d, exist_ok=True)
    from rl_pool.protocol import keys

    pool_id = keys.new_pool_id()
    key, where = keys.create(pool_id, key_file)
    versions = {}
    try:
        from rl_pool.versions import versions as _versions

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


def select(paths: Paths, i: int, cfg: PoolConfig, like: Agent, members: set[int], reason: str,
           previous: dict) -> dict:
    """The selection of iteration ``i``: the deposits of ``members`` read and verified, the rule
    (:func:`rl_pool.protocol.selection.decide`) applied to them and ``previous`` (the selection of
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
        momentum = None
        if "momentum" in spec:
            momentum, why = _momentum_term(paths, i, spec["momentum"], like)
            if why is not None:
                spec["momentum"] = {"skipped": why}
        merged = merge.merge_agents(parent, [agents[m] for m in spec["members"]], spec["weights"],
                                    spec["scale"], [agents[m] for m in spec["statistics_from"]], momentum)
        data = merged.to_bytes()
        digest = sha256(data)
        path = os.path.join(paths.iteration(i), layout.merged_name(digest))
        make_room(paths, path)
        fsutil.atomic_write(path, data)
        parse_agent(data, digest, path)  # every member trains from it next: parsed once
        out |= {"agent": paths.rel(path), "agent_sha256": digest}
    return out


def _momentum_term(paths: Paths, i: int, term: dict, like: Agent):
    """``((beta, P'), None)`` for the momentum ``term`` of iteration ``i``'s merge, P' being the
    agent its ``from`` names (checked against its hash and, as deposits are, against this pool's
    env and policy: ``like``'s meta), or ``(None, why)``
    when that agent cannot be used: then the merge goes without the term and says why. The reason
    names files relative to the pool, so records read the same from any mount point. A member that
    still holds P' parsed (by its hash) does not read the file again; whichever member publishes
    the selection first decides for all."""
    try:
        before = load_named_agent(paths, term["from"], "the previous merge's parent", paths.selected(i - 1), like)
    except (OSError, RuntimeError, ValueError, UsageError) as exc:
        return None, str(exc).replace(paths.root + os.sep, "")
    if before.meta != like.meta:
        return None, "the previous merge's parent has other shapes than this pool's agents (another env or policy)"
    return (float(term["beta"]), before), None


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
    best = paths.read_object(paths.best_json, signed=True)  # not a key holder's: replace it
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
            # a file, or a proposal directory of a killed member (rl_pool.protocol.claim)
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
