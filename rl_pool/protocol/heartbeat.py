"""Heartbeats: each member's ``members/member-III.json``, rewritten while it runs, and how the
others judge from it whether a missing member is still coming (``docs/protocol.md``: "One
iteration", step 4)."""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from typing import TYPE_CHECKING

from rl_pool import fsutil

if TYPE_CHECKING:
    from rl_pool.protocol.layout import Paths

log = logging.getLogger("rl_pool")

TERMINAL_STATES = ("finished", "failed", "stopped")
HOST = socket.gethostname()


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def read_heartbeat(paths: Paths, m: int) -> dict | None:
    try:
        doc = paths.read_json(paths.heartbeat(m))
    except (OSError, ValueError):
        return None
    # A heartbeat decides who counts as alive at the barrier: only a key holder's counts.
    return doc if isinstance(doc, dict) and not paths.why_unsigned(doc) else None


class Heartbeat:
    """This member's heartbeat: rewritten on :meth:`set` and at least every ``interval`` seconds.

    ``beat`` increases on every write; observers judge liveness by whether the
    file changes, not by comparing clocks across hosts. :meth:`set` writes at
    once (a member starting an iteration); :meth:`set_soon` (a member starting to
    wait) leaves a change less than :attr:`MIN_GAP` seconds after the last write to
    the beat thread, which writes when the gap has passed, unless a write came
    first: a pool whose iterations take tens of milliseconds would otherwise
    replace every heartbeat file twice an iteration on the shared filesystem.
    """

    MIN_GAP = 0.2

    def __init__(self, paths: Paths, member: int, interval: float, extra: dict):
        self.paths, self.member, self.interval = paths, member, interval
        self.doc = {"member": member, "pid": os.getpid(), "host": HOST, "beat": 0,
                    "state": "starting", "iteration": None, **extra}
        self._cond = threading.Condition()  # guards doc, _last, _pending, _stopped
        self._io = threading.Lock()  # one write at a time, so the file never goes back to an older beat
        self._last = float("-inf")  # monotonic time of the last write
        self._pending = False
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)

    def start(self) -> Heartbeat:
        self.write()
        self._thread.start()
        return self

    def set(self, **fields) -> None:
        """Change fields and write them now."""
        self.update(**fields)
        self.write()

    def set_soon(self, **fields) -> None:
        """Change fields and write them now, or, within :attr:`MIN_GAP` of the last write, when the
        gap has passed (whatever the fields are then: a later ``set`` may have made this moot)."""
        with self._cond:
            self.doc.update(fields)
            if time.monotonic() - self._last < self.MIN_GAP:
                self._pending = True
                self._cond.notify()
                return
        self.write()

    def update(self, **fields) -> None:
        """Change fields for the next write (a state change, or the periodic beat), without writing."""
        with self._cond:
            self.doc.update(fields)

    def write(self) -> None:
        with self._io:
            with self._cond:
                self.doc["beat"] += 1
                self.doc["time"] = time.time()
                self._last, self._pending = time.monotonic(), False
                data = fsutil.dumps(self.paths.sign(fsutil.finite_or_null(self.doc)))
            try:
                fsutil.atomic_write(self.paths.heartbeat(self.member), data, durable=False)
            except OSError as exc:
                log.warning("heartbeat write failed: %s", exc)

    def _run(self) -> None:
        while True:
            with self._cond:
                if self._stopped:
                    return
                due = self._last + (self.MIN_GAP if self._pending else self.interval)
                left = due - time.monotonic()
                if left > 0:
                    self._cond.wait(left)
                    continue
            self.write()

    def stop(self, state: str, **fields) -> None:
        """Stop the beat thread and write the final state at once."""
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self.update(state=state, **fields)
        self.write()


class Liveness:
    """Judges other members' heartbeats from what this observer sees change.

    A member is *stale* if its heartbeat file has not changed for ``timeout``
    seconds of this observer's monotonic clock (a missing file counts as
    unchanged), if it says it has finished, failed or stopped, or if it runs
    on this host under a pid that no longer exists.
    """

    def __init__(self, paths: Paths, timeout: float):
        self.paths, self.timeout = paths, timeout
        self.seen: dict[int, tuple] = {}

    def stale(self, m: int) -> str | None:
        """Why member ``m`` is not coming to the barrier, or None if it may."""
        hb = read_heartbeat(self.paths, m)
        now = time.monotonic()
        key = None if hb is None else (hb.get("pid"), hb.get("host"), hb.get("beat"))
        prev = self.seen.get(m)
        if prev is None or prev[0] != key:
            self.seen[m] = (key, now)
            changed_at = now
        else:
            changed_at = prev[1]
        if hb is not None:
            if hb.get("state") in TERMINAL_STATES:
                return f"member {m} {hb.get('state')}"
            if hb.get("host") == HOST and isinstance(hb.get("pid"), int) and not pid_alive(hb["pid"]):
                return f"member {m} process {hb['pid']} is gone"
        if now - changed_at >= self.timeout:
            return f"member {m} heartbeat unchanged for {now - changed_at:.0f}s"
        return None


