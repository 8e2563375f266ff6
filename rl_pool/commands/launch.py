"""``rl-pool launch``: N members as local processes, live progress, Ctrl-C forwarded.

Each member is a fresh interpreter (``python -m rl_pool train``), never a fork
of the launcher: JAX and the BLAS libraries start threads that a fork would
copy in a locked state. Children get the one-thread caps in their environment
and their own session, so the launcher alone decides when they get a signal.
Progress (:mod:`rl_pool.commands.progress`) is a live panel on a terminal and plain
lines in a log.

``minutes`` is a wall-clock budget for the launch: when it runs out the members are stopped as
Ctrl-C stops them (their deposits stay; a later launch resumes). ``pick`` ends the run with
``rl-pool pick`` (:mod:`rl_pool.commands.pick`) on the pool's agents, into ``POOL/picked.npz``;
with a budget as well, the members stop early enough for the pick to fit in it, by an estimate
from the pool's own pace (env steps per second) of what the pick's episodes cost.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time

from rl_pool import fsutil
from rl_pool.commands import pick as picking
from rl_pool.commands import progress, status
from rl_pool.config import MemberConfig
from rl_pool.errors import SignalLatch, UsageError, drop_output
from rl_pool.protocol import heartbeat, layout, pool
from rl_pool.threads import capped_environ

DEFAULT_RATIO = 0.1  # the first member's learning rate relative to the others'


def default_learning_rates(pool_size: int, base: float) -> list[float]:
    """The first member at ``base / 10`` (a guard against steps that are too large), the rest at ``base``."""
    if pool_size == 1:
        return [base]
    return [base * DEFAULT_RATIO] + [base] * (pool_size - 1)


#: How many of the last decided iterations a resume looks through for a member's deposit.
RESUME_LOOKBACK = 20


def resumed_learning_rates(paths: layout.Paths, pool_size: int) -> list[float] | None:
    """The learning rate each member trained at in the pool's last decided iterations (its latest
    signed deposit among them), or None when the pool has not run yet or a member has no such
    deposit. A launch that resumes a pool without rates goes on with these instead of the
    default pair, so a pool started with a preset's rates (or ones given then) keeps them."""
    from rl_pool.protocol import deposits

    last = deposits.last_selected(paths)
    rates: dict[int, float] = {}
    for i in range(last, max(last - RESUME_LOOKBACK, 0), -1):
        # one listing per iteration: only deposits that are there are read (no waits for absent ones)
        for m in deposits.present(paths, i, pool_size) - rates.keys():
            try:
                lr = deposits.read_metrics(paths, i, m).get("learning_rate")
            except ValueError:
                continue
            if isinstance(lr, (int, float)) and not isinstance(lr, bool) and lr > 0:
                rates[m] = float(lr)
        if len(rates) == pool_size:
            return [rates[m] for m in range(pool_size)]
    return None


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _args(opts: dict) -> list[str]:
    out = []
    for k, v in opts.items():
        out += [_flag(k), json.dumps(v) if isinstance(v, dict) else str(v)]
    return out


