"""Live progress: the tracker's figures, `status --watch` on a terminal (pty) and on a pipe, the launch view."""

import os
import pty
import re
import select
import signal
import subprocess
import sys
import time

import pytest

from rl_pool.commands import progress, status

from .conftest import ROOT, SHORT
from .helpers import T0, fake_pool, write_heartbeat, write_iteration

HISTORY = [[10.0, 12.0], [15.0, 11.0], ([14.0, 13.0], "parent", 15.5), [20.0, 25.0], [24.0, 19.0]]


def test_tracker_figures(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    write_heartbeat(paths, 0, "training", 6, last_return=24.0)
    write_heartbeat(paths, 1, "waiting", 6, last_return=19.0)
    snap = progress.Tracker(paths.root, since=time.time() - 65).poll()
    assert snap.iteration == 5 and snap.target == 20 and snap.pool_size == 2 and snap.env == "Swimmer-v5"
    assert snap.last["eval_return"] == 24.0 and snap.last["winner"] == "branch"
    assert snap.best["eval_return"] == 25.0 and snap.best["iteration"] == 4
    # 2 members x 1200 steps every 2 s (selections at T0 + 2 i; the pool was created at T0)
    assert snap.steps_per_second == pytest.approx(1200.0)
    assert snap.seconds_per_iteration == pytest.approx(2.0)
    assert snap.eta == pytest.approx(15 * 2.0)
    assert [m["state"] for m in snap.members] == ["training", "waiting"]
    line = progress.line(snap)
    for part in ("iteration 5/20", "selected 24.00 (member 0)", "best 25.00 (iteration 4)",
                 "m0 training 24.00", "m1 waiting 19.00", "1,200 steps/s", "elapsed 0:01:05", "left ~0:00:30"):
        assert part in line, (part, line)


def test_a_parent_win_is_named_not_member_none(tmp_path):
    paths = fake_pool(tmp_path / "p", [[10.0, 12.0], ([11.0, 9.0], "parent", 16.0)])
    snap = progress.Tracker(paths.root).poll()
    assert "selected 16.00 (the parent)" in progress.line(snap)
    st = status.status(paths.root)
    assert st["best"] == {"iteration": 2, "member": None, "eval_return": 16.0, "winner": "parent",
                          "agent_from": {"iteration": 1, "member": 1}}
    assert st["history"][1]["winner"] == "parent" and st["history"][1]["selected_member"] is None
    table = status.format_table(st)
    assert "best: 16.00 (iteration 2, the parent (member 1's agent of iteration 1))" in table
    assert "None" not in table


def test_rates_leave_out_downtime(tmp_path):
    paths = fake_pool(tmp_path / "p", [[1.0, 2.0]] * 4)
    # the pool was stopped for an hour after iteration 4, then went on at 2 s per iteration
    for i in range(5, 9):
        write_iteration(paths, i, [3.0, 4.0], t=T0 + 3600 + 2.0 * i)
    write_heartbeat(paths, 0, "training", 9)
    snap = progress.Tracker(paths.root).poll()
    assert snap.seconds_per_iteration == pytest.approx(2.0)
    assert snap.steps_per_second == pytest.approx(1200.0)


def test_no_time_left_while_no_member_runs(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    write_heartbeat(paths, 0, "stopped", 6, error="stopped by SIGTERM")
    write_heartbeat(paths, 1, "stopped", 6, error="stopped by SIGTERM")
    snap = progress.Tracker(paths.root).poll()
    assert snap.eta is None and "left -" in progress.line(snap)


def _watch(pool_dir, *args):
    return [sys.executable, "-m", "rl_pool", "status", str(pool_dir), "--watch", *map(str, args)]


def _read_for(fd, seconds):
    out, end = b"", time.monotonic() + seconds
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            try:
                chunk = os.read(fd, 65536)
            except OSError:  # pty closed
                break
            if not chunk:
                break
            out += chunk
    return out.decode(errors="replace")


def _wait_for(fd, text, timeout=20.0):
    out, end = "", time.monotonic() + timeout
    while time.monotonic() < end and text not in out:
        out += _read_for(fd, 0.2)
    assert text in out, out[-2000:]
    return out


def test_watch_on_a_pipe_prints_plain_lines_when_something_changes(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    write_heartbeat(paths, 0, "training", 6)
    write_heartbeat(paths, 1, "training", 6)
    proc = subprocess.Popen(_watch(paths.root, "--interval", 0.3), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=ROOT)
    try:
        first = _wait_for(proc.stdout.fileno(), "iteration 5/20")
        write_iteration(paths, 6, [30.0, 28.0])
        write_heartbeat(paths, 0, "evaluating", 7)
        later = _wait_for(proc.stdout.fileno(), "iteration 6/20")
        time.sleep(1.0)  # nothing changes now: no more lines
        quiet = _read_for(proc.stdout.fileno(), 0.5)
    finally:
        proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    text = first + later + quiet + rest.decode()
    assert "\x1b" not in text  # no terminal control codes in a log
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert all(" | " in ln for ln in lines), lines
    assert "selected 30.00 (member 0)" in later and "m0 evaluating" in later
    assert quiet == ""


def test_watch_on_a_terminal_redraws_in_place(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    write_heartbeat(paths, 0, "training", 6, last_return=24.0)
    write_heartbeat(paths, 1, "waiting", 6, last_return=19.0)
    master, slave = pty.openpty()
    env = dict(os.environ, TERM="xterm-256color", COLUMNS="120", LINES="40")
    proc = subprocess.Popen(_watch(paths.root, "--interval", 0.2), stdin=slave, stdout=slave, stderr=slave,
                            cwd=ROOT, env=env, start_new_session=True)
    os.close(slave)
    try:
        first = _wait_for(master, "iteration 5 / 20")
        write_iteration(paths, 6, [30.0, 28.0])
        later = _wait_for(master, "iteration 6 / 20")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        rest = _read_for(master, 0.5)
        os.close(master)
    assert proc.returncode == 0
    text = first + later + rest
    assert "\x1b[" in text                         # styled, and
    assert "\x1b[2K" in text and "\x1b[1A" in text  # the panel is erased and redrawn in place
    for part in ("Swimmer-v5", "member", "training", "waiting", "24.00", "left ~", "1,200 env steps/s"):
        assert part in text, part
    # the plain log line format never shows up on a terminal
    assert " | m0 " not in text


def test_watch_waits_for_a_pool_being_created_and_refuses_others(tmp_path):
    d = tmp_path / "new"
    (d / "logs").mkdir(parents=True)  # what shell/pool.sh makes before its members create the pool
    proc = subprocess.Popen(_watch(d, "--interval", 0.2), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=ROOT)
    try:
        out = _wait_for(proc.stdout.fileno(), "waiting for the pool to be created")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=20)
    assert proc.returncode == 0 and "\x1b" not in out
    for bad, why in ((tmp_path / "missing", "no pool directory"), (tmp_path, "not an rl-pool pool")):
        p = subprocess.run(_watch(bad), capture_output=True, text=True, cwd=ROOT, timeout=60)
        assert p.returncode == 2 and why in p.stderr and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1
    p = subprocess.run(_watch(tmp_path / "new", "--json"), capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert p.returncode == 2 and "--watch" in p.stderr


@pytest.mark.multiprocess
def test_launch_shows_live_progress_on_a_terminal(tmp_path):
    master, slave = pty.openpty()
    env = dict(os.environ, TERM="xterm-256color", COLUMNS="120", LINES="40")
    proc = subprocess.Popen([sys.executable, "-m", "rl_pool", "launch", "--pool-dir", str(tmp_path / "p"),
                             "--pool-size", "2", "--iterations", "4", *map(str, SHORT)],
                            stdin=slave, stdout=slave, stderr=slave, cwd=ROOT, env=env, start_new_session=True)
    os.close(slave)
    try:
        out = _wait_for(master, "iterations completed 4", timeout=240)
        proc.wait(timeout=60)
        out += _read_for(master, 0.3)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        os.close(master)
    assert proc.returncode == 0, out[-3000:]
    assert "\x1b[1A" in out and "iteration 4 / 4" in out and "finished" in out
    assert "member None" not in out


@pytest.mark.multiprocess
def test_pool_script_shows_progress_lines_in_a_log_and_stops_all_when_one_fails(tmp_path):
    d = tmp_path / "shell"
    env = dict(os.environ, POOL_DIR=str(d), N="2", LEARNING_RATES="0.02 0.2", ITERATIONS="3",
               PROGRESS_INTERVAL="0.5")
    script = os.path.join(ROOT, "shell", "pool.sh")
    p = subprocess.run(["bash", script, *map(str, SHORT)], env=env, capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stdout.splitlines() if " | " in ln]
    assert lines and "iteration 3/3" in lines[-1] and "m0 finished" in lines[-1], p.stdout
    assert "\x1b" not in p.stdout
    # a member that cannot run stops the others, and the script says which and why
    env["ITERATIONS"] = "6"
    bad = subprocess.run(["bash", script, *map(str, SHORT), "--gamma", "2"], env=env, capture_output=True,
                         text=True, timeout=240)
    assert bad.returncode == 1, bad.stderr
    # both members refuse the bad option; whichever the script sees first is named
    assert re.search(r"member [01] exited with 2", bad.stderr) and "--gamma" in bad.stderr
