"""Stop signals that Python loses in a finaliser are raised again (errors.SignalLatch), and one that
lands inside an environment's constructor stops the member instead of failing it."""
import json
import os
import signal
import sys
import threading
import time

import pytest

from rl_pool.errors import SignalLatch, Stopped
from rl_pool.protocol import barrier, heartbeat

from .conftest import ROOT, SHORT, spawn
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


_STALLING_ENV = '''
import os, signal, time

import gymnasium
from gymnasium.envs.mujoco.swimmer_v5 import SwimmerEnv


def make(**kwargs):
    """Swimmer, except that making it stalls the way a first `import mujoco` does (when STALL_WHEN is
    "always", or "latched" and the member's stop handler is in place), and an interrupt comes out
    as an ImportError, as from a C extension."""
    latched = type(getattr(signal.getsignal(signal.SIGTERM), "__self__", None)).__name__ == "SignalLatch"
    if os.environ["STALL_WHEN"] == "always" or latched:
        with open(os.environ["STALL_MARK"], "w") as fh:
            fh.write(str(os.getpid()))
        try:
            time.sleep(120)
        except BaseException as exc:
            raise ImportError("initialization of an extension module failed") from exc
    return SwimmerEnv(**kwargs)


gymnasium.register("Stall-v0", entry_point=make, max_episode_steps=60)
'''


@pytest.mark.parametrize("when", ["latched", "always"], ids=["resumed-pool", "new-pool"])
def test_ctrl_c_while_an_env_is_made_stops_instead_of_reporting_a_bad_environment(tmp_path, when):
    """Ctrl-C that lands while an environment is made and comes out of that code as an ImportError:
    exit 130, no traceback, and no "cannot make environment". In a member at work (its stop
    handler in place) the heartbeat says stopped; while a new pool is made (before any member
    runs) the command stops as on any Ctrl-C."""
    (tmp_path / "stall.py").write_text(_STALLING_ENV)
    mark = tmp_path / "stalled"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), ROOT]), "STALL_MARK": str(mark),
           "STALL_WHEN": when}
    d = tmp_path / "pool"
    # SIGINT as a terminal delivers it, even where this test runs with SIGINT ignored: the child
    # inherits the default disposition (set here for the spawn, not in the child: no Python code
    # may run between fork and exec in a process with JAX's threads)
    old = signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        proc = spawn("train", "--pool-dir", d, "--env", "stall:Stall-v0", "--member", 0, "--pool-size", 1,
                     "--iterations", 2, *SHORT, "--quiet", env=env)
    finally:
        signal.signal(signal.SIGINT, old)
    try:
        deadline = time.monotonic() + 120
        while not mark.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert mark.exists(), proc.communicate(timeout=10)
        time.sleep(0.1)  # the pid is written: the process is asleep inside the env's constructor
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "Traceback" not in err and "cannot make environment" not in err
    if when == "latched":
        doc = json.loads((d / "members" / "member-000.json").read_text())
        assert doc["state"] == "stopped" and "SIGINT" in doc["error"], doc
    else:
        assert err.strip() == "rl-pool: interrupted"


def test_a_stop_that_jax_wraps_in_its_own_error_still_stops_the_member():
    """SIGTERM landing while jax compares a jitted call's static arguments (the policy's spec)
    reaches the member as jax's ValueError, not as Stopped; the member's latch raises the stop
    behind it (``check``), and a failure with no signal behind it stays a failure."""
    import jax

    armed = []

    class Spec:  # a static argument like PolicySpec: hashed, and compared with the cached one
        def __hash__(self):
            return 1

        def __eq__(self, other):
            if armed:
                signal.raise_signal(signal.SIGTERM)
            return isinstance(other, Spec)

    step = jax.jit(lambda x, spec: x + 1.0, static_argnames=("spec",))
    latch = SignalLatch(Stopped)
    old = latch.install((signal.SIGTERM,))
    try:
        step(1.0, spec=Spec())
        armed.append(True)
        with pytest.raises(BaseException) as caught:
            step(1.0, spec=Spec())
        assert not isinstance(caught.value, Stopped)  # what the member's loop sees: jax's error
        with pytest.raises(Stopped) as stop:
            latch.check()
        assert stop.value.signum == signal.SIGTERM
    finally:
        latch.restore(old)
    SignalLatch(Stopped).check()  # no signal behind a real failure: nothing to raise
