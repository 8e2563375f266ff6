"""benchmarks/bench.py profile: a real pool of member processes, each under cProfile."""

import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "bench.py")


def test_profile_covers_every_member_after_the_warmup_and_lists_the_protocol():
    members, iterations, warmup = 3, 6, 2
    proc = subprocess.run([sys.executable, SCRIPT, "profile", "--members", str(members), "--iterations",
                           str(iterations), "--warmup", str(warmup), "--top", "40"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    # each member's profile starts at its deposit of iteration `warmup` and ends with its last deposit
    covered = int(re.search(r"\((\d+) member-iterations", out).group(1))
    assert covered == members * (iterations - warmup)
    assert re.search(rf"(\d+) of {iterations - warmup} selections merged", out)
    total = float(re.search(r"all profiled functions: ([\d.]+) ms", out).group(1))
    assert total > 0
    cumulative = out.split("CPU including callees")[1]
    # the member's own loop: the barrier, training and the deposit, each with its share of the CPU
    for where in ("rl_pool/protocol/barrier.py", "rl_pool/learning/trainer.py", "rl_pool/protocol/deposits.py"):
        line = next(ln for ln in cumulative.splitlines() if where in ln)
        assert 0 < float(line.split()[0]) <= total
