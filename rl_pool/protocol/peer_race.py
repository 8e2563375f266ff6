"""Two clients race the filesystem's create-once primitives (``rl-pool doctor DIR --peer``).

Whether a primitive is exclusive *across* clients needs two of them: two runs of
``rl-pool doctor --peer`` (on two hosts, or two mounts of the same filesystem) against
the same directory find each other through files in ``DIR/.rl-pool-doctor/SESSION/``,
then race each primitive on the same names, round after round, and count the winners
each round had and whether both clients read the same winner (:mod:`.doctor` reports it).
"""

from __future__ import annotations

import errno
import math
import os
import time

from rl_pool import fsutil
from rl_pool.protocol import claim

#: The primitives raced, in order (also what ``rl-pool doctor`` describes).
PRIMITIVES = ("link", "excl", "mkdir", "rename-dir", "rename-take")

class PeerTimeout(Exception):
    pass


def _makedirs_shared(path: str, patience: float = 10.0) -> None:
    """``os.makedirs(path, exist_ok=True)`` for a path the peer may be creating at the same moment
    through another client: there a parent it just made can be missing for a moment (ENOENT), or
    exist without showing as a directory yet (EEXIST); both pass, so try again for a while."""
    deadline = time.monotonic() + patience
    while True:
        try:
            os.makedirs(path, exist_ok=True)
            return
        except (FileNotFoundError, FileExistsError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class _Session:
    """Two doctor runs meeting in ``DIR/.rl-pool-doctor/SESSION``."""

    def __init__(self, d: str, session: str, timeout: float):
        self.root = os.path.join(d, ".rl-pool-doctor", session)
        self.me = fsutil.writer_token(6)
        self.timeout = timeout
        self.peer: str | None = None
        _makedirs_shared(self.root)

    def put(self, name: str, obj) -> None:
        fsutil.atomic_write(os.path.join(self.root, name), fsutil.dumps(obj), sync_dir=False)

    def get(self, name: str):
        try:
            return fsutil.read_json(os.path.join(self.root, name))  # bounded, never blocks
        except (OSError, ValueError):
            return None

    def wait_for(self, name: str, what: str):
        deadline = time.monotonic() + self.timeout
        delay = 0.001
        while True:
            got = self.get(name)
            if got is not None:
                return got
            if time.monotonic() > deadline:
                raise PeerTimeout(f"no {what} from the peer after {self.timeout:.0f}s")
            time.sleep(delay)
            delay = min(2 * delay, 0.02)

    def meet(self) -> str:
        """Find the other run: both write ``ready-ME``, then ``go-ME`` naming every other ready run;
        the peer is a run whose go names us (a stale ready file from an old run never says go)."""
        self.put(f"ready-{self.me}", {"me": self.me})
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            others = sorted(n[6:] for n in os.listdir(self.root) if n.startswith("ready-") and
                            n != f"ready-{self.me}" and not fsutil.is_tmp(n))
            if others:
                self.put(f"go-{self.me}", {"peers": others})
                for o in others:
                    go = self.get(f"go-{o}")
                    if go and self.me in go.get("peers", []):
                        self.peer = o
                        return o
            time.sleep(0.01)
        raise PeerTimeout(f"no peer started `rl-pool doctor {os.path.dirname(os.path.dirname(self.root))} "
                          f"--peer` within {self.timeout:.0f}s")

    def barrier(self, step: str, payload: dict | None = None) -> dict:
        """Wait until the peer reached ``step`` too; returns what it passed there."""
        self.put(f"{step}-{self.me}", payload or {})
        return self.wait_for(f"{step}-{self.peer}", f"'{step}'")

    def start_together(self, step: str, lead: float = 1.0) -> None:
        """Meet at ``step``, then sleep until the later of the two start times proposed there.

        A barrier alone lets the runs go up to a poll interval (or, on a busy machine, a
        scheduling delay) apart, which can be longer than a whole race; clients whose clocks
        agree (one host, or NTP) start within a millisecond or so. A far-off peer clock is
        not waited for more than ``3 lead``. ``lead`` covers the time the later run's proposal
        takes to show on the other client (up to a second or so on NFS)."""
        mine = time.time() + lead
        got = self.barrier(step, {"start": mine})
        theirs = got.get("start") if isinstance(got, dict) else None
        at = max(mine, theirs) if isinstance(theirs, (int, float)) and math.isfinite(theirs) else mine
        time.sleep(min(max(0.0, at - time.time()), 3 * lead))


def _race_one(prim: str, race: str, me: str, k: int) -> bool:
    name = os.path.join(race, f"{prim}-{k:04d}")
    try:
        if prim == "link":
            os.link(os.path.join(race, f".src-{me}-{k:04d}"), name)
        elif prim == "excl":
            fd = os.open(name, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            os.write(fd, me.encode())
            os.close(fd)
        elif prim == "mkdir":
            os.mkdir(name)
        elif prim == "rename-dir":
            os.rename(os.path.join(race, f".prop-{me}-{k:04d}"), name)
        elif prim == "rename-take":
            os.rename(os.path.join(race, f"take-{k:04d}"), os.path.join(race, f"took-{me}-{k:04d}"))
        return True
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOENT, errno.EIO):
            return False  # lost (SeaweedFS answers a rename whose source is gone with EIO)
        raise


def _observe(prim: str, race: str, k: int, me: str, peer: str) -> str | None:
    """Whose win this client sees for round ``k`` (a run's token), or None."""
    name = os.path.join(race, f"{prim}-{k:04d}")
    try:
        if prim in ("link", "excl"):
            return fsutil.read_bytes(name, 256).decode(errors="replace") or None
        if prim == "mkdir":
            by = [n[3:] for n in os.listdir(name) if n.startswith("by-")]
            return by[0] if len(by) == 1 else ("+".join(sorted(by)) or None)
        if prim == "rename-dir":
            return fsutil.read_bytes(os.path.join(name, "data"), 256).decode(errors="replace")
        took = [t for t in (me, peer) if os.path.lexists(os.path.join(race, f"took-{t}-{k:04d}"))]
        return "+".join(took) or None
    except OSError:
        return None


def peer_race(d: str, rounds: int = 50, session: str = "default", timeout: float = 120.0,
              settle: float = 2.0) -> dict:
    """Race a peer run of the same function on another client; both return the same summary."""
    s = _Session(d, session, timeout)
    finished = False
    try:
        peer = s.meet()
        # A fresh directory per pair: names left by an earlier, interrupted session never count.
        race = os.path.join(s.root, "race-" + "-".join(sorted((s.me, peer))))
        _makedirs_shared(race)
        for k in range(rounds):  # each run's private sources, made before the race
            fsutil.atomic_write(os.path.join(race, f".src-{s.me}-{k:04d}"), s.me.encode(), sync_dir=False)
            prop = os.path.join(race, f".prop-{s.me}-{k:04d}")
            os.mkdir(prop)
            fsutil.atomic_write(os.path.join(prop, "data"), s.me.encode(), sync_dir=False)
            if s.me < peer:
                fsutil.atomic_write(os.path.join(race, f"take-{k:04d}"), b"", sync_dir=False)
        s.barrier("prepared")
        time.sleep(settle)  # the peer's files visible here before any race starts
        wins = {}
        for prim in PRIMITIVES:
            s.start_together(f"start-{prim}")
            wins[prim] = [k for k in range(rounds) if _race_one(prim, race, s.me, k)]
        for k in wins["mkdir"]:
            fsutil.atomic_write(os.path.join(race, f"mkdir-{k:04d}", f"by-{s.me}"), b"", sync_dir=False)
        s.barrier("raced")
        time.sleep(settle)  # let each client's view of the other's writes catch up
        sees = {p: [_observe(p, race, k, s.me, peer) for k in range(rounds)] for p in PRIMITIVES}
        s.put(f"result-{s.me}", {"wins": wins, "sees": sees})
        other = s.wait_for(f"result-{peer}", "result")
        s.put(f"done-{s.me}", {})
        finished = True
        deadline = time.monotonic() + settle  # give the peer's done- file time to show here
        while s.get(f"done-{peer}") is None and time.monotonic() < deadline:
            time.sleep(0.01)
        summary = _summarize(rounds, {s.me: {"wins": wins, "sees": sees}, peer: other})
        return summary | {"me": s.me, "peer": peer}
    finally:
        if finished and s.get(f"done-{s.peer}") is not None:
            claim.remove_tree(s.root)  # the peer is done with it too
            try:
                os.rmdir(os.path.dirname(s.root))  # .rl-pool-doctor, if no other session is there
            except OSError:
                pass
        elif not finished:
            for n in (f"ready-{s.me}", f"go-{s.me}"):
                claim.remove_proposal(os.path.join(s.root, n))
        # else: the peer still reads our result; it removes the session when it sees our done-


def _summarize(rounds: int, runs: dict) -> dict:
    a, b = sorted(runs)
    out = {"rounds": rounds, "primitives": {}}
    for prim in PRIMITIVES:
        wa, wb = set(runs[a]["wins"][prim]), set(runs[b]["wins"][prim])
        sa, sb = runs[a]["sees"][prim], runs[b]["sees"][prim]
        both = len(wa & wb)
        none = rounds - len(wa | wb)
        disagree = sum(1 for k in range(rounds) if sa[k] != sb[k])
        out["primitives"][prim] = {
            "both_won": both, "none_won": none, "exactly_one": rounds - both - none,
            "wins": {a: len(wa), b: len(wb)}, "clients_disagree": disagree,
            "exclusive": both == 0 and none == 0 and disagree == 0,
        }
    return out


# ---------------------------------------------------------------- the command
