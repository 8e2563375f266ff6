"""Live progress of a pool: what ``rl-pool launch``, ``rl-pool status --watch`` and ``shell/pool.sh`` show.

A :class:`Tracker` reads the pool directory incrementally (each selection and
its deposits once, the heartbeats on every poll) into a :class:`Snapshot`:
iteration and target, selected and best return, each member's state and last
return, env steps per second, elapsed and estimated time left. A
:class:`Display` shows snapshots as a live panel redrawn in place on a
terminal (rich), or as plain lines at most every ``interval`` seconds when
stdout is a pipe or a file (logs, SLURM output), so logs stay readable.
"""

from __future__ import annotations

import itertools
import os
import select
import statistics
import sys
import time
from dataclasses import dataclass, field

from rl_pool.commands import status
from rl_pool.errors import SignalLatch, UsageError, drop_output
from rl_pool.protocol import deposits, layout, pool

#: Heartbeat states of a member that is running.
ACTIVE = ("starting", "training", "evaluating", "waiting")
#: Selections over which rates (steps/s, seconds per iteration) are averaged.
WINDOW = 20
#: A gap between two selections longer than this many typical ones is downtime, not pace.
GAP_FACTOR = 5.0


@dataclass
class Snapshot:
    """The state of a pool at one moment, as a person watching it wants to see it."""

    pool_dir: str
    waiting: str | None = None          # why there is nothing to show yet (pool not created)
    env: str | None = None
    pool_size: int = 0
    iteration: int = 0                  # last selected iteration (0: none yet)
    target: int | None = None
    last: dict | None = None            # history row of the last selection
    best: dict | None = None            # {"iteration", "eval_return", "winner", "member", ...}
    members: list[dict] = field(default_factory=list)
    recent: list[dict] = field(default_factory=list)   # last few history rows, oldest first
    steps_per_second: float | None = None
    seconds_per_iteration: float | None = None
    elapsed: float = 0.0
    eta: float | None = None

    @property
    def done(self) -> bool:
        return self.target is not None and self.iteration >= self.target


