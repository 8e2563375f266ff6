"""TensorBoard event files, read back with TensorBoard's own reader: tags and values agree with the pool."""

import json
import logging
import os

import pytest

from rl_pool.commands import status, tb
from rl_pool.protocol import deposits, layout

from .helpers import fake_pool, write_iteration

pytest.importorskip("tensorboard", reason="TensorBoard (test extra) reads the event files back")
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

HISTORY = [[10.0, 12.0], [15.0, 11.0], ([14.0, 13.0], "parent", 15.5), [20.0, 25.0], [24.0, 19.0]]


def scalars(run_dir) -> dict[str, list[tuple[int, float]]]:
    """{tag: [(step, value), ...]} as TensorBoard's reader (with its restart purging) sees the run."""
    ea = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    ea.Reload()
    return {t: [(e.step, e.value) for e in ea.Scalars(t)] for t in ea.Tags()["scalars"]}


def _members_loop(paths, upto, first=1, pool_size=2):
    """What each member's loop does: catch up on start, then record every iteration after its barrier."""
    for m in range(pool_size):
        board = tb.Board(paths, m, pool_size, on=True)
        board.catch_up(first - 1)
        for i in range(first, upto + 1):
            metrics = json.loads(open(paths.deposit_json(i, m)).read())
            board.record(i, deposits.read_selected(paths, i), metrics, 0.01 * (m + 1))
        board.close()


def _check_against_history(paths, pool_size=2):
    st = status.status(paths.root)
    hist = st["history"]
    p = scalars(tb.pool_run(paths))
    assert set(p) == set(tb.POOL_TAGS)
    assert p["return/eval"] == [(h["iteration"], pytest.approx(h["eval_return"])) for h in hist]
    best = [c["best_so_far"] for c in status.curve(st)]
    assert p["return/best"] == [(h["iteration"], pytest.approx(b)) for h, b in zip(hist, best, strict=True)]
    assert p["pool/branch_won"] == [(h["iteration"], float(h["winner"] == "branch")) for h in hist]
    for m in range(pool_size):
        s = scalars(tb.member_run(paths, m))
        assert set(s) == set(tb.MEMBER_TAGS)
        mine = [(h, x) for h in hist for x in h["members"] if x["member"] == m]
        assert s["return/eval"] == [(h["iteration"], pytest.approx(x["eval_return"])) for h, x in mine]
        assert s["member/learning_rate"] == [(h["iteration"], pytest.approx(x["learning_rate"])) for h, x in mine]
        assert s["member/barrier_wait_seconds"] == [(h["iteration"], pytest.approx(x["wait_seconds"]))
                                                    for h, x in mine]
        assert s["member/train_steps_per_second"] == [
            (h["iteration"], pytest.approx(x["train_steps"] / x["train_seconds"])) for h, x in mine]
        assert s["member/won"] == [(h["iteration"], float(h["selected_member"] == m)) for h, _ in mine]


