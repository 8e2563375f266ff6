"""The learning benchmark's summary table: medians and ratios with pools that did not get there."""

import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "learning.py")
spec = importlib.util.spec_from_file_location("learning_benchmark", SCRIPT)
learning = importlib.util.module_from_spec(spec)
spec.loader.exec_module(learning)


def _pool(size, iterations, steps=None, ran=60, error=None, minutes=None, ran_minutes=None):
    out = {"size": size, "reached": iterations is not None, "iterations": iterations,
           "env_steps": steps if iterations is not None else None,
           "minutes": minutes if iterations is not None else None,
           "ran_iterations": iterations if iterations is not None else ran}
    if ran_minutes is not None:
        out["ran_minutes"] = ran_minutes
    return out | ({"error": error} if error else {})


def test_medians_and_ratios_against_the_first_size():
    results = [_pool(2, 45, 9_000_000), _pool(2, 24, 5_000_000), _pool(2, 16, 3_000_000),
               _pool(8, 10, 8_000_000), _pool(8, 7, 6_000_000), _pool(8, 14, 10_000_000)]
    assert learning.summary(results, [2, 8]) == [(2, "24", "1.00x", "5000000", "-"),
                                                   (8, "10", "2.40x", "8000000", "-")]


def test_pools_that_did_not_get_there_give_bounds():
    results = [_pool(2, None), _pool(2, None), _pool(8, None), _pool(8, None),
               _pool(16, 24, 9_219_000), _pool(16, 31, 11_813_000)]
    # the 2-member median is more than 60, so 16 members needed more than 60 / 27.5 times fewer
    assert learning.summary(results, [2, 8, 16]) == [
        (2, ">60", "1.00x", "-", "-"), (8, ">60", "-", "-", "-"), (16, "27.5", ">2.18x", "10516000", "-")]
    # half of an even number short of it: the median is more than (24 + 60) / 2
    rows = learning.summary([_pool(2, 10, 1), _pool(2, 12, 1), _pool(8, 24, 5), _pool(8, None)], [2, 8])
    assert rows == [(2, "11", "1.00x", "1", "-"), (8, ">42", "<0.26x", "-", "-")]
    # one of three short of it still has an exact median
    assert learning.summary([_pool(2, None), _pool(2, 20, 4), _pool(2, 30, 6)], [2]) == [(2, "30", "1.00x", "6", "-")]


def test_a_pool_that_ran_fewer_iterations_bounds_with_what_it_ran_and_errors_are_left_out():
    results = [_pool(2, None, ran=11), _pool(2, None, ran=40), _pool(2, 50, 7, error=None),
               _pool(8, None, ran=3, error="Traceback ...")]
    assert learning.summary(results, [2, 8]) == [(2, ">40", "1.00x", "-", "-"), (8, "-", "-", "-", "-")]
    # nothing left of the first size: nothing to compare with
    assert learning.summary([_pool(2, None, error="x"), _pool(8, 5, 1)], [2, 8]) == [(2, "-", "-", "-", "-"),
                                                                                     (8, "5", "-", "1", "-")]


def test_ratios_are_against_two_members_and_minutes_bound_by_what_a_pool_ran():
    results = [_pool(1, 90, 9, minutes=4.0), _pool(1, 80, 8, minutes=3.0), _pool(1, 70, 7, minutes=2.0),
               _pool(2, 40, 8, minutes=2.0), _pool(2, 30, 6, minutes=1.5), _pool(2, None, ran_minutes=3.5),
               _pool(8, 10, 8, minutes=0.5), _pool(8, 5, 4, minutes=0.25), _pool(8, 20, 16, minutes=1.0)]
    for r in results:
        r.setdefault("ran_minutes", r["minutes"])
    # 2 members: iterations 30, 40, more than 60; steps 6, 8, more; minutes 1.5, 2.0, more than 3.5:
    # every median exact
    assert learning.summary(results, [1, 2, 8]) == [
        (1, "80", "0.50x", "8", "3"), (2, "40", "1.00x", "8", "2"), (8, "10", "4.00x", "8", "0.5")]
    # asked against one member instead
    assert learning.summary(results, [1, 2, 8], base_size=1)[2][2] == "8.00x"
    # without 2 members, against the first size
    assert learning.summary(results, [1, 8])[1][2] == "8.00x"
    # two of three short of it: the minutes' median is at least what the middle one ran
    short = [_pool(4, None, ran=100, ran_minutes=4.4), _pool(4, None, ran=60, ran_minutes=2.5),
             _pool(4, 70, 7, minutes=3.1, ran_minutes=3.1)]
    assert learning.summary(short, [4]) == [(4, ">70", "1.00x", "-", ">3.1")]