def launch(pool_dir: str, requested: dict, member_opts: dict, learning_rates: list[float] | None,
           base_lr: float | None, quiet: bool = False, interval: float = 10.0, minutes: float | None = None,
           pick: bool = False, pick_finalists: int = 0,
           pick_final_episodes: int = picking.DEFAULT_FINAL_EPISODES) -> int:
    """Start the members, show progress until they exit; 0, 1 if a member failed (or the pick found
    no agent), 130 if stopped (Ctrl-C, a signal; also during the pick).

    ``interval``: seconds between plain progress lines when stdout is not a terminal.
    ``minutes``: stop the members after this much wall-clock time (not a failure); ``pick``: then,
    or when they are done, pick the pool's agent on held-out episodes (within ``minutes``), with a
    final round for its ``pick_finalists`` best candidates on ``pick_final_episodes`` more.
    """
    from rl_pool.commands.member import check_arguments, make_initial

    if pick_finalists < 0 or not 1 <= pick_final_episodes <= picking.MAX_EPISODES - picking.DEFAULT_EPISODES:
        raise UsageError(f"--pick-finalists must be >= 0 and --pick-final-episodes 1 to "
                         f"{picking.MAX_EPISODES - picking.DEFAULT_EPISODES}")
    paths = layout.Paths(pool_dir)
    n = check_arguments(paths, requested, []).pool_size
    base = base_lr if base_lr is not None else MemberConfig.learning_rate
    lrs = learning_rates if learning_rates is not None else default_learning_rates(n, base)
    if len(lrs) != n:
        raise UsageError(f"--learning-rates has {len(lrs)} values for a pool of {n}")
    for m, lr in enumerate(lrs):
        MemberConfig(**(member_opts | {"member": m, "learning_rate": lr})).validate(n)
    cfg = pool.open_pool(paths, requested, make_initial, key_file=member_opts.get("key_file") or None)  # refuses a mismatched pool before any spawn
    # a resumed pool goes on at the rates it ran with (a preset's, or ones given then); each was
    # validated by the member that signed the deposit it comes from
    ran = resumed_learning_rates(paths, n) if learning_rates is None and base_lr is None else None
    lrs = ran or lrs

    procs = []
    started = time.time()
    budget = pick_budget(paths, minutes, pick, pick_finalists, pick_final_episodes)
    target = member_opts.get("iterations", MemberConfig.iterations)
    env = capped_environ()
    interrupted = False
    # Members run in their own sessions, so the launcher must pass on every way it can be told
    # to stop (Ctrl-C, kill, a closed terminal): otherwise they would train on unattended. The
    # latch stays until the pick is done, so a stop during the summary or the pick is one too.
    old = _interrupt.install((signal.SIGINT, signal.SIGTERM, signal.SIGHUP))
    try:
        try:
            for m, lr in enumerate(lrs):
                cmd = [sys.executable, "-m", "rl_pool", "train", "--pool-dir", paths.root, "--member", str(m),
                       "--learning-rate", repr(lr), "--quiet", *_args(requested | {"pool_size": n}),
                       *_args(member_opts)]
                with fsutil.open_append(os.path.join(paths.logs, layout.member_name(m) + ".out"),
                                        root=paths.root) as out:
                    procs.append(subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT,
                                                  stdin=subprocess.DEVNULL, env=env, start_new_session=True))
            _say(f"launched {n} members on {cfg.env} in {paths.root}; learning rates "
                 + ", ".join(f"m{m}={lr:g}" for m, lr in enumerate(lrs))
                 + (" (as the pool ran; give --learning-rates for others)" if ran is not None else ""))
            codes = _watch(paths, procs, quiet, interval, started, target, budget)
        except KeyboardInterrupt:
            interrupted = True
            _say("\nstopping members (deposits on disk are safe; run again to resume)...", sys.stderr)
            codes = _stop_all(procs, signal.SIGTERM)
        st = status.status(paths.root)
        b = st["best"]
        _say(f"iterations completed {st['iterations_completed']} in {progress.clock(time.time() - started)}"
             + (f" (stopped at the budget of {minutes:g} minutes)" if budget.stopped else "") + "; best "
             + ("none" if b is None else f"{b['eval_return']:.2f} (iteration {b['iteration']}, {status.describe(b)})"))
        if interrupted:
            return 130
        failed = [(m, c) for m, c in enumerate(codes) if c != 0 and not (budget.stopped and c in STOPPED)]
        for m, c in failed:
            _say(f"member {m} failed (exit {c}): {_why(paths, m)}", sys.stderr)
        if failed:
            return 1
        if not pick:
            return 0
        _interrupt.check()  # a stop that a finaliser swallowed while the members were stopping
        return _pick(paths, n, pick_finalists, pick_final_episodes)
    except KeyboardInterrupt:
        _say("stopped; the pool is intact" + (" (rl-pool pick POOL picks its agent)" if pick else ""), sys.stderr)
        return 130
    finally:
        _interrupt.restore(old)


#: Exit codes of a member that the launcher stopped at the budget: its own clean stop on SIGTERM
#: (128 + 15), the signal itself (before the member's handler was in place), or the KILL after
#: the grace (its files are whole either way).
STOPPED = (128 + signal.SIGTERM, -signal.SIGTERM, -signal.SIGKILL)


def _pick(paths: layout.Paths, n: int, finalists: int, final_episodes: int) -> int:
    """The run's last step: ``rl-pool pick`` with its defaults but the final round's, on as many
    workers as members (or cores)."""
    try:
        res = picking.pick(paths.root, workers=max(1, min(n, os.cpu_count() or 1)), finalists=finalists,
                           final_episodes=final_episodes)
    except UsageError as exc:
        _say(f"no pick: {exc}", sys.stderr)
        return 1
    p = res["picked"]
    final = f", {res['finalists']} of them played on" if res["finalists"] else ""
    _say(f"picked the agent of iteration {p['iteration']} on {p['episodes']} held-out episodes: mean "
         f"{p['mean_return']:.2f} ± {p['std_return']:.2f} ({len(res['candidates'])} candidates{final}, "
         f"{res['seconds']:.0f} s), written to {res['out']}")
    return 0


#: Seconds a pick needs beyond its episodes (spawning its workers, loading the agents).
PICK_OVERHEAD = 10.0
#: Margin on the estimate of a pick's episodes: a pick must not run past the budget.
PICK_MARGIN = 1.5
#: The pace assumed before the pool has one (env steps per second): a slow pool's.
SLOW_PACE = 5000.0


