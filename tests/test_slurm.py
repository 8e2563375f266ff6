"""A pool as a SLURM job array on a real single-node cluster (shell/slurm_selftest.sh).

The script brings up its own slurmctld, slurmd and munged (installing them with
apt-get if missing), runs the 2-member pool locally and as a job array, cancels
and resubmits one array task, and compares the selection histories. Without
root, apt-get or working daemons it exits 77 with "SKIP: <reason>".
"""

import os
import signal
import subprocess
import sys
import time

import pytest

from .conftest import ROOT

pytestmark = pytest.mark.slurm

SELFTEST = os.path.join(ROOT, "shell", "slurm_selftest.sh")
SKIPPED = 77
TIMEOUT = 600  # seconds; a run takes ~20 s once SLURM is installed (the install itself ~10 s plus downloads)


def test_job_array_pool_matches_local_launch_and_resumes_after_scancel():
    env = dict(os.environ)
    venv_bin = os.path.dirname(sys.executable)  # the members run with this test's own venv
    if os.path.exists(os.path.join(venv_bin, "rl-pool")):
        env |= {"RL_POOL": os.path.join(venv_bin, "rl-pool"), "PYTHON": sys.executable}
    t0 = time.monotonic()
    proc = subprocess.Popen(["bash", SELFTEST], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, cwd=ROOT, env=env)
    try:
        out, _ = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        # SIGTERM, not SIGKILL: the script's exit trap stops the daemons it started.
        proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        pytest.fail(f"slurm_selftest.sh did not finish within {TIMEOUT}s:\n{out}")
    print(out)
    print(f"slurm_selftest.sh: exit {proc.returncode} after {time.monotonic() - t0:.1f}s")
    if proc.returncode == SKIPPED:
        reasons = [line for line in out.splitlines() if line.startswith("SKIP:")]
        pytest.skip(reasons[-1] if reasons else f"slurm_selftest.sh exited {SKIPPED} without a reason:\n{out}")
    assert proc.returncode == 0, f"slurm_selftest.sh exited {proc.returncode}:\n{out}"
    assert out.rstrip().endswith("PASS"), out
