"""benchmarks/bench.py profile: a real pool of member processes, each under cProfile."""

import os
import re
import signal
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "bench.py")


@pytest.mark.multiprocess
def test_profile_covers_every_member_after_the_warmup_and_lists_the_protocol():
    members, iterations, warmup = 3, 6, 2
    proc = subprocess.Popen([sys.executable, SCRIPT, "profile", "--members", str(members), "--iterations",
                             str(iterations), "--warmup", str(warmup), "--top", "40"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # the bench and its members, which share its session
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err[-2000:]
    # each member's profile runs from its deposit of iteration `warmup` to its last deposit
    covered = int(re.search(r"\((\d+) member-iterations", out).group(1))
    assert covered == members * (iterations - warmup)
    assert re.search(rf"(\d+) of {iterations - warmup} selections merged", out)
    total = float(re.search(r"all profiled functions: ([\d.]+) ms", out).group(1))
    assert total > 0
    cumulative = out.split("CPU including callees")[1]
    # the member's own loop: the barrier, training and the deposit, each with its share of the CPU
    for where in ("rl_pool/protocol/barrier.py", "rl_pool/learning/trainer.py", "rl_pool/protocol/deposits.py"):
        lines = [ln for ln in cumulative.splitlines() if where in ln]
        assert lines, f"{where} not among the top 40:\n{cumulative}"
        assert 0 < float(lines[0].split()[0]) <= total


def test_train_cost_times_a_preset_beside_its_change_on_the_same_agent():
    """``bench.py train-cost``: a committed agent trained with its preset and with an option
    changed, in alternating rounds; an option the pool does not have is refused in one line."""
    run = lambda *a: subprocess.run([sys.executable, SCRIPT, "train-cost", "--preset", "reacher",  # noqa: E731
                                     "--agent", "results/reacher-v5/best.npz", *a],
                                    cwd=ROOT, capture_output=True, text=True, timeout=300)
    r = run("--set", "policy_epochs=3", "--repeats", "1")
    assert r.returncode == 0, r.stderr[-2000:]
    times = re.findall(r"^  (the preset|changed) +([\d.]+) s per iteration, +(\d+) env steps$", r.stdout, re.M)
    assert [t[0] for t in times] == ["the preset", "changed"]
    assert all(float(t[1]) > 0 and int(t[2]) == 100 * 50 for t in times)  # 100 episodes of Reacher's 50 steps
    ratio = float(re.search(r"changed \(policy_epochs=3\) / the preset: ([\d.]+)", r.stdout).group(1))
    # the times are printed to 0.01 s: the ratio of the printed times within their rounding
    lo = (float(times[1][1]) - 0.005) / (float(times[0][1]) + 0.005)
    hi = (float(times[1][1]) + 0.005) / (float(times[0][1]) - 0.005)
    assert lo - 0.005 <= ratio <= hi + 0.005
    bad = run("--set", "no_such_option=1")
    assert bad.returncode != 0 and bad.stderr.strip() == "bench: unknown option 'no_such_option'"