class Tracker:
    """Follows one pool directory; :meth:`poll` returns a fresh :class:`Snapshot`.

    ``since`` is when the watching started (elapsed time counts from it);
    ``target`` the iteration the run aims at (default: the largest target in
    the members' heartbeats).
    """

    def __init__(self, pool_dir: str, since: float | None = None, target: int | None = None,
                 recent: int = 5):
        self.paths = layout.Paths(pool_dir)
        self.since = time.time() if since is None else since
        self.target = target
        self.keep = max(recent, 0)
        self.cfg = None
        self.created: float | None = None
        self.rows: dict[int, dict] = {}     # the last WINDOW + recent selections
        self.steps: dict[int, int] = {}
        self.best: dict | None = None
        self.seen = 0

    def _open(self) -> bool:
        if self.cfg is not None:
            return True
        if not os.path.exists(self.paths.pool_json):
            return False
        self.cfg = pool.read_config(self.paths, readonly=True)
        # with the pool's key (if this host has it) forged or unsigned files are left out, as in status
        pool.attach_key(self.paths, required=False)
        doc = self.paths.read_object(self.paths.pool_json) or {}
        self.created = status._num(doc.get("created"))
        return True

    def _read_new(self) -> None:
        if self.seen == 0:
            last = deposits.last_selected(self.paths)  # one listing on the first look
        else:
            # selections come in order, so probing the next ones is enough (no listing of a long pool)
            last = self.seen
            while deposits.read_selected(self.paths, last + 1) is not None:
                last += 1
        if last <= self.seen:
            return
        start = max(self.seen + 1, last - WINDOW - self.keep, 1)
        if start > self.seen + 1 and self.seen == 0:
            # first look at a long-running pool: the best so far is in best.json
            b = self.paths.read_object(self.paths.best_json)
            if b and status._num(b.get("eval_return")) is not None:
                self.best = {"iteration": b.get("iteration"), "member": b.get("member"),
                             "eval_return": float(b["eval_return"]),
                             "winner": "branch" if isinstance(b.get("member"), int) else "parent"}
        for i in range(start, last + 1):
            sel = deposits.read_selected(self.paths, i)
            if sel is None:
                continue
            row = status.history_row(self.paths, sel, self.cfg.pool_size)
            self.rows[i] = row
            self.steps[i] = sum((x.get("train_steps") or 0) + (x.get("eval_steps") or 0)
                                + (x.get("parent_eval_steps") or 0)
                                + (x.get("fallback_eval_steps") or 0) for x in row["members"])
            ret = row["eval_return"]
            if ret is not None and (self.best is None or ret > self.best["eval_return"]):
                self.best = {"iteration": i, "member": row["selected_member"], "eval_return": ret,
                             "winner": row["winner"], "agent_from": row["agent_from"]}
        self.seen = last
        for i in [k for k in self.rows if k <= last - WINDOW - self.keep]:
            del self.rows[i]
            self.steps.pop(i, None)

    def _rates(self) -> tuple[float | None, float | None]:
        """(env steps per second, seconds per iteration) over the recent selections, downtime left out."""
        its = sorted(i for i in self.rows if self.rows[i]["time"] is not None)
        times = {i: self.rows[i]["time"] for i in its}
        if self.created is not None and 1 in times:
            its, times = [0, *its], {0: self.created, **times}
        gaps = [(b, times[b] - times[a]) for a, b in itertools.pairwise(its) if b == a + 1 and times[b] > times[a]]
        if not gaps:
            return None, None
        typical = statistics.median(g for _, g in gaps)
        gaps = [(b, g) for b, g in gaps if g <= max(GAP_FACTOR * typical, 1.0)]
        seconds = sum(g for _, g in gaps)
        if seconds <= 0:
            return None, None
        return sum(self.steps.get(b, 0) for b, _ in gaps) / seconds, seconds / len(gaps)

    def poll(self) -> Snapshot:
        snap = Snapshot(pool_dir=self.paths.root, elapsed=max(0.0, time.time() - self.since),
                        target=self.target)
        if not self._open():
            snap.waiting = "waiting for the pool to be created"
            return snap
        self._read_new()
        snap.env, snap.pool_size = self.cfg.env, self.cfg.pool_size
        snap.iteration = max(self.seen, 0)
        snap.members = status.members(self.paths, self.cfg.pool_size)
        if snap.target is None:
            targets = [m.get("target") for m in snap.members]
            targets = [t for t in targets if isinstance(t, int) and not isinstance(t, bool)]
            snap.target = max(targets) if targets else None
        snap.last = self.rows.get(self.seen)
        snap.best = self.best
        snap.recent = [self.rows[i] for i in sorted(self.rows)[-self.keep:]] if self.keep else []
        snap.steps_per_second, snap.seconds_per_iteration = self._rates()
        # time left only while someone runs: the pace of a stopped pool says nothing about when it ends
        if snap.target is not None and snap.seconds_per_iteration \
                and any(m["state"] in ACTIVE for m in snap.members):
            snap.eta = max(0, snap.target - snap.iteration) * snap.seconds_per_iteration
        return snap


# ---------------------------------------------------------------- text
def clock(seconds: float | None) -> str:
    """``0:05:07``; ``-`` when unknown."""
    if seconds is None:
        return "-"
    s = round(seconds)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _headline(label: str, rec: dict | None, style: str, why):
    """A rich ``Text``: ``label``, then a return in ``style`` and ``(why(rec))``, or ``-``."""
    from rich.text import Text

    out = Text(label)
    if rec is None:
        out.append("-")
    else:
        out.append(status.fixed(rec["eval_return"]), style=style)
        out.append(f" ({why(rec)})")
    return out


def _rate(x) -> str:
    return "-" if x is None else f"{x:,.0f}"


def _member_states(snap: Snapshot, limit: int = 8) -> str:
    if len(snap.members) > limit:
        counts: dict[str, int] = {}
        for m in snap.members:
            counts[m["state"] or "-"] = counts.get(m["state"] or "-", 0) + 1
        return ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    return ", ".join(f"m{m['member']} {m['state'] or '-'} {status.fixed(m.get('last_return'))}" for m in snap.members)


def line(snap: Snapshot) -> str:
    """One plain progress line (logs, pipes, SLURM output)."""
    stamp = time.strftime("%H:%M:%S")
    if snap.waiting:
        return f"{stamp} {snap.pool_dir}: {snap.waiting}"
    target = f"/{snap.target}" if snap.target is not None else ""
    parts = [f"{stamp} iteration {snap.iteration}{target}"]
    if snap.last is not None:
        parts.append(f"selected {status.fixed(snap.last['eval_return'])} ({status.describe(snap.last, origin=False)})")
    if snap.best is not None:
        parts.append(f"best {status.fixed(snap.best['eval_return'])} (iteration {snap.best['iteration']})")
    parts.append(_member_states(snap))
    parts.append(f"{_rate(snap.steps_per_second)} steps/s")
    parts.append(f"elapsed {clock(snap.elapsed)}, left {'~' + clock(snap.eta) if snap.eta is not None else '-'}")
    return " | ".join(parts)


