"""Stop signals that Python loses in a finaliser are raised again (errors.SignalLatch)."""
import signal
import sys
import threading
import time

import pytest

from rl_pool.errors import SignalLatch, Stopped
from rl_pool.protocol import barrier, heartbeat

from .helpers import deposit, like_agent, make_pool


def _lose_a_signal_in_a_finaliser() -> None:
    """SIGTERM arrives while an abandoned generator is closed: the handler runs inside that
    close, where Python only reports the exception to sys.unraisablehook and drops it."""
    def gen():
        try:
            yield 1
        finally:
            signal.raise_signal(signal.SIGTERM)

    g = gen()
    next(g)
    del g


def test_a_stop_lost_in_a_finaliser_is_raised_again_and_later_signals_are_ignored(monkeypatch):
    lost = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: lost.append(u.exc_type))
    latch = SignalLatch(Stopped)
    old = latch.install((signal.SIGTERM,))
    try:
        _lose_a_signal_in_a_finaliser()
        assert lost == [Stopped]  # the process would have run on
        with pytest.raises(Stopped) as exc:
            latch.check()
        assert exc.value.signum == signal.SIGTERM
        signal.raise_signal(signal.SIGTERM)  # a second signal does not cut the shutdown short
        with pytest.raises(Stopped):
            latch.check()
    finally:
        latch.restore(old)
    assert signal.getsignal(signal.SIGTERM) is old[signal.SIGTERM]
    fresh = SignalLatch(Stopped)
    fresh.check()  # no signal: nothing to raise


def test_a_waiting_member_stops_at_its_next_poll_when_the_signal_was_lost(tmp_path, monkeypatch):
    """The barrier calls ``check`` between polls: a member whose Stopped was lost while it waited
    for a member that will not come stops within a poll instead of waiting out the barrier."""
    lost = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: lost.append(u.exc_type))
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0)
    latch = SignalLatch(Stopped)
    old = latch.install((signal.SIGTERM,))
    try:
        threading.Timer(0.2, lambda: signal.pthread_kill(threading.main_thread().ident, signal.SIGALRM)).start()
        signal.signal(signal.SIGALRM, lambda *a: _lose_a_signal_in_a_finaliser())
        t0 = time.monotonic()
        with pytest.raises(Stopped):
            barrier.barrier(paths, 1, cfg, 0, like_agent(paths), quorum=2, timeout=60,
                         liveness=heartbeat.Liveness(paths, 60), poll_max=0.01, check=latch.check)
        assert 0.2 <= time.monotonic() - t0 < 1.0 and lost == [Stopped]
    finally:
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        latch.restore(old)
