import os
import subprocess
import sys
import tempfile

import pytest

from rl_pool.threads import cap_threads

cap_threads()

# Pool keys made by the tests (and the members they start) go to a throw-away config directory,
# never to the user's ~/.config/rl-pool/keys.
os.environ["XDG_CONFIG_HOME"] = tempfile.mkdtemp(prefix="rl-pool-test-config-")
for _var in ("RL_POOL_KEY", "RL_POOL_KEY_FILE"):
    os.environ.pop(_var, None)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: Short episodes keep real Swimmer-v5 runs to a second or two per process.
SHORT = ["--max-episode-steps", "60", "--train-episodes", "4", "--batch-episodes", "2",
         "--eval-episodes", "2"]


def rl_pool(*args, timeout=180, check=None, **kw) -> subprocess.CompletedProcess:
    """Run the real CLI in a fresh interpreter."""
    proc = subprocess.run([sys.executable, "-m", "rl_pool", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=kw.pop("cwd", ROOT), **kw)
    if check is not None:
        assert proc.returncode == check, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc


def spawn(*args, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rl_pool", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, **kw)


def past_its_deposit(d, m, since: int, at_latest: int | None = None) -> int | None:
    """The iteration k >= ``since`` whose deposit member ``m`` of the pool in ``d`` has made while
    the pool has not started iteration k + 1 yet (no directory for it), judged from the files
    alone; else None. That member is then waiting at k's barrier, or deciding, or just done
    (a heartbeat need not say "waiting": a short wait is not written).

    A member that decides is past its deposit for milliseconds only, so polls can miss every
    such window: with ``at_latest``, its deposit of that iteration answers ``at_latest``
    whatever the member does by then."""
    it = os.path.join(os.fspath(d), "iterations")
    if at_latest is not None and os.path.exists(os.path.join(it, f"{at_latest:06d}", f"member-{m:03d}.json")):
        return at_latest
    try:
        ks = sorted(int(n) for n in os.listdir(it) if n.isdigit())
    except OSError:
        return None
    k = ks[-1] if ks else -1
    if k >= since and os.path.exists(os.path.join(it, f"{k:06d}", f"member-{m:03d}.json")):
        return k
    return None


@pytest.fixture
def cli():
    return rl_pool