def panel(snap: Snapshot):
    """The live view: a rich renderable (header, progress bar, members, last iterations)."""
    from rich.console import Group
    from rich.progress_bar import ProgressBar
    from rich.table import Table
    from rich.text import Text

    if snap.waiting:
        return Text(f"{snap.pool_dir}: {snap.waiting}", style="dim")
    head = Text()
    head.append(f"{snap.env}", style="bold")
    head.append(f"  pool of {snap.pool_size}  {snap.pool_dir}", style="dim")
    grid = Table.grid(padding=(0, 2))
    grid.add_column()
    grid.add_column()
    it = Text(f"iteration {snap.iteration}" + (f" / {snap.target}" if snap.target is not None else ""),
              style="bold")
    bar = ProgressBar(total=float(snap.target or 1), completed=float(min(snap.iteration, snap.target or 0)),
                      width=30) if snap.target else Text("")
    grid.add_row(it, bar)
    pace = Text(f"elapsed {clock(snap.elapsed)}   left "
                + ("~" + clock(snap.eta) if snap.eta is not None else "-")
                + f"   {_rate(snap.steps_per_second)} env steps/s")
    sel = _headline("selected ", snap.last, "bold cyan", lambda r: status.describe(r))
    best = _headline("best     ", snap.best, "bold green",
                     lambda r: f"iteration {r['iteration']}, {status.describe(r)}")

    mt = Table(box=None, padding=(0, 2), header_style="bold dim")
    for col, just in (("member", "right"), ("state", "left"), ("iter", "right"), ("lr", "right"),
                      ("last return", "right"), ("heartbeat", "right")):
        mt.add_column(col, justify=just)
    style = {"training": "yellow", "evaluating": "magenta", "waiting": "blue", "finished": "green",
             "failed": "bold red", "dead": "bold red", "stopped": "red"}
    for m in snap.members:
        age = m.get("heartbeat_age")
        st = m["state"] or "-"
        mt.add_row(str(m["member"]), Text(st, style=style.get(st, "")), status.cell(m.get("iteration")),
                   status.general(m.get("learning_rate")), status.fixed(m.get("last_return")),
                   "-" if age is None else f"{age:.0f}s ago")
    parts = [head, grid, pace, sel, best, Text(""), mt]
    for m in snap.members:
        if m.get("error") and m["state"] in ("failed", "stopped", "dead"):
            parts.append(Text(f"member {m['member']}: {str(m['error'])[:300]}", style="red"))
    if snap.recent:
        ht = Table(box=None, padding=(0, 2), header_style="bold dim")
        ht.add_column("iter", justify="right")
        ht.add_column("winner")
        ht.add_column("return", justify="right")
        show = snap.pool_size <= 8
        if show:
            for m in range(snap.pool_size):
                ht.add_column(f"m{m}", justify="right")
        for r in snap.recent:
            by = {x["member"]: x for x in r["members"]}
            cells = [str(r["iteration"]), status.short_winner(r), status.fixed(r["eval_return"])]
            if show:
                cells += [status.fixed(by.get(m, {}).get("eval_return")) for m in range(snap.pool_size)]
            ht.add_row(*cells)
        parts += [Text(""), ht]
    return Group(*parts)


