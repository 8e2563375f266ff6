"""TensorBoard event files of a pool: ``tensorboard --logdir POOL/tb``.

Layout: one run directory per writer, so N members on a shared filesystem
never write the same file::

    POOL/tb/member-002/   written by member 2 only: its evaluation return, learning rate,
                          training steps per second, barrier wait, ...
    POOL/tb/pool/         written by member 0 only: the selected agent's return, the best so far

Every scalar's step is the iteration and its wall time the moment the
deposit (or selection) was made, so TensorBoard's STEP, RELATIVE and WALL
axes are all meaningful. ``return/eval`` is written by every run: in
TensorBoard's "return" section one chart overlays the selected agent (run
``pool``) and each member's branch.

Resume. The pool's JSON files, not the event files, are the record: a
restarted member opens a *new* event file (tensorboardX names each by time,
host and here the pid) and first rewrites, from the pool's files, every
iteration after the last one it knows to be flushed (``written.json`` in the
run directory, updated every :data:`MARK_EVERY` iterations and on close;
:meth:`Board.catch_up`). The new file starts with a ``SessionLog.START`` at
that first rewritten step (tensorboardX's ``purge_step``): TensorBoard reads
a run's event files in name order, and the START tells its reader to drop
every earlier event at or after that step; its data server likewise lets a
step written again replace the one before (it keeps one value per step and
"preempts" older records at or after a step seen again). So after any number
of kills and restarts each step shows once, with the values on disk. An event
file cut mid-record by a SIGKILL loses only that record: readers stop at a
torn record, and the file is never appended to again. Writing to the
dashboard can never stop a member: any error disables the board with one
warning.
"""

from __future__ import annotations

import logging
import math
import os
import time

from rl_pool import fsutil
from rl_pool.protocol import deposits, layout, selection

log = logging.getLogger("rl_pool")

#: Set to 0 to write no event files.
ENV_SWITCH = "RL_POOL_TENSORBOARD"
#: The member that writes the pool's run (the selection is a pure function of the pool's files,
#: so if member 0 is down for a while its restart fills in what it missed).
POOL_WRITER = 0
#: Iterations between updates of a run's ``written.json`` (how far a restart must rewrite, at most).
MARK_EVERY = 50
MARK = "written.json"
#: Seconds between flushes of the event files (each flush is an fsync).
FLUSH_EVERY = 2.0

MEMBER_TAGS = ("return/eval", "return/train_mean", "member/learning_rate", "member/train_steps_per_second",
               "member/train_seconds", "member/eval_seconds", "member/barrier_wait_seconds", "member/won")
POOL_TAGS = ("return/eval", "return/best", "pool/branch_won", "pool/deposits_considered")


def tb_dir(paths: layout.Paths) -> str:
    return os.path.join(paths.root, "tb")


def member_run(paths: layout.Paths, m: int) -> str:
    return os.path.join(tb_dir(paths), layout.member_name(m))


def pool_run(paths: layout.Paths) -> str:
    return os.path.join(tb_dir(paths), "pool")


def enabled() -> bool:
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "false", "no", "off")


def _num(x) -> float | None:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def member_scalars(metrics: dict, wait_seconds: float | None, won: bool | None) -> dict[str, float]:
    """The member run's scalars of one iteration, from its deposit metrics (``member-III.json``)."""
    steps, secs = _num(metrics.get("train_steps")), _num(metrics.get("train_seconds"))
    out = {
        "return/eval": _num(metrics.get("eval_return")),
        "return/train_mean": _num(metrics.get("train_return_mean")),
        "member/learning_rate": _num(metrics.get("learning_rate")),
        "member/train_steps_per_second": steps / secs if steps is not None and secs else None,
        "member/train_seconds": secs,
        "member/eval_seconds": _num(metrics.get("eval_seconds")),
        "member/barrier_wait_seconds": _num(wait_seconds),
        "member/won": None if won is None else float(won),
    }
    return {k: v for k, v in out.items() if v is not None}


