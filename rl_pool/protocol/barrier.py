"""The barrier: wait for an iteration's deposits, then select, or adopt the selection already made
(``docs/protocol.md``: "One iteration", step 4)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from rl_pool.config import PoolConfig
from rl_pool.maths.agent import Agent
from rl_pool.protocol import pool
from rl_pool.protocol.deposits import present, read_selected
from rl_pool.protocol.heartbeat import Liveness
from rl_pool.protocol.layout import Paths
from rl_pool.protocol.pool import publish_selection

log = logging.getLogger("rl_pool")

class BarrierTimeout(Exception):
    pass


@dataclass
class BarrierResult:
    selection: dict
    created: bool
    waited: float


#: Listings of a waiting member's iteration directory: right after its deposit, then after gaps
#: doubling from LIST_FIRST to LIST_MAX seconds (docs/cluster.md: "Listings"). A timed listing
#: that shows every deposit waits LIST_GRACE more for the last depositor's decision before
#: selecting itself, times one plus the member's index (at most GRACE_STEPS times): staggered, so
#: that when selecting takes longer than the grace (N metrics files over a network filesystem),
#: member 0 selects for a silent last depositor and the others find its decision at their next
#: poll, instead of every waiting member selecting at once (harmless, but each reads N files).
LIST_FIRST, LIST_MAX, LIST_GRACE, GRACE_STEPS = 0.05, 1.0, 0.05, 100


def barrier(paths: Paths, i: int, cfg: PoolConfig, me: int, like: Agent, quorum: int,
            timeout: float, liveness: Liveness, poll_max: float = 0.01,
            check: Callable[[], None] | None = None, previous: dict | None = None) -> BarrierResult:
    """Wait for iteration ``i``'s deposits, then select (or adopt the selection already made).

    A waiting member polls one name, the iteration's decision (a lookup, not a
    listing; pauses back off from 1 ms to ``poll_max``), and lists the
    directory only right after its own deposit and then on a slow timer
    (:data:`LIST_FIRST` doubling to :data:`LIST_MAX` seconds). The member whose
    listing shows all ``pool_size`` deposits selects: normally the last
    depositor, alone; the timer covers a listing that lagged behind another
    host's deposit and a last depositor that stopped before deciding (then,
    after a grace staggered by member index, one waiting member decides for
    it). With at least ``quorum`` deposits listed, a member also
    goes on when every missing member is stale or ``timeout`` seconds have
    passed (checked at listing times). Without a quorum after ``timeout`` it
    raises :class:`BarrierTimeout`. Two members selecting at once is harmless:
    selection is a pure function of the files and the decision is create-once.
    ``previous``: the selection of ``i - 1`` if the caller has it (else it is read). ``check``:
    called between polls; it may raise to stop the wait (a stop signal).
    """
    t0 = time.monotonic()
    delay = 0.001
    next_list, list_gap = t0, LIST_FIRST
    have: set[int] = set()
    reason, listed, all_seen = None, False, False
    with paths.holding(paths.iteration(i)):
        while True:
            sel = read_selected(paths, i)
            if sel is not None:
                return BarrierResult(sel, False, time.monotonic() - t0)
            now = time.monotonic()
            if now >= next_list:
                next_list, list_gap = now + list_gap, min(2 * list_gap, LIST_MAX)
                have = present(paths, i, cfg.pool_size)
                if len(have) == cfg.pool_size:
                    if not listed or all_seen:  # right after our deposit, or still undecided after the grace
                        reason = "complete"
                        break
                    all_seen, next_list = True, now + LIST_GRACE * min(1 + me, GRACE_STEPS)
                    continue
                listed = True
                missing = sorted(set(range(cfg.pool_size)) - have)
                if len(have) >= quorum:
                    why = [liveness.stale(m) for m in missing]
                    if all(why):
                        # List again: a member may have deposited and then stopped since the last listing.
                        have = present(paths, i, cfg.pool_size)
                        reason = "went on without stale members: " + "; ".join(
                            w for m, w in zip(missing, why, strict=True) if m not in have)
                        if len(have) == cfg.pool_size:
                            reason = "complete"
                        break
                if now - t0 >= timeout:
                    if len(have) >= quorum:
                        reason = f"barrier timeout after {timeout:.0f}s; missing {missing}"
                        break
                    raise BarrierTimeout(
                        f"iteration {i}: only {len(have)} of {cfg.pool_size} deposits after {timeout:.0f}s "
                        f"(quorum {quorum}); restart to resume")
            if check is not None:
                check()
            time.sleep(max(0.0, min(delay, next_list - time.monotonic())))
            delay = min(delay * 2, poll_max)
        if reason != "complete":
            log.warning("iteration %d: %s", i, reason)
        previous = previous or read_selected(paths, i - 1)
        if previous is None:
            raise RuntimeError(f"iteration {i - 1} has no readable selection")
        selection = pool.select(paths, i, cfg, like, have, reason, previous)
        for s in selection["skipped"]:
            if s["reason"] != "missing":
                log.warning("iteration %d: skipped member %d: %s", i, s["member"], s["reason"])
        doc, created = publish_selection(paths, selection, me)
    return BarrierResult(doc, created, time.monotonic() - t0)