# ---------------------------------------------------------------- display
class Display:
    """Shows snapshots: redrawn in place on a terminal, plain lines otherwise.

    ``live=None`` decides from ``stream`` (a terminal that is not ``TERM=dumb``).
    Plain lines come at most every ``interval`` seconds and only when something
    changed (a selection, a member's state), plus one at the end.
    """

    def __init__(self, stream=None, interval: float = 10.0, live: bool | None = None):
        self.stream = stream or sys.stdout
        self.interval = interval
        self.console = None
        if live is None:
            live = _is_terminal(self.stream)
        self.live = None
        if live:
            from rich.console import Console
            from rich.live import Live

            self.console = Console(file=self.stream, force_terminal=True)
            self.live = Live(console=self.console, auto_refresh=False, transient=False,
                             redirect_stdout=False, redirect_stderr=False)
        self._last_key = None
        self._last_print = float("-inf")
        self._snap: Snapshot | None = None
        self._printed_snap: Snapshot | None = None
        #: True once nothing written can reach a reader (a pipe whose reader left).
        self.closed = False

    def __enter__(self) -> Display:
        if self.live is not None:
            self.live.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, snap: Snapshot, force: bool = False) -> None:
        """Show ``snap`` (plain mode: if something changed and ``interval`` has passed, or ``force``)."""
        self._snap = snap
        if self.live is not None:
            self.live.update(panel(snap), refresh=True)
            return
        key = _change_key(snap)
        now = time.monotonic()
        if key != self._last_key and (force or now - self._last_print >= self.interval):
            self._emit(snap)
            self._last_key, self._last_print = key, now

    def _emit(self, snap: Snapshot) -> None:
        try:
            self.stream.write(line(snap) + "\n")
            self.stream.flush()
        except BrokenPipeError:
            # The reader has gone (`... | head`). A launcher goes on watching its members; a
            # watcher (`status --watch`) stops.
            self.closed = True
            drop_output(self.stream)
        except ValueError:  # a closed stream
            self.closed = True
        self._printed_snap = snap

    def reader_gone(self) -> bool:
        """Whether nothing written can reach a reader any more: a write failed, or the stream is a
        pipe whose reader has closed it (seen without writing: poll's POLLERR)."""
        if not self.closed:
            try:
                poller = select.poll()
                poller.register(self.stream.fileno(), select.POLLOUT)
                self.closed = any(ev & select.POLLERR for _, ev in poller.poll(0))
            except (OSError, ValueError, AttributeError):
                pass  # no descriptor, or no poll on this platform: the next failed write tells
        return self.closed

    def close(self) -> None:
        if self.live is not None:
            if self._snap is not None:
                self.live.update(panel(self._snap), refresh=True)
            self.live.stop()
            self.live = None
            return
        if self._snap is not None and self._snap is not self._printed_snap \
                and _change_key(self._snap) != self._last_key:
            self._emit(self._snap)


def _change_key(snap: Snapshot):
    return (snap.waiting, snap.iteration, tuple((m["member"], m["state"]) for m in snap.members))


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty() and os.environ.get("TERM", "") not in ("dumb", "unknown")
    except (AttributeError, ValueError):
        return False


# ---------------------------------------------------------------- status --watch
def check_watchable(pool_dir: str) -> None:
    """Refuse what will never become a pool: no such directory, or one holding foreign files."""
    paths = layout.Paths(pool_dir)
    if not os.path.isdir(paths.root):
        raise UsageError(f"no pool directory at {paths.root}")
    if os.path.exists(paths.pool_json):
        pool.read_config(paths, readonly=True)
        return
    from rl_pool import fsutil

    foreign = [n for n in fsutil.listdir(paths.root)
               if n not in ("iterations", "members", "logs", "tb", ".init.lock") and not fsutil.is_tmp(n)]
    if foreign:
        raise UsageError(f"{paths.root} is not an rl-pool pool (no pool.json; found {foreign[0]!r})")


def watch(pool_dir: str, interval: float | None = None, recent: int = 5, stream=None,
          live: bool | None = None, refresh: float = 0.5) -> int:
    """``rl-pool status DIR --watch``: follow the pool until interrupted (Ctrl-C or SIGTERM: exit 0).

    On a terminal the view is redrawn every ``interval`` seconds (default
    ``refresh``); otherwise a plain line is printed at most every ``interval``
    seconds (default 10) when something changed.
    """
    import signal

    check_watchable(pool_dir)
    stream = stream or sys.stdout
    is_live = _is_terminal(stream) if live is None else live
    period = (interval if interval is not None else refresh) if is_live else min(interval or 10.0, refresh)
    tracker = Tracker(pool_dir, recent=recent)

    stop = SignalLatch(lambda signum: KeyboardInterrupt())
    old = stop.install((signal.SIGTERM,))
    try:
        with Display(stream, interval=interval if interval is not None else 10.0, live=is_live) as d:
            try:
                while not d.reader_gone():  # a reader that left (`--watch | head`) ends the watch
                    d.update(tracker.poll())
                    stop.check()
                    time.sleep(period)
            except KeyboardInterrupt:
                try:  # show how it ended (members stopped or finished), not the state of the last poll
                    d.update(tracker.poll(), force=True)
                except (KeyboardInterrupt, UsageError):
                    pass
    finally:
        stop.restore(old)
    return 0