def pool_scalars(sel: dict, best: float | None) -> dict[str, float]:
    """The pool run's scalars of one iteration, from its ``selected.json`` and the best so far."""
    considered = sel.get("considered")
    out = {
        "return/eval": _num(sel.get("eval_return")),
        "return/best": best,
        "pool/branch_won": float(sel.get("winner", "branch") == "branch"),
        "pool/deposits_considered": float(len(considered)) if isinstance(considered, list) else None,
        "pool/rate_scale": selection.recorded_rate_scale(sel),
    }
    return {k: v for k, v in out.items() if v is not None}


class Board:
    """One member's TensorBoard writer (and, for member 0, the pool's).

    Call :meth:`catch_up` once on start, :meth:`record` once per iteration
    after the barrier, :meth:`close` at the end. Records are flushed (with
    fsync) at most every :data:`FLUSH_EVERY` seconds and on close: a dashboard
    a few seconds behind costs nothing, an fsync per iteration costs a pool
    of short iterations much of its time (docs/cluster.md).
    """

    def __init__(self, paths: layout.Paths, member: int, pool_size: int, on: bool | None = None):
        self.paths, self.member, self.pool_size = paths, member, pool_size
        self.on = enabled() if on is None else on
        self.runs = [member_run(paths, member)] + ([pool_run(paths)] if member == POOL_WRITER else [])
        self.writers: dict[str, object] = {}
        self.best: float | None = None
        self.through = 0      # every iteration up to this one is flushed to this process's files
        self.written = 0      # ... written (perhaps not yet flushed)
        self.flushed_at = float("-inf")
        self.marked = 0       # ... and recorded in written.json
        self.pool_through = 0  # the pool run has every selection up to this one

    # ------------------------------------------------------------ files
    def _written(self, run: str) -> int:
        """The iteration through which ``run`` is known to be on disk (0: nothing, or no event file left)."""
        try:
            if not any(".tfevents." in n for n in os.listdir(run)):
                return 0
        except OSError:
            return 0
        doc = self.paths.read_object(os.path.join(run, MARK)) or {}
        k = doc.get("through")
        return k if isinstance(k, int) and not isinstance(k, bool) and k >= 0 else 0

    def _open(self, first: int) -> None:
        # tensorboardX's synchronous EventsWriter, not its SummaryWriter: that one queues events
        # for a thread, so its flush() can return before they are in the file, and written.json
        # would then claim steps a kill could still lose.
        from tensorboardX.event_file_writer import EventsWriter
        from tensorboardX.proto.event_pb2 import Event, SessionLog

        # a new file per process; name order (time, host, then this suffix) is write order
        suffix = f".{time.time_ns()}.{os.getpid()}"
        for d in self.runs:
            os.makedirs(d, exist_ok=True)
            w = EventsWriter(os.path.join(d, "events"), suffix)
            self.writers[d] = w
            # what tensorboardX's purge_step writes: a SessionLog.START at `first`, so TensorBoard drops
            # what earlier files of this run said about steps >= first (catch_up rewrites them)
            w.write_event(Event(step=first, wall_time=time.time(), session_log=SessionLog(status=SessionLog.START)))

    def _mark(self) -> None:
        for d in self.writers:
            fsutil.write_json(os.path.join(d, MARK), {"through": self.through}, durable=False)
        self.marked = self.through

    def _guard(self, fn, *args) -> None:
        """Run ``fn``; on any error, say so once and stop writing event files (training goes on)."""
        if not self.on:
            return
        try:
            fn(*args)
        except Exception as exc:
            log.warning("TensorBoard event files disabled: %s: %s", type(exc).__name__, exc)
            self.on = False
            self._close_quietly()

    def _write(self, run: str, step: int, scalars: dict[str, float], walltime: float | None) -> None:
        """One event: all of a step's scalars, stamped with ``walltime`` (default now)."""
        from tensorboardX.proto.event_pb2 import Event
        from tensorboardX.proto.summary_pb2 import Summary

        w = self.writers.get(run)
        if w is None or not scalars:
            return
        summary = Summary(value=[Summary.Value(tag=t, simple_value=v) for t, v in scalars.items()])
        w.write_event(Event(step=step, wall_time=time.time() if walltime is None else walltime, summary=summary))

    def _flush(self, through: int, force: bool = True) -> None:
        self.written = max(self.written, through)
        if not force and time.monotonic() - self.flushed_at < FLUSH_EVERY:
            return
        for w in self.writers.values():
            w.flush()  # file flush + fsync
        self.flushed_at = time.monotonic()
        self.through = max(self.through, self.written)
        if self.through - self.marked >= MARK_EVERY:
            self._mark()

    # ------------------------------------------------------------ API for the member loop
    def catch_up(self, upto: int) -> None:
        """Start writing: rewrite iterations after the last one known on disk, through ``upto``
        (the last selected iteration), from the pool's files."""
        self._guard(self._catch_up, upto)

    def _catch_up(self, upto: int) -> None:
        first = min([self._written(d) for d in self.runs] + [upto]) + 1
        self._open(first)
        self.through = self.written = self.marked = self.pool_through = first - 1
        if self.member == POOL_WRITER and first > 1:
            self.best = self._best_before(first)
        for i in range(first, upto + 1):
            sel = deposits.read_selected(self.paths, i)
            metrics = self._deposit(i)
            if metrics is not None:
                wait = (self.paths.read_object(self.paths.wait_json(i, self.member)) or {}).get("wait_seconds")
                won = None if sel is None else (sel.get("winner", "branch") == "branch"
                                                and sel.get("member") == self.member)
                self._write(self.runs[0], i, member_scalars(metrics, wait, won), _num(metrics.get("time")))
            if sel is not None:
                self._pool(sel)
        self._flush(upto)
        self._mark()

    def _best_before(self, first: int) -> float | None:
        """The best selected return before iteration ``first`` (selected.json carries it; best.json
        for pools whose selections do not)."""
        prev = deposits.read_selected(self.paths, first - 1) or {}
        if isinstance(prev.get("best"), dict):
            return _num(prev["best"].get("eval_return"))
        b = self.paths.read_object(self.paths.best_json, signed=True) or {}
        it = b.get("iteration")
        return _num(b.get("eval_return")) if isinstance(it, int) and it < first else None

    def _deposit(self, i: int) -> dict | None:
        """This member's metrics of iteration ``i`` from its deposit (a key holder's only)."""
        doc = self.paths.read_object(self.paths.deposit_json(i, self.member), signed=True)
        return doc if doc is not None and doc.get("iteration") == i and doc.get("member") == self.member else None

    def record(self, i: int, sel: dict, metrics: dict | None, wait_seconds: float | None) -> None:
        """Iteration ``i`` after its barrier: ``sel`` its selection, ``metrics`` this member's deposit
        metrics (None: read them from the deposit, e.g. when it was made before a restart)."""
        self._guard(self._record, i, sel, metrics, wait_seconds)

    def _record(self, i: int, sel: dict, metrics: dict | None, wait_seconds: float | None) -> None:
        if not self.writers:
            self._catch_up(i - 1)
        if metrics is None:
            metrics = self._deposit(i)
        if metrics is not None:
            won = sel.get("winner", "branch") == "branch" and sel.get("member") == self.member
            self._write(self.runs[0], i, member_scalars(metrics, wait_seconds, won), _num(metrics.get("time")))
        self._pool(sel)
        self._flush(i, force=False)

    def _pool(self, sel: dict) -> None:
        """The pool run through ``sel``'s iteration, including selections this member skipped (it fell
        behind and rejoined later)."""
        if pool_run(self.paths) not in self.writers:
            return
        i = int(sel["iteration"])
        for j in range(self.pool_through + 1, i):
            missed = deposits.read_selected(self.paths, j)
            if missed is not None:
                self._pool_one(missed)
        self._pool_one(sel)
        self.pool_through = max(self.pool_through, i)

    def _pool_one(self, sel: dict) -> None:
        run = pool_run(self.paths)
        ret = _num(sel.get("eval_return"))
        if ret is not None and (self.best is None or ret > self.best):
            self.best = ret
        self._write(run, int(sel["iteration"]), pool_scalars(sel, self.best), _num(sel.get("time")))

    def close(self) -> None:
        """Flush, record how far the files go, close (idempotent)."""
        if self.on and self.writers:
            self._guard(self._flush_and_mark)
        self._close_quietly()

    def _flush_and_mark(self) -> None:
        self._flush(self.written)
        self._mark()

    def _close_quietly(self) -> None:
        for w in self.writers.values():
            try:
                w.close()
            except Exception:
                pass
        self.writers = {}

    def __enter__(self) -> Board:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