class Budget:
    """When a launch with ``minutes`` stops its members: at the end of the budget, or, with a
    pick to come, early enough for it by the pool's pace. ``pick_steps``: the env steps of one
    candidate's held-out episodes at most (:func:`rl_pool.commands.pick.episode_steps`);
    ``finalists`` of the candidates then play ``final_steps`` more each (a final round)."""

    def __init__(self, minutes: float | None, pick_steps: float | None = None, now: float | None = None,
                 finalists: int = 0, final_steps: float = 0.0):
        start = time.monotonic() if now is None else now
        self.end = None if minutes is None else start + 60.0 * minutes
        self.pick_steps = pick_steps
        self.finalists = finalists
        self.final_steps = final_steps
        self.stopped = False

    def reserve(self, steps_per_second: float | None, iterations: int) -> float:
        """Seconds kept for the pick after ``iterations`` selections (one new agent each at most,
        so that many candidates and the initial agent, and as many finalists at most); before the
        pool has a pace, a slow one's."""
        if not self.pick_steps:
            return 0.0
        rate = steps_per_second if steps_per_second and math.isfinite(steps_per_second) else SLOW_PACE
        candidates = min(picking.DEFAULT_TOP, max(iterations, 0)) + 1
        steps = candidates * self.pick_steps + min(self.finalists, candidates) * self.final_steps
        return PICK_OVERHEAD + PICK_MARGIN * steps / max(rate, 1.0)

    def due(self, steps_per_second: float | None, iterations: int, now: float | None = None) -> bool:
        if self.end is None:
            return False
        now = time.monotonic() if now is None else now
        return now >= self.end - self.reserve(steps_per_second, iterations)


def pick_budget(paths: layout.Paths, minutes: float | None, pick: bool, finalists: int,
                final_episodes: int) -> Budget:
    """The launch's budget, keeping time for its pick (and the pick's final round) where it has one."""
    if not pick:
        return Budget(minutes)
    per_episode = picking.episode_steps(paths, 1)  # one read of the pool's initial agent
    return Budget(minutes, per_episode * picking.DEFAULT_EPISODES, finalists=finalists,
                  final_steps=per_episode * final_episodes)


#: Only the first signal stops the pool: a second Ctrl-C, or the same signal sent to the whole
#: process group as well (GNU timeout does that), must not cut the members' shutdown short and
#: leave them training unattended. One lost in a finaliser is raised again by the watch loop.
_interrupt = SignalLatch(lambda signum: KeyboardInterrupt())


def _say(line: str, stream=None) -> None:
    """Print a line if anyone can still read it. Output that closed (`launch | head`, a tee that
    died) is not a reason to stop: the launcher goes on watching its members, as the progress
    display does, and still exits with their status."""
    stream = stream or sys.stdout
    try:
        print(line, file=stream, flush=True)
    except BrokenPipeError:
        drop_output(stream)
    except ValueError:  # closed
        pass


def _watch(paths, procs, quiet, interval, started, target, budget: Budget) -> list[int]:
    """Wait for the members while showing progress; stop the others if one fails, and all of them
    when the budget is spent."""
    tracker = progress.Tracker(paths.root, since=started, target=target)
    display = contextlib.nullcontext() if quiet else progress.Display(sys.stdout, interval=interval)
    next_poll = 0.0
    pace, iterations = None, 0
    with display:
        while True:
            codes = [p.poll() for p in procs]
            done = all(c is not None for c in codes)
            failed = any(c not in (None, 0) for c in codes) and not done
            now = time.monotonic()
            if (not quiet or budget.pick_steps) and (now >= next_poll or done or failed):
                snap = tracker.poll()
                pace, iterations = snap.steps_per_second or pace, snap.iteration
                if not quiet:
                    display.update(snap)
                next_poll = now + 0.5
            if failed or done:
                break
            if budget.due(pace, iterations, now):
                budget.stopped = True
                return _stop_all(procs, signal.SIGTERM, keep=codes)
            _interrupt.check()
            time.sleep(0.1)
    if failed:
        bad = next(m for m, c in enumerate(codes) if c not in (None, 0))
        _say(f"member {bad} exited with {codes[bad]}: {_why(paths, bad)}; stopping the others", sys.stderr)
        return _stop_all(procs, signal.SIGTERM, keep=codes)
    return codes


def _stop_all(procs, sig, keep=None, grace: float = 30.0) -> list[int]:
    for p in procs:
        if p.poll() is None:
            try:
                p.send_signal(sig)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    codes = [p.returncode for p in procs]
    if keep is not None:  # a member that failed on its own keeps its own exit code
        codes = [c if k is None else k for k, c in zip(keep, codes, strict=True)]
    return codes


def _why(paths, m) -> str:
    hb = heartbeat.read_heartbeat(paths, m) or {}
    if hb.get("error"):
        return str(hb["error"])
    try:
        fd, st = fsutil.open_regular(os.path.join(paths.logs, layout.member_name(m) + ".out"), root=paths.root)
    except OSError:
        return "no output"
    with os.fdopen(fd, "rb") as fh:  # a regular file, opened without blocking or following links
        fh.seek(max(0, st.st_size - 2000))
        tail = fh.read(4000).decode(errors="replace").strip().splitlines()
    return tail[-1] if tail else "no output"
