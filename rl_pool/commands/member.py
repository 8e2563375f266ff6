"""One member's loop: take the selected agent, train, evaluate, deposit, wait, repeat.

Resume is the default: started on an existing pool, a member finds the last
selected iteration and rejoins there; if its own deposit of the current
iteration is already on disk it only waits. Because every random draw comes
from ``(seed, member, iteration)``, an iteration redone after a kill produces
the same deposit as the lost attempt would have.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import json
import logging
import os
import signal
import socket
import sys
import time
import traceback

from rl_pool import fsutil
from rl_pool.commands import status, tb
from rl_pool.config import MemberConfig, PoolConfig
from rl_pool.errors import SignalLatch, Stopped, UsageError
from rl_pool.learning import envs, trainer
from rl_pool.maths import learner, policy
from rl_pool.maths.agent import Agent, AgentMeta
from rl_pool.protocol import barrier, deposits, heartbeat, layout, pool, selection

log = logging.getLogger("rl_pool")

#: Exit codes of ``rl-pool train``; bad input (exit 2) is a UsageError for cli.main. EXIT_DISK: a
#: write failed for want of space or a writable disk (full, over quota, read-only, I/O error):
#: nothing half written is visible, and running the member again once that is fixed resumes.
EXIT_OK, EXIT_FAILED, EXIT_BARRIER, EXIT_DISK = 0, 1, 3, 4
DISK_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO})


#: SIGTERM/SIGINT/SIGHUP as Stopped. Ctrl-C reaches a member both from the terminal and from its
#: launcher: the first counts; a Stopped lost in a finaliser is raised again at the next check.
_stop = SignalLatch(Stopped)


def make_initial(cfg: PoolConfig):
    """``(initial agent, config with the episode length resolved)``; deterministic in ``cfg`` (with
    ``--init-agent``, in the file whose hash ``cfg`` records once the pool is made)."""
    kwargs = dict(cfg.env_kwargs)
    if cfg.max_episode_steps:
        kwargs["max_episode_steps"] = cfg.max_episode_steps
    env, info = envs.make(cfg.env, kwargs)
    env.close()
    if cfg.train_env_kwargs:  # the agent must fit both tasks: refuse here, before the pool is made
        env, train = envs.make(cfg.env, dict(kwargs, **cfg.train_env_kwargs))
        env.close()
        shape = lambda i: (i.obs_dim, i.act_dim, tuple(i.low), tuple(i.high), i.max_episode_steps)  # noqa: E731
        if shape(train) != shape(info):
            raise UsageError("--train-env-kwargs changes the observations, actions or episode length of "
                             f"{cfg.env}; training and evaluation must share them")
    cfg = dataclasses.replace(cfg, max_episode_steps=info.max_episode_steps)
    meta = AgentMeta(cfg.env, dict(cfg.env_kwargs), info.max_episode_steps, info.obs_dim, info.act_dim,
                     tuple(float(x) for x in info.low), tuple(float(x) for x in info.high), cfg.spec)
    if cfg.init_agent:
        agent, digest = _starting_agent(cfg.init_agent, meta, cfg.init_agent_sha256)
        return agent, dataclasses.replace(cfg, init_agent=os.path.abspath(cfg.init_agent), init_agent_sha256=digest)
    return Agent.initial(meta, seed=cfg.seed, shape=cfg.init_shape or None), cfg


def _starting_agent(target: str, meta: AgentMeta, expected_sha256: str) -> tuple[Agent, str]:
    """``--init-agent``: ``(the agent at target with fresh Adam moments, the sha256 of its file)``;
    refused unless it is an agent for the task and policy the pool is made for and, once the pool
    records one, the file whose hash it recorded (every member builds iteration 0 alike)."""
    from rl_pool.commands.evaluate import resolve_agent

    try:
        path, data = resolve_agent(target)
    except UsageError as exc:
        raise UsageError(f"--init-agent: {exc}") from None
    digest = layout.sha256(data)
    if expected_sha256 and digest != expected_sha256:
        raise UsageError(f"--init-agent {target} is not the agent this pool was made from (sha256 "
                         f"{digest[:12]}…, the pool recorded {expected_sha256[:12]}…): it changed since")
    agent = Agent.from_bytes(data, source=path)
    if agent.meta != meta:
        def says(m):
            return (f"{m.env} {json.dumps(m.env_kwargs, sort_keys=True)}, {m.max_episode_steps} steps, "
                    f"{m.obs_dim} observations, {m.act_dim} actions, {m.spec.describe()}")
        theirs, ours = says(agent.meta), says(meta)
        if theirs == ours:
            theirs += " (other action bounds)"
        raise UsageError(f"--init-agent {target} is an agent for {theirs}; this pool trains {ours}")
    fresh = learner.init_opt_state(agent.params)
    return agent.evolve(opt_m=fresh.m, opt_v=fresh.v, opt_t=fresh.t), digest


def check_arguments(paths: layout.Paths, requested: dict, members: list[MemberConfig]) -> PoolConfig:
    """Refuse bad arguments before anything is created or changed on disk; the merged pool config."""
    saved = pool.read_config(paths) if os.path.exists(paths.pool_json) else None
    cfg = PoolConfig.merged(requested, saved, where=f"pool {paths.root}")
    for mc in members:
        mc.validate(cfg.pool_size)
    return cfg


def _setup_logging(paths: layout.Paths, member: int, quiet: bool) -> None:
    fmt = logging.Formatter(f"%(asctime)s {layout.member_name(member)} %(levelname)s %(message)s")
    log.setLevel(logging.INFO)
    log.handlers.clear()
    log.propagate = False
    # never blocks on, nor writes through, a FIFO or link a stranger put at the log's name
    fh = logging.StreamHandler(io.TextIOWrapper(fsutil.open_append(paths.log(member), root=paths.root),
                                                encoding="utf-8", line_buffering=True))
    fh.setFormatter(fmt)
    log.addHandler(fh)
    if not quiet:
        sh = logging.StreamHandler(sys.stderr)
        sh.setFormatter(fmt)
        log.addHandler(sh)


def _check_not_running(paths: layout.Paths, member: int, stale_after: float) -> None:
    hb = heartbeat.read_heartbeat(paths, member)
    if not hb or hb.get("host") != heartbeat.HOST or hb.get("state") in heartbeat.TERMINAL_STATES:
        return
    pid = hb.get("pid")
    if not isinstance(pid, int) or pid == os.getpid() or not heartbeat.pid_alive(pid):
        return
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            cmd = fh.read().decode(errors="replace")
    except OSError:
        cmd = ""
    age = time.time() - os.path.getmtime(paths.heartbeat(member))
    if ("rl_pool" in cmd or "rl-pool" in cmd) and age < stale_after:
        raise UsageError(f"member {member} of {paths.root} is already running (pid {pid})")


def run(pool_dir: str, requested: dict, mc: MemberConfig, quiet: bool = False) -> int:
    """Run member ``mc.member`` until the pool's iteration ``mc.iterations`` is selected.

    Returns an ``EXIT_*`` code (signals: 128 + the signal); bad input raises UsageError.
    """
    # A log line that cannot be written (full disk) must not print a traceback: the member
    # says what went wrong itself, in one line (see _disk_error).
    logging.raiseExceptions = False
    paths = layout.Paths(pool_dir)
    me = mc.member
    try:
        check_arguments(paths, requested, [mc])
        cfg = pool.open_pool(paths, requested, make_initial, key_file=mc.key_file or None)
        _check_not_running(paths, me, mc.heartbeat_timeout)
        _setup_logging(paths, me, quiet)
    except OSError as exc:
        if exc.errno in DISK_ERRORS:
            return _disk_error(paths, me, None, exc, quiet)
        raise

    last = deposits.last_selected(paths)
    # A killed writer's temp files sit where the pool was when it died: near the last selection.
    pool.remove_dead_temps(paths.root, paths.members,
                           *(paths.iteration(k) for k in range(max(0, last - 2), last + 2)))
    pool.publish_missing_selections(paths, range(max(1, last - 2), last + 1))
    if last >= mc.iterations:
        log.info("pool already at iteration %d (target %d): nothing to do", last, mc.iterations)
        return EXIT_OK

    hb = heartbeat.Heartbeat(paths, me, interval=min(2.0, mc.heartbeat_timeout / 4),
                        extra={"learning_rate": mc.learning_rate, "target": mc.iterations})
    old = {}
    try:
        old = _stop.install((signal.SIGTERM, signal.SIGINT, signal.SIGHUP))
        hb.start()
        try:
            _loop(paths, cfg, mc, hb, last + 1)
        except Exception:
            # A stop can surface wrapped in a library's own error (jax turns one raised while it
            # compares a jitted call's static arguments into a ValueError): still a stop.
            _stop.check()
            raise
    except Stopped as exc:
        log.warning("stopped by %s; deposits on disk are whole, restart to resume", exc)
        hb.stop("stopped", error=f"stopped by {exc}")
        return 128 + exc.signum
    except barrier.BarrierTimeout as exc:
        log.error("%s", exc)
        hb.stop("failed", error=str(exc))
        return EXIT_BARRIER
    except UsageError as exc:
        hb.stop("failed", error=str(exc))
        raise
    except BaseException as exc:
        if isinstance(exc, OSError) and exc.errno in DISK_ERRORS:
            return _disk_error(paths, me, hb, exc, quiet)
        tb = traceback.format_exc()
        log.error("member failed:\n%s", tb)
        hb.stop("failed", error=f"{type(exc).__name__}: {exc}", traceback=tb[-4000:])
        if not quiet:
            sys.stderr.write(tb)
        return EXIT_FAILED
    finally:
        _stop.restore(old)
    hb.stop("finished")
    log.info("done: iteration %d selected", mc.iterations)
    return EXIT_OK


def disk_error_line(member: int, exc: OSError, root: str) -> str:
    """The one line a member stops with when it cannot write, e.g.
    ``member 1 stopped: No space left on device [ENOSPC] writing iterations/000003/member-001.npz;
    free space (or make the pool writable) and run it again to resume``."""
    where = exc.filename
    if isinstance(where, (str, bytes, os.PathLike)):
        where = os.fsdecode(where)
        rel = os.path.relpath(where, root)
        where = where if rel.startswith("..") else rel
    code = errno.errorcode.get(exc.errno, str(exc.errno))
    verb = "at" if exc.errno == errno.EIO else "writing"  # EIO may come from a read
    return (f"member {member} stopped: {exc.strerror or exc} [{code}]"
            + (f" {verb} {where}" if where else "")
            + "; free space (or make the pool writable) and run it again to resume")


def _disk_error(paths: layout.Paths, member: int, hb: heartbeat.Heartbeat | None, exc: OSError, quiet: bool) -> int:
    """Stop with one line on stderr, in the log and in the heartbeat (each only if it can still be
    written). Every file was written whole or not at all, so a restart resumes exactly."""
    line = disk_error_line(member, exc, paths.root)
    if log.handlers:  # none yet if the log could not be opened (and then not Python's last-resort one)
        log.error("%s", line)  # on stderr too, unless quiet
    if hb is not None:
        hb.stop("failed", error=line)  # a heartbeat that cannot be written is skipped
    if quiet or not any(type(h) is logging.StreamHandler for h in log.handlers):
        try:
            sys.stderr.write(f"rl-pool: {line}\n")
            sys.stderr.flush()
        except OSError:
            pass  # stderr on the same full disk
    return EXIT_DISK


def _loop(paths: layout.Paths, cfg: PoolConfig, mc: MemberConfig, hb: heartbeat.Heartbeat, first: int) -> None:
    me = mc.member
    from rl_pool.maths import learner

    learner.enable_compilation_cache()
    like = deposits.load_selected_agent(paths, 0)
    kwargs = dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps)
    # Training episodes may run a changed task (--train-env-kwargs) on envs of their own; evaluation
    # always runs the task itself. Without the option one set of envs serves both.
    apart = bool(cfg.train_env_kwargs)
    n_eval = cfg.eval_episodes if apart else max(cfg.batch_episodes, cfg.eval_episodes)
    env_list = [envs.make(cfg.env, kwargs)[0] for _ in range(n_eval)]
    train_envs = ([envs.make(cfg.env, dict(kwargs, **cfg.train_env_kwargs))[0] for _ in range(cfg.batch_episodes)]
                  if apart else env_list)
    liveness = heartbeat.Liveness(paths, mc.heartbeat_timeout)
    quorum = mc.quorum_for(cfg.pool_size)
    log.info("member %d of %d on %s, lr %g, from iteration %d to %d (quorum %d)",
             me, cfg.pool_size, cfg.env, mc.learning_rate, first, mc.iterations, quorum)

    prev = deposits.read_selected(paths, first - 1)
    pool.update_best(paths, prev)  # in case a kill skipped it
    lr = _learning_rate_for(paths, cfg, mc, first)
    board = tb.Board(paths, me, cfg.pool_size)  # TensorBoard: POOL/tb/member-III/ (member 0 also POOL/tb/pool/)
    board.catch_up(first - 1)
    try:
        i = first
        while i <= mc.iterations:
            _stop.check()
            if deposits.read_selected(paths, i) is not None:
                # Decided without us (we were stopped or slow): rejoin where the pool is now.
                i = max(deposits.last_selected(paths) + 1, i + 1)
                log.warning("pool went on without this member; rejoining at iteration %d", i)
                lr = _learning_rate_for(paths, cfg, mc, i)
                prev = deposits.read_selected(paths, i - 1)
                continue
            deposits.make_iteration_dir(paths, i)
            if os.path.lexists(paths.deposit_json(i, me)):
                log.info("iteration %d: own deposit already on disk; waiting for the others", i)
                mine = metrics = None
            else:
                selected = deposits.load_selected_agent(paths, i - 1, prev, like=like)
                sharpen = selection.sharpening(cfg, prev, me)
                start = selected if sharpen == 1.0 else selected.evolve(
                    params=policy.sharpened(selected.params, selected.spec, sharpen))
                hb.set(state="training", iteration=i)
                # --rate-patience and --rate-anneal: the pool's share of every rate
                scale = selection.rate_scale(prev) * selection.anneal_scale(cfg, i)
                tr = trainer.train(start, train_envs, cfg, lr * scale, me, i)
                hb.update(state="evaluating")  # shown by the next periodic beat: one write less per iteration
                ev = trainer.evaluate(tr.agent, env_list, cfg, i)
                parent = {}
                if selection.rescores_parent(cfg, prev) and selection.scores_parent(i, me, cfg.pool_size):
                    # The parent competes on the same episodes (or, with --best-score mean, a best
                    # is re-scored); several members score it (three in turn), so the selection
                    # does not depend on any one member's deposit being there.
                    pe = trainer.evaluate(selected, env_list, cfg, i)
                    parent = {"parent_eval_return": pe.mean, "parent_eval_score": pe.score,
                              "parent_eval_returns": pe.returns, "parent_eval_lengths": pe.lengths,
                              "parent_sha256": prev["agent_sha256"],
                              "parent_eval_seconds": pe.seconds, "parent_eval_steps": pe.steps}
                    parent |= _score_fallback(paths, cfg, prev, like, env_list, i)
                metrics = ev.summary() | parent | {
                    "learning_rate": lr, **({"rate_scale": scale} if cfg.rate_patience or cfg.rate_anneal else {}),
                    **({"sharpen": sharpen} if cfg.sharpen != 1.0 or cfg.revert_sharpen != 1.0 else {}),
                    "train_steps": tr.steps, "train_seconds": tr.seconds,
                    "train_return_mean": sum(tr.episode_returns) / len(tr.episode_returns),
                    "eval_steps": ev.steps, "eval_seconds": ev.seconds,
                    "grad_norm": tr.grad_norms[-1],
                    "parent": {"iteration": i - 1, "member": prev.get("member")},
                    "host": socket.gethostname(), "pid": os.getpid(), "time": time.time(),
                }
                deposits.deposit(paths, i, me, tr.agent, metrics)
                mine = ev.mean
                hb.update(last_return=mine)
            hb.set_soon(state="waiting", iteration=i)  # a short wait is not worth a write
            res = barrier.barrier(paths, i, cfg, me, like, quorum, mc.barrier_timeout, liveness,
                               poll_max=mc.poll_max_for(cfg.pool_size), previous=prev, check=_stop.check)
            fsutil.write_json(paths.wait_json(i, me),
                                   {"iteration": i, "member": me, "wait_seconds": res.waited,
                                    "resumed_at": time.time()}, durable=False)
            sel = res.selection
            pool.update_best(paths, sel)  # every member: a kill of the selection's writer must not lose it
            if res.created and i - mc.keep_iterations >= 1:
                pool.collect_garbage(paths, i - mc.keep_iterations)
            log.info("iteration %d: selected %s (eval return %s); mine %s; waited %.3fs",
                     i, status.describe(sel, origin=False), status.fixed(sel.get("eval_return")), status.fixed(mine), res.waited)
            board.record(i, sel, metrics, res.waited)
            lr = _next_learning_rate(paths, cfg, mc, sel, lr)
            # written with the next state change (training, a moment from now) or the final one
            hb.update(selected=sel.get("member"), selected_return=sel.get("eval_return"), learning_rate=lr)
            prev = sel
            i += 1
    finally:
        board.close()  # flushes what the last seconds recorded, on every way out


def _deposit_lr(paths: layout.Paths, i: int, m: int) -> float | None:
    try:
        lr = paths.read_json(paths.deposit_json(i, m)).get("learning_rate")
    except (OSError, ValueError, AttributeError):
        return None
    return float(lr) if isinstance(lr, (int, float)) and lr > 0 else None


def _next_learning_rate(paths: layout.Paths, cfg: PoolConfig, mc: MemberConfig, sel: dict | None,
                        own: float) -> float:
    """This member's rate after the selection ``sel`` of an iteration: a function of that iteration's files."""
    if not mc.lr_adapt or sel is None:
        return mc.learning_rate
    i, winner = sel["iteration"], sel.get("member")
    winner_lr = _deposit_lr(paths, i, winner) if isinstance(winner, int) else None
    return trainer.adapted_learning_rate(cfg.seed, mc.member, i, own, winner_lr, winner == mc.member,
                                         mc.lr_adapt)


def _learning_rate_for(paths: layout.Paths, cfg: PoolConfig, mc: MemberConfig, first: int) -> float:
    """On (re)start: the rate an uninterrupted run would use in iteration ``first``."""
    if not mc.lr_adapt or first <= 1:
        return mc.learning_rate
    own = _deposit_lr(paths, first - 1, mc.member) or mc.learning_rate
    return _next_learning_rate(paths, cfg, mc, deposits.read_selected(paths, first - 1), own)


def _score_fallback(paths: layout.Paths, cfg: PoolConfig, prev: dict, like: Agent, env_list, i: int) -> dict:
    """After a merge, the scorers of the parent also re-score the merge's fallback (the best agent
    the merge's iteration evaluated) on the same episodes, so selection can go back to it."""
    fb = prev.get("next_fallback")
    if not isinstance(fb, dict):
        return {}
    try:
        agent = deposits.load_named_agent(paths, fb, f"fallback of iteration {i - 1}", paths.selected(i - 1), like)
    except (RuntimeError, OSError, ValueError) as exc:
        log.warning("iteration %d: cannot re-score the fallback: %s", i, exc)
        return {}
    fe = trainer.evaluate(agent, env_list, cfg, i)
    return {"fallback_eval_return": fe.mean, "fallback_eval_score": fe.score,
            "fallback_sha256": fb["agent_sha256"], "fallback_eval_seconds": fe.seconds,
            "fallback_eval_steps": fe.steps}