def test_summary_of_saved_lines_groups_by_options_and_refuses_what_is_not_a_result(tmp_path, capsys):
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    rows = [_pool(2, 40, 8, minutes=2.0) | {"seed": 0}, _pool(8, 10, 4, minutes=0.5) | {"seed": 0},
            _pool(2, 20, 4, minutes=1.0) | {"seed": 1}]
    a.write_text("".join(json.dumps(r | {"options": ["--preset", "halfcheetah"], "threshold": 3000.0}) + "\n"
                         for r in rows))
    b.write_text(json.dumps(_pool(8, 5, 2, minutes=0.2) | {"seed": 1, "options": ["--preset", "halfcheetah"],
                                                            "threshold": 3000.0}) + "\n"
                 + json.dumps(_pool(8, 7, 2) | {"seed": 0, "options": [], "threshold": 350.0}) + "\n")
    assert learning.main(["--summary", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    # seeds 0 and 1 of the same options from two files make one table: 2 members 30, 8 members 7.5
    assert "# --preset halfcheetah; threshold 3000.0; seeds 0,1" in out
    assert re.search(r"^\s+8\s+7.5\s+4.00x\s+3\s+0.35$", out, re.M)
    assert "# defaults; threshold 350.0; seeds 0" in out
    # --seeds picks seeds out of the saved lines
    assert learning.main(["--summary", str(a), str(b), "--seeds", "0"]) == 0
    assert re.search(r"^\s+8\s+10\s+4.00x\s+4\s+0.5$", capsys.readouterr().out, re.M)
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"size": 2}\n')
    assert learning.main(["--summary", str(a), str(bad)]) == 2
    assert capsys.readouterr().err.strip() == f"learning.py: {bad}:1: not a result line"
    assert learning.main(["--summary", str(tmp_path / "missing.jsonl")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_ctrl_c_stops_the_running_pool_with_one_line_and_no_traceback(tmp_path):
    """A real run interrupted while its pool trains: exit 130, one line, and no member left behind."""
    work = str(tmp_path / "pools")
    proc = subprocess.Popen([sys.executable, SCRIPT, "--env", "Swimmer-v5", "--threshold", "1e9", "--sizes", "1",
                             "--seeds", "0", "--max-iterations", "1000", "--workdir", work, "--", "--train-episodes",
                             "2", "--eval-episodes", "1", "--max-episode-steps", "50"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    heartbeat = os.path.join(work, "n1-s0", "members", "member-000.json")
    deadline = time.monotonic() + 120
    while not os.path.exists(heartbeat) and time.monotonic() < deadline:
        time.sleep(0.2)
    pid = json.loads(open(heartbeat).read())["pid"]  # the member, training before the interrupt
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=90)
    assert out.startswith("# ")
    assert proc.returncode == 130
    assert "Traceback" not in err
    assert err.strip().splitlines() == ["learning.py: interrupted; the running pool was stopped, the lines written "
                                        "so far stay"]
    assert not os.path.exists(f"/proc/{pid}") or "zombie" in open(f"/proc/{pid}/status").read().lower()
    assert json.loads(open(heartbeat).read())["state"] == "stopped"


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the lost KeyboardInterrupt
def test_a_ctrl_c_lost_in_a_finaliser_still_stops_the_running_pool(tmp_path, monkeypatch):
    """Python runs a signal handler between any two bytecodes, a ``__del__``'s too, and an exception
    raised there is only printed: the first Ctrl-C's KeyboardInterrupt can be lost. The latch keeps
    it, so the poll loop raises it and stops the real pool it is running (no member left behind)."""
    from rl_pool.errors import SignalLatch

    latch = SignalLatch(lambda signum: KeyboardInterrupt())
    monkeypatch.setattr(learning, "_interrupt", latch)
    old = latch.install((signal.SIGINT,))
    try:
        class Finaliser:
            def __del__(self):
                os.kill(os.getpid(), signal.SIGINT)  # the handler runs here; its exception is lost

        Finaliser()
        time.sleep(0.1)
        assert latch.signum == signal.SIGINT  # the interrupt happened and nothing raised it here
        pool = str(tmp_path / "pool")
        t0 = time.monotonic()
        try:
            learning.run_pool(pool, 1, 0, 1e9, 1000, ["--env", "Swimmer-v5", "--train-episodes", "2",
                                                      "--eval-episodes", "1", "--max-episode-steps", "50"])
        except KeyboardInterrupt:
            pass
        else:
            raise AssertionError("run_pool ran on after a lost Ctrl-C")
    finally:
        latch.restore(old)
    assert time.monotonic() - t0 < 60
    left = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                cmd = fh.read().decode(errors="replace")
        except OSError:
            continue
        if pool in cmd and "zombie" not in open(f"/proc/{pid}/status").read().lower():
            left.append(cmd)
    assert not left  # the launcher and its members are gone
