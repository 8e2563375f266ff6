"""`rl-pool compare`: the committed histories of three seeds, pools grouped by settings, bad input."""

import csv
import glob
import os
import struct

import pytest

from rl_pool.commands import compare, status

from .conftest import ROOT, rl_pool
from .helpers import fake_pool, write_heartbeat

SEEDS = sorted(glob.glob(os.path.join(ROOT, "results", "swimmer-v5", "seeds", "history-seed*.csv")))
SCREENING = os.path.join(ROOT, "results", "swimmer-v5", "screening")


def _png_size(path) -> tuple[int, int]:
    with open(path, "rb") as fh:
        head = fh.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


@pytest.mark.skipif(len(SEEDS) != 3, reason="the committed seed histories are not in this checkout")
def test_committed_seeds_give_the_readme_figures(tmp_path):
    out = tmp_path / "seeds.png"
    p = rl_pool("compare", *SEEDS, "--threshold", 350, "--at", "5,10,20", "--out", out, check=0)
    rows = {ln.split("  ")[0].strip(): ln.split() for ln in p.stdout.splitlines()}
    # docs/results.md: time to 350 of seeds 0, 1, 2 = 73, 39, 49 s; best at 5/10/20 min; env steps to 350
    assert rows["seeds/history-seed0"][4:] == ["361.2", "361.2", "362.0", "73", "1.24"]
    assert rows["seeds/history-seed1"][4:] == ["359.8", "361.2", "361.6", "39", "0.78"]
    assert rows["seeds/history-seed2"][4:] == ["359.6", "362.9", "362.9", "49", "0.92"]
    med = next(ln for ln in p.stdout.splitlines() if ln.startswith("seeds: median [min, max]"))
    for cell in ("359.8 [359.6, 361.2]", "361.2 [361.2, 362.9]", "362.0 [361.6, 362.9]", "49 [39, 73]",
                 "0.92 [0.78, 1.24]"):
        assert cell in med, (cell, med)
    assert _png_size(out) == (1320, 495) and os.path.getsize(out) > 30_000


def test_groups_seeds_together_and_settings_apart(tmp_path):
    runs = [compare.load(p) for p in SEEDS + sorted(glob.glob(os.path.join(SCREENING, "exp-*.csv")))]
    groups = compare.group_runs(runs)
    assert list(groups) == ["seeds", "exp-lr0.003-0.03", "exp-lr0.01-0.1"]
    assert [len(v) for v in groups.values()] == [3, 1, 1]
    named = compare.group_runs([compare.load(p) for p in SEEDS], ["a", "b", "a"])
    assert {k: [r.name for r in v] for k, v in named.items()} == {
        "a": ["history-seed0", "history-seed2"], "b": ["history-seed1"]}


def test_pools_differing_only_in_seed_form_one_group(tmp_path):
    hist = [[10.0, 12.0], [15.0, 11.0], [20.0, 25.0]]
    a = fake_pool(tmp_path / "a", hist, seed=0)
    b = fake_pool(tmp_path / "b", [[11.0, 9.0], [30.0, 12.0], [31.0, 40.0]], seed=1)
    c = fake_pool(tmp_path / "c", hist, seed=0, gamma=0.99)
    for p in (a, b, c):
        write_heartbeat(p, 0, "finished", 3)
    groups = compare.group_runs([compare.load(p.root) for p in (a, b, c)])
    assert [len(v) for v in groups.values()] == [2, 1]
    first, second = groups
    assert first == "Swimmer-v5 lr 0.01/0.1" and second == "Swimmer-v5 lr 0.01/0.1 (2)"
    run = groups[first][0]
    # a pool directory and its history.csv are the same curve
    csv_path = tmp_path / "a.csv"
    status.write_csv(status.status(a.root), str(csv_path))
    again = compare.load(str(csv_path))
    assert list(again.seconds) == pytest.approx(list(run.seconds))
    assert list(again.steps) == list(run.steps) == [2400, 4800, 7200]
    assert list(again.best) == list(run.best) == [12.0, 15.0, 25.0]
    text = compare.compare([a.root, b.root], threshold=20.0, at_minutes=[1])
    med = next(ln for ln in text.splitlines() if ln.startswith("Swimmer-v5 lr 0.01/0.1: median"))
    assert "5 [4, 6]" in med  # seconds to 20: pool a at iteration 3 (6 s), pool b at iteration 2 (4 s)


def _best_by_steps(path, steps):
    """Reference for --at-steps: the best evaluation return among the rows at or before ``steps``
    env steps, by a plain loop over the CSV; None if the run ended more than 5% short of them."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if float(rows[-1]["env_steps"]) < 0.95 * steps:
        return None
    seen = [float(r["eval_return"]) for r in rows if r["eval_return"] and float(r["env_steps"]) <= steps]
    return max(seen) if seen else None


@pytest.mark.skipif(len(SEEDS) != 3, reason="the committed seed histories are not in this checkout")
def test_best_at_env_steps_matches_a_plain_loop_over_the_csv():
    at = [0.5, 1, 2.5, 40]  # 40 M: longer than any of these runs
    p = rl_pool("compare", *SEEDS, "--at-steps", ",".join(map(str, at)), check=0)
    head, *lines = p.stdout.splitlines()
    assert "min" not in head.replace("minutes", "") and "best at 2.5 M steps" in head
    for path in SEEDS:
        name = "seeds/" + os.path.splitext(os.path.basename(path))[0]
        cells = next(ln for ln in lines if ln.startswith(name + " ")).split()[4:]
        want = [_best_by_steps(path, 1e6 * s) for s in at]
        assert want[-1] is None and all(w is not None for w in want[:-1])
        assert cells == [status.fixed(w, 1) for w in want], (name, cells, want)


def test_best_at_env_steps_of_a_pool(tmp_path):
    a = fake_pool(tmp_path / "a", [[10.0, 12.0], [15.0, 11.0], [20.0, 25.0]], seed=0)
    run = compare.load(a.root)  # 2400 env steps per iteration
    assert [run.best_at_steps(s) for s in (2000, 2400, 4799, 4800, 7200, 7500, 7700)] == \
        [None, 12.0, 12.0, 15.0, 25.0, 25.0, None]


def test_bad_inputs_are_one_line_and_exit_2(tmp_path):
    bad_csv = tmp_path / "x.csv"
    bad_csv.write_text("a,b\n1,2\n")
    for args, why in (([tmp_path / "nope"], "no pool directory or history.csv"),
                      ([bad_csv], "not a history.csv"),
                      ([*SEEDS[:1], "--at", "0,5"], "--at"),
                      ([*SEEDS[:1], "--at-steps", "1,-2"], "--at-steps"),
                      ([*SEEDS[:2], "--groups", "a"], "--groups has 1 names for 2 inputs")):
        p = rl_pool("compare", *args)
        assert p.returncode == 2 and why in p.stderr and "Traceback" not in p.stderr, p.stderr