def test_one_run_per_member_and_one_for_the_pool_agree_with_the_history(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    _members_loop(paths, len(HISTORY))
    assert sorted(os.listdir(tb.tb_dir(paths))) == ["member-000", "member-001", "pool"]
    # one writer per directory: member 1 never writes the pool's run
    for run in ("member-000", "member-001", "pool"):
        assert len([n for n in os.listdir(os.path.join(tb.tb_dir(paths), run)) if ".tfevents." in n]) == 1
    _check_against_history(paths)
    # wall time is when the deposit / selection was made: TensorBoard's WALL axis is the pool's clock
    ea = EventAccumulator(tb.pool_run(paths))
    ea.Reload()
    sel = deposits.read_selected(paths, 3)
    assert ea.Scalars("return/eval")[2].wall_time == pytest.approx(sel["time"])


def test_restart_after_a_kill_shows_each_step_once_with_the_values_on_disk(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    # first life: iterations 1-3 recorded, then SIGKILL: no close, the last record torn in half
    boards = [tb.Board(paths, m, 2, on=True) for m in (0, 1)]
    for m, b in enumerate(boards):
        b.catch_up(0)
        for i in (1, 2, 3):
            b.record(i, deposits.read_selected(paths, i), None, 0.01 * (m + 1))
    for run in (tb.member_run(paths, 0), tb.pool_run(paths)):
        (name,) = [n for n in os.listdir(run) if ".tfevents." in n]
        with open(os.path.join(run, name), "r+b") as fh:
            fh.truncate(os.path.getsize(os.path.join(run, name)) - 7)
    # second life: the pool went on (iterations 4, 5); written.json still says 0, so everything is rewritten
    assert json.loads(open(os.path.join(tb.pool_run(paths), tb.MARK)).read()) == {"through": 0}
    _members_loop(paths, 5, first=4)
    for run in ("member-000", "pool"):
        assert len([n for n in os.listdir(os.path.join(tb.tb_dir(paths), run)) if ".tfevents." in n]) == 2
    _check_against_history(paths)  # exact lists: every step once, in order, with the pool's values


def test_restart_rewrites_only_after_the_last_mark(tmp_path, monkeypatch):
    monkeypatch.setattr(tb, "MARK_EVERY", 2)
    paths = fake_pool(tmp_path / "p", HISTORY)
    _members_loop(paths, 3)
    assert json.loads(open(os.path.join(tb.pool_run(paths), tb.MARK)).read()) == {"through": 3}
    # a later life starting at iteration 5 rewrites 4 only (from the files) and goes on with 5
    b = tb.Board(paths, 0, 2, on=True)
    b.catch_up(4)
    b.record(5, deposits.read_selected(paths, 5), None, 0.01)
    b.close()
    write_iteration(paths, 6, [30.0, 31.0])
    assert [s for s, _ in scalars(tb.pool_run(paths))["return/eval"]] == [1, 2, 3, 4, 5]
    # the rewritten file holds iterations 4 and 5 only
    newest = max(n for n in os.listdir(tb.pool_run(paths)) if ".tfevents." in n)
    only = EventAccumulator(os.path.join(tb.pool_run(paths), newest))
    only.Reload()
    assert [e.step for e in only.Scalars("return/eval")] == [4, 5]
    assert [v for _, v in scalars(tb.pool_run(paths))["return/best"]] == [12.0, 15.0, 15.5, 25.0, 25.0]


def test_the_pool_run_fills_in_selections_its_writer_skipped(tmp_path):
    paths = fake_pool(tmp_path / "p", HISTORY)
    b = tb.Board(paths, 0, 2, on=True)
    b.catch_up(0)
    b.record(1, deposits.read_selected(paths, 1), None, 0.0)
    b.record(4, deposits.read_selected(paths, 4), None, 0.0)  # fell behind: 2 and 3 were decided without it
    b.close()
    assert [s for s, _ in scalars(tb.pool_run(paths))["return/eval"]] == [1, 2, 3, 4]
    assert [s for s, _ in scalars(tb.member_run(paths, 0))["return/eval"]] == [1, 4]


def test_switched_off_or_failing_never_stops_a_member(tmp_path, monkeypatch):
    paths = fake_pool(tmp_path / "p", HISTORY)
    monkeypatch.setenv(tb.ENV_SWITCH, "0")
    b = tb.Board(paths, 0, 2)
    b.catch_up(5)
    b.record(5, deposits.read_selected(paths, 5), None, 0.0)
    b.close()
    assert not os.path.exists(tb.tb_dir(paths))
    monkeypatch.delenv(tb.ENV_SWITCH)
    open(tb.tb_dir(paths), "w").close()  # tb/ cannot be made: e.g. a full or read-only disk
    seen = []
    handler = logging.Handler()
    handler.emit = lambda record: seen.append(record.getMessage())
    logging.getLogger("rl_pool").addHandler(handler)
    try:
        b = tb.Board(paths, 0, 2)
        b.catch_up(5)
        b.record(5, deposits.read_selected(paths, 5), None, 0.0)
        b.close()
    finally:
        logging.getLogger("rl_pool").removeHandler(handler)
    assert not b.on
    assert len(seen) == 1 and seen[0].startswith("TensorBoard event files disabled")


@pytest.mark.multiprocess
def test_a_real_pool_writes_event_files_that_match_its_history(tmp_path):
    from .conftest import SHORT, rl_pool

    d = tmp_path / "real"
    rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--iterations", 3, *SHORT, "--quiet", check=0)
    paths = layout.Paths(d)
    assert os.path.isdir(tb.tb_dir(paths)), "a pool run writes TensorBoard event files"
    hist = status.status(paths.root)["history"]
    assert [s for s, _ in scalars(tb.pool_run(paths))["return/eval"]] == [h["iteration"] for h in hist]
    _check_against_history(paths)
