"""The shared-directory protocol on tmp_path: deposits, selection, hostile files, init, GC."""

import collections
import io
import json
import os
import pickle
import threading
import time

import numpy as np
import pytest

from rl_pool import fsutil
from rl_pool.errors import UsageError
from rl_pool.maths import policy
from rl_pool.protocol import barrier, deposits, heartbeat, layout, pool, selection

from .helpers import Evil, agent, deposit, fake_initial, like_agent, make_pool


def _decide(paths, cfg, i, members):
    sel = pool.select(paths, i, cfg, like_agent(paths), set(members), "complete", deposits.read_selected(paths, i - 1))
    doc, _ = pool.publish_selection(paths, sel, by=0)
    return doc


def test_init_writes_config_initial_and_selection_zero(tmp_path):
    paths, cfg = make_pool(tmp_path / "p")
    assert cfg.pool_size == 2 and deposits.last_selected(paths) == 0
    sel = deposits.read_selected(paths, 0)
    assert sel["agent"] == "iterations/000000/initial.npz"
    assert deposits.load_selected_agent(paths, 0).params["w"].shape == (9, 4)
    saved = json.loads(open(paths.pool_json).read())
    assert saved["protocol"] == 3 and saved["pool_size"] == 2


def test_reopening_with_other_settings_is_refused_and_changes_nothing(tmp_path):
    paths, cfg = make_pool(tmp_path / "p")
    before = {p: open(os.path.join(dp, p), "rb").read() for dp, _, fs in os.walk(paths.root) for p in fs}
    with pytest.raises(UsageError, match="--pool-size 2"):
        make_pool(tmp_path / "p", pool_size=3)
    with pytest.raises(UsageError, match="--env Swimmer-v5"):
        make_pool(tmp_path / "p", env="Hopper-v5")
    after = {p: open(os.path.join(dp, p), "rb").read() for dp, _, fs in os.walk(paths.root) for p in fs}
    assert before == after
    # Unset options take the pool's values.
    cfg = pool.open_pool(paths, {}, fake_initial)
    assert cfg.pool_size == 2


def test_foreign_directories_are_refused(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "thesis.tex").write_text("x")
    with pytest.raises(UsageError, match="not an rl-pool pool"):
        make_pool(tmp_path / "d")
    (tmp_path / "e").mkdir()
    (tmp_path / "e" / "pool.json").write_text("{garbage")
    with pytest.raises(UsageError, match="not a valid"):
        pool.read_config(layout.Paths(tmp_path / "e"))


def test_choose_highest_return_ties_to_lowest_member():
    assert selection.choose([(2, 5.0), (0, 3.0), (1, 5.0)]) == (1, 5.0)
    assert selection.choose([(3, -1.0)]) == (3, -1.0)
    with pytest.raises(ValueError):
        selection.choose([])


def test_selection_is_argmax_over_valid_deposits(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    deposit(paths, 1, 0, 10.0)
    deposit(paths, 1, 1, 12.5)
    deposit(paths, 1, 2, 12.5)
    have = deposits.present(paths, 1, 3)
    sel = pool.select(paths, 1, cfg, like_agent(paths), have, "complete", deposits.read_selected(paths, 0))
    assert sel["member"] == 1 and sel["eval_return"] == 12.5
    assert [c["member"] for c in sel["considered"]] == [0, 1, 2] and sel["skipped"] == []
    _, created = pool.publish_selection(paths, sel, by=0)
    assert created and deposits.load_selected_agent(paths, 1).to_bytes() == agent(1).to_bytes()


def test_stray_files_are_ignored_and_temp_files_never_count(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=2)
    d = paths.iteration(1)
    os.makedirs(d)
    for name in ["member-007.json", "member-1.json", "member-0001.json", "notes.txt", "member-000.json.bak",
                 ".member-001.json.tmp-host-1-abc", "member-001.wait.json"]:
        open(os.path.join(d, name), "w").write("{}")
    assert deposits.present(paths, 1, 2) == set()
    deposit(paths, 1, 0, 1.0)
    assert deposits.present(paths, 1, 2) == {0}


def test_hostile_and_broken_deposits_are_skipped_with_reasons(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=4)
    marker = tmp_path / "code-ran"
    deposit(paths, 1, 0, 3.0)
    # 1: a pickled object inside the .npz claiming a huge return
    with np.load(io.BytesIO(agent().to_bytes())) as z:
        arrays = {k: z[k] for k in z.files}
    buf = io.BytesIO()
    np.savez(buf, **(arrays | {"param.w": np.array([Evil(marker)], dtype=object)}))
    data = buf.getvalue()
    open(paths.deposit_npz(1, 1), "wb").write(data)
    fsutil.write_json(paths.deposit_json(1, 1), paths.sign({"iteration": 1, "member": 1, "eval_return": 1e9,
                                                            "agent_sha256": layout.sha256(data)}))
    # 2: garbage JSON
    open(paths.deposit_json(1, 2), "w").write("{\"eval_return\": 1e99, oops")
    # 3: a valid agent whose JSON claims NaN
    deposit(paths, 1, 3, 1.0)
    doc = json.loads(open(paths.deposit_json(1, 3)).read())
    # a member whose return came out NaN writes null (JSON has no NaN; signed, like any deposit)
    open(paths.deposit_json(1, 3), "w").write(json.dumps(paths.sign(doc | {"eval_return": None})))
    sel = pool.select(paths, 1, cfg, like_agent(paths), deposits.present(paths, 1, 4), "complete",
                      deposits.read_selected(paths, 0))
    assert sel["member"] == 0
    reasons = {s["member"]: s["reason"] for s in sel["skipped"]}
    assert set(reasons) == {1, 2, 3}
    assert "unreadable agent" in reasons[1] and "unreadable" in reasons[2] and "finite" in reasons[3]
    assert not marker.exists()


def test_swapped_agent_or_other_env_is_skipped(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 3.0)
    deposit(paths, 1, 1, 5.0)
    open(paths.deposit_npz(1, 1), "wb").write(agent(9).to_bytes())  # not the agent its JSON hashed
    sel = pool.select(paths, 1, cfg, like_agent(paths), {0, 1}, "complete", deposits.read_selected(paths, 0))
    assert sel["member"] == 0 and "hash" in sel["skipped"][0]["reason"]


def test_no_valid_deposit_carries_the_previous_agent_over(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    open(os.path.join(paths.iteration(0), "..", "x"), "w").close()
    os.makedirs(paths.iteration(1))
    open(paths.deposit_json(1, 0), "w").write("nope")
    sel = pool.select(paths, 1, cfg, like_agent(paths), {0}, "timeout", deposits.read_selected(paths, 0))
    assert sel["member"] is None and sel["carried_from"] == 0
    pool.publish_selection(paths, sel, by=0)
    assert deposits.load_selected_agent(paths, 1).to_bytes() == deposits.load_selected_agent(paths, 0).to_bytes()


def test_first_selection_written_wins(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0)
    prev = deposits.read_selected(paths, 0)
    alone = pool.select(paths, 1, cfg, like_agent(paths), {0}, "timeout", prev)
    doc1, c1 = pool.publish_selection(paths, alone, by=0)
    deposit(paths, 1, 1, 99.0)
    full = pool.select(paths, 1, cfg, like_agent(paths), {0, 1}, "complete", prev)
    doc2, c2 = pool.publish_selection(paths, full, by=1)
    assert (c1, c2) == (True, False)
    assert doc2["member"] == doc1["member"] == 0


def test_selection_pointing_outside_the_pool_is_refused(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=1)
    with pytest.raises(ValueError, match="outside"):
        paths.resolve("../../etc/passwd")


def test_gc_keeps_selected_agent_and_all_json(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    for m, r in enumerate([1.0, 7.0, 2.0]):
        deposit(paths, 1, m, r)
    open(os.path.join(paths.iteration(1), f".member-002.npz.tmp-{heartbeat.HOST.split('.')[0]}-{2**22 + 4321}-x"), "w").close()  # a dead writer's
    live = f".member-000.json.tmp-{heartbeat.HOST.split('.')[0]}-{os.getpid()}-y"
    open(os.path.join(paths.iteration(1), live), "w").close()  # a live writer's: kept
    sel = pool.select(paths, 1, cfg, like_agent(paths), {0, 1, 2}, "complete", deposits.read_selected(paths, 0))
    pool.publish_selection(paths, sel, by=0)
    assert pool.collect_garbage(paths, 1) == 3
    names = sorted(os.listdir(paths.iteration(1)))
    assert names == sorted([live, "member-000.json", "member-001.json", "member-001.npz",
                            "member-002.json", "selected.json", ".selected.json.once"])


def test_update_best_only_on_improvement(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=1)
    for i, r in [(1, 5.0), (2, 3.0), (3, 8.0)]:
        deposit(paths, i, 0, r, seed=i)
        sel = pool.select(paths, i, cfg, like_agent(paths), {0}, "complete", deposits.read_selected(paths, i - 1))
        pool.publish_selection(paths, sel, by=0)
        pool.update_best(paths, sel)
        best = json.loads(open(paths.best_json).read())
        assert best["iteration"] == {1: 1, 2: 1, 3: 3}[i]
    assert open(paths.best_npz, "rb").read() == agent(3).to_bytes()


def test_atomic_write_leaves_no_temp_and_create_once_is_once(tmp_path):
    from rl_pool.protocol import claim

    p = tmp_path / "f.json"
    fsutil.atomic_write(p, b"one")
    fsutil.atomic_write(p, b"two")
    assert p.read_bytes() == b"two" and os.listdir(tmp_path) == ["f.json"]
    assert claim.create_once(tmp_path / "g", b"a") == (b"a", True)
    assert claim.create_once(tmp_path / "g", b"b") == (b"a", False)
    assert (tmp_path / "g").read_bytes() == b"a" and sorted(n for n in os.listdir(tmp_path)
                                                          if not n.startswith(".")) == ["f.json", "g"]


def test_liveness_judges_change_not_clocks(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=2)
    live = heartbeat.Liveness(paths, timeout=0.2)
    assert live.stale(1) is None  # never seen: not stale until the timeout passes
    import time

    time.sleep(0.25)
    assert "unchanged" in live.stale(1)
    # A heartbeat from another host with a wildly wrong clock, but changing: alive.
    doc = {"member": 1, "pid": 1, "host": "elsewhere", "beat": 1, "state": "training", "time": 0}
    fsutil.write_json(paths.heartbeat(1), paths.sign(doc))
    assert live.stale(1) is None
    fsutil.write_json(paths.heartbeat(1), paths.sign(doc | {"state": "failed", "beat": 2}))
    assert "failed" in live.stale(1)
    fsutil.write_json(paths.heartbeat(1), paths.sign(doc | {"host": heartbeat.HOST, "pid": 2**22 + 12345, "beat": 3}))
    assert "gone" in live.stale(1)


def test_a_heartbeat_writes_a_quick_state_change_when_its_gap_has_passed(tmp_path, monkeypatch):
    import time

    monkeypatch.setattr(heartbeat.Heartbeat, "MIN_GAP", 0.5)  # "within the gap" holds on a loaded machine too
    paths, _cfg = make_pool(tmp_path / "p", pool_size=1)
    hb = heartbeat.Heartbeat(paths, 0, interval=30.0, extra={}).start()
    read = lambda: heartbeat.read_heartbeat(paths, 0)  # noqa: E731
    assert (read()["state"], read()["beat"]) == ("starting", 1)
    hb.set(state="training", iteration=1)  # written at once
    assert (read()["state"], read()["iteration"], read()["beat"]) == ("training", 1, 2)
    hb.set_soon(state="waiting")  # within the gap: left to the beat thread
    assert read()["state"] == "training"
    time.sleep(2 * heartbeat.Heartbeat.MIN_GAP + 0.1)  # the pending write, then a full gap after it
    assert (read()["state"], read()["beat"]) == ("waiting", 3)
    # a change after the gap is written at once; one made moot by a write before the gap ends is not rewritten
    hb.set_soon(state="waiting", iteration=2)
    assert (read()["iteration"], read()["beat"]) == (2, 4)
    hb.set_soon(state="waiting", iteration=3)
    hb.set(state="training", iteration=4)
    time.sleep(2 * heartbeat.Heartbeat.MIN_GAP + 0.1)  # a pending write would have come by now
    assert (read()["state"], read()["iteration"], read()["beat"]) == ("training", 4, 5)
    hb.stop("finished")
    assert (read()["state"], read()["beat"]) == ("finished", 6)


def test_barrier_lists_again_after_a_stale_verdict(tmp_path):
    """A member that deposits and then stops between two polls is not left out."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    deposit(paths, 1, 0, 1.0)
    deposit(paths, 1, 1, 2.0)

    class LateThenStopped(heartbeat.Liveness):
        def stale(self, m):
            if not os.path.exists(paths.deposit_json(1, 2)):
                deposit(paths, 1, 2, 9.0)
            return f"member {m} stopped"

    res = barrier.barrier(paths, 1, cfg, 0, like_agent(paths), quorum=2, timeout=30,
                       liveness=LateThenStopped(paths, 60))
    assert res.selection["member"] == 2 and res.selection["skipped"] == []
    assert res.selection["quorum_reason"] == "complete"


def test_the_member_that_sees_every_deposit_selects_the_others_wait_on_the_decision(tmp_path):
    """Member 0 deposits first and waits; member 1 deposits last, lists once, sees both and
    selects; member 0 adopts that decision having listed the directory only on its slow timer."""

    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0)
    listings = []
    real_listdir = fsutil.listdir

    def counting_listdir(path, root=None):
        if threading.current_thread().name == "member-0":
            listings.append(path)
        return real_listdir(path, root)

    out = {}

    def member0():
        out[0] = barrier.barrier(paths, 1, cfg, 0, like_agent(paths), quorum=2, timeout=30,
                              liveness=heartbeat.Liveness(paths, 60), poll_max=0.01)

    fsutil.listdir = counting_listdir
    try:
        t = threading.Thread(target=member0, name="member-0")
        t.start()
        time.sleep(0.6)  # member 0 polls the decision ~60 times meanwhile
        deposit(paths, 1, 1, 2.0)
        out[1] = barrier.barrier(paths, 1, cfg, 1, like_agent(paths), quorum=2, timeout=30,
                              liveness=heartbeat.Liveness(paths, 60), poll_max=0.01)
        t.join(10)
    finally:
        fsutil.listdir = real_listdir
    assert out[1].created and not out[0].created
    assert out[0].selection == out[1].selection and out[1].selection["member"] == 1
    # listed at 0, 0.05, 0.15, 0.35 s (gaps doubling to 1 s), perhaps at 0.75 s: never per poll
    assert 3 <= len(listings) <= 5, listings


def test_a_waiting_member_selects_when_the_last_depositor_does_not(tmp_path):
    """The last deposit appears but its writer never selects (killed, or its listing lagged): the
    waiting member's timed listing sees every deposit, waits the grace for a decision, then selects."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0)
    threading.Timer(0.3, lambda: deposit(paths, 1, 1, 2.0)).start()
    t0 = time.monotonic()
    res = barrier.barrier(paths, 1, cfg, 0, like_agent(paths), quorum=2, timeout=30,
                       liveness=heartbeat.Liveness(paths, 60), poll_max=0.01)
    waited = time.monotonic() - t0
    assert res.created and res.selection["member"] == 1 and res.selection["quorum_reason"] == "complete"
    # listings at 0, 0.05, 0.15, 0.35 (sees both), + grace 0.05: about 0.4 s; far below the 30 s timeout
    # even on a loaded machine, where a listing can come a few tenths of a second late
    assert 0.35 <= waited < 2.0, waited


def test_waiting_members_stagger_their_grace_so_one_selects_for_a_silent_last_depositor(tmp_path, monkeypatch):
    """Two members wait; the third deposit appears but its writer never decides. Member 0 decides
    after one grace, member 1 (two graces) finds that decision at its next poll: one selection, not
    one per waiting member (each reads N files)."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    deposit(paths, 1, 0, 1.0)
    deposit(paths, 1, 1, 3.0)
    calls = []
    real_select = pool.select
    monkeypatch.setattr(pool, "select", lambda *a, **kw: calls.append(a[1]) or real_select(*a, **kw))
    threading.Timer(0.3, lambda: deposit(paths, 1, 2, 2.0)).start()
    results = {}

    def wait(m):
        results[m] = barrier.barrier(paths, 1, cfg, m, like_agent(paths), quorum=3, timeout=30,
                                  liveness=heartbeat.Liveness(paths, 60), poll_max=0.01)

    threads = [threading.Thread(target=wait, args=(m,)) for m in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(calls) == 1, calls
    assert results[0].created and not results[1].created
    assert results[0].selection == results[1].selection and results[1].selection["member"] == 1


def test_a_held_directory_is_walked_to_once_and_reads_below_it_stay_bounded(tmp_path):
    """Under a hold, each read or listing opens the held directory afresh ("." relative to it: one
    open, which on NFS revalidates the directory) instead of walking pool/iterations/000001 again."""
    paths, _ = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0)
    d = paths.iteration(1)
    os.symlink("/dev/zero", os.path.join(d, "member-001.json"))
    opened = []
    real_open = os.open

    def counting_open(path, flags, *a, **kw):
        if flags & os.O_DIRECTORY:
            opened.append(path)
        return real_open(path, flags, *a, **kw)

    os.open = counting_open
    try:
        with paths.holding(d):
            assert len(opened) == 3  # pool, iterations, 000001: once
            for _ in range(5):
                assert deposits.read_metrics(paths, 1, 0)["eval_return"] == 1.0
                with pytest.raises(ValueError, match="refused"):
                    deposits.read_metrics(paths, 1, 1)
            assert opened[3:] == ["."] * 10
            for _ in range(3):  # listings from the held directory: each complete
                assert deposits.present(paths, 1, 2) == {0, 1}  # by name; selection then skips the link
            assert opened[3:] == ["."] * 13
            assert deposits.read_selected(paths, 1) is None  # the decision poll: one open, one lookup
            assert opened[3:] == ["."] * 14
        held_reads = len(opened)
        deposits.read_metrics(paths, 1, 0)
        assert len(opened) == held_reads + 3  # walked from the root again
    finally:
        os.open = real_open
    assert paths.root.held() == {}
    # a copy of the root (a spawned process's) holds nothing of this one's
    copy = pickle.loads(pickle.dumps(paths.root))
    assert copy == paths.root and isinstance(copy, fsutil.Root) and copy.held() == {}


def test_parent_competes_and_keeps_the_pool_from_losing_ground(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    assert cfg.selection == "parent"
    start = deposits.read_selected(paths, 0)
    # every branch is worse than the agent they started from, re-scored on the same episodes
    for m, r in enumerate([4.0, 6.0, 5.0]):
        deposit(paths, 1, m, r, parent=9.0)
    sel = _decide(paths, cfg, 1, {0, 1, 2})
    assert (sel["winner"], sel["member"], sel["eval_return"]) == ("parent", None, 9.0)
    assert sel["agent_sha256"] == start["agent_sha256"]
    assert sel["best_branch"] == {"member": 1, "eval_return": 6.0, "score": 6.0}
    assert deposits.load_selected_agent(paths, 1).to_bytes() == deposits.load_selected_agent(paths, 0).to_bytes()
    # a branch that ties with the parent has not lost ground: it wins (then lowest member among tied branches)
    for m, r in enumerate([9.0, 9.0, 1.0]):
        deposit(paths, 2, m, r, seed=10 + m, parent=9.0)
    sel = _decide(paths, cfg, 2, {0, 1, 2})
    assert (sel["winner"], sel["member"]) == ("branch", 0)
    assert sel["parent"] == {"iteration": 1, "member": None, "agent_sha256": start["agent_sha256"],
                             "eval_return": 9.0, "score": 9.0}


def test_parent_score_needs_the_right_parent_and_the_parent_rule(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    # member 0 reports a score for some other agent: not the parent's; member 1's counts
    deposit(paths, 1, 0, 3.0, parent=100.0, parent_sha="0" * 64)
    deposit(paths, 1, 1, 2.0, parent=5.0)
    sel = pool.select(paths, 1, cfg, like_agent(paths), {0, 1}, "complete", deposits.read_selected(paths, 0))
    assert sel["winner"] == "parent" and sel["eval_return"] == 5.0
    # the old rule (branches only) ignores the parent
    paths2, cfg2 = make_pool(tmp_path / "q", pool_size=2, selection="branches")
    deposit(paths2, 1, 0, 3.0, parent=100.0)
    deposit(paths2, 1, 1, 2.0, parent=100.0)
    sel2 = pool.select(paths2, 1, cfg2, like_agent(paths2), {0, 1}, "complete", deposits.read_selected(paths2, 0))
    assert (sel2["winner"], sel2["member"]) == ("branch", 0)


def test_three_members_in_turn_re_score_the_parent():
    for n in range(1, 40):
        counts = collections.Counter()
        for i in range(1, 3 * n + 1):
            scorers = [m for m in range(n) if selection.scores_parent(i, m, n)]
            if n <= 3:
                assert scorers == list(range(n))
                continue
            # members i, i + n//3, i + 2n//3 (mod n): spread, so that a block of n//3 consecutive
            # members (one node of an array job) never holds two of them
            step = n // 3
            assert sorted(scorers) == sorted((i + k * step) % n for k in range(3))
            for start in range(n):
                assert len({(start + j) % n for j in range(step)} & set(scorers)) <= 1
            counts.update(scorers)
        if n > 3:
            assert set(counts.values()) == {9}  # each member takes its turn equally: 3 times every n iterations


def test_without_any_report_of_the_parent_the_best_branch_wins(tmp_path):
    """No deposit reports the parent's score (members 1 and 2, due to re-score it, are missing;
    member 3, also due, reports nothing): the selection is the branches' (as with --selection
    branches), and a later report from any member counts again."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=5)
    for m, r in ((3, 4.0), (4, 6.0)):
        deposit(paths, 1, m, r)
    sel = _decide(paths, cfg, 1, {3, 4})
    assert (sel["winner"], sel["member"], sel["parent"]["eval_return"]) == ("branch", 4, None)
    deposit(paths, 2, 3, 1.0)
    deposit(paths, 2, 4, 2.0, parent=7.0)
    sel = _decide(paths, cfg, 2, {3, 4})
    assert (sel["winner"], sel["eval_return"]) == ("parent", 7.0)


def test_selection_is_a_pure_function_of_the_files(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3)
    for m, r in [(2, 4.0), (0, 7.0), (1, 7.5)]:  # written in another order than member order
        deposit(paths, 1, m, r, parent=7.2)
    prev = deposits.read_selected(paths, 0)
    picks = []
    for _ in range(3):
        deposits._parsed.clear()  # each pick reads and parses the files anew, none from the agent cache
        picks.append(pool.select(paths, 1, cfg, like_agent(paths), {0, 1, 2}, "complete", prev))
    assert picks[0] == picks[1] == picks[2] and picks[0]["member"] == 1


def test_revert_to_the_best_after_k_iterations_without_improvement(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=1, selection="branches", revert_after=2)
    sels = {}
    for i, r in [(1, 5.0), (2, 8.0), (3, 6.0), (4, 7.0), (5, 3.0), (6, 9.0)]:
        deposit(paths, i, 0, r, seed=i)
        sels[i] = _decide(paths, cfg, i, {0})
    assert [sels[i]["winner"] for i in range(1, 7)] == ["branch", "branch", "branch", "revert", "branch", "branch"]
    assert [sels[i]["since_best"] for i in range(1, 7)] == [0, 0, 1, 0, 1, 0]
    assert sels[4]["reverted_to"] == 2 and sels[4]["eval_return"] == 8.0
    assert sels[4]["instead"] == {"winner": "branch", "member": 0, "eval_return": 7.0, "score": 7.0}
    assert deposits.load_selected_agent(paths, 4).to_bytes() == agent(2).to_bytes()
    assert sels[6]["best"]["iteration"] == 6


@pytest.mark.parametrize("best_score", ["first", "mean"])
def test_best_score_mean_lets_a_lucky_first_score_wear_off(tmp_path, best_score):
    """With ``--best-score mean`` the best ranks by the mean of its first score and its re-scores
    as the parent: iteration 1's agent scored 10 once, then 7 twice as the parent (mean 8), so
    iteration 3's 8.2 takes its place and the revert goes back to iteration 3's agent. By first
    scores iteration 1's agent stays the best and the revert goes back to it."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=1, revert_after=3, best_score=best_score)
    sels = {}
    for i, (branch, parent) in enumerate([(10.0, 1.0), (6.0, 7.0), (8.2, 7.0), (5.0, 8.0), (7.0, 7.0),
                                          (4.0, 5.0), (3.0, 7.9)], start=1):
        deposit(paths, i, 0, branch, seed=i, parent=parent)
        sels[i] = _decide(paths, cfg, i, {0})
    if best_score == "first":
        assert [sels[i]["winner"] for i in range(1, 5)] == ["branch", "parent", "branch", "revert"]
        assert [sels[i]["best"]["iteration"] for i in range(1, 5)] == [1, 1, 1, 1]
        assert sels[4]["reverted_to"] == 1 and "mean_score" not in sels[4]["best"]
        return
    assert [sels[i]["winner"] for i in range(1, 8)] == ["branch", "parent", "branch", "parent", "branch", "revert",
                                                        "parent"]
    assert sels[2]["best"] == {"iteration": 1, "eval_return": 10.0, "score": 10.0, "scores": 2, "score_sum": 17.0,
                               "mean_score": 8.5, "agent": sels[1]["agent"], "agent_sha256": sels[1]["agent_sha256"]}
    assert (sels[3]["best"]["iteration"], sels[3]["best"]["scores"], sels[3]["since_best"]) == (3, 1, 0)
    # the new best re-scored as the parent: 8.0, then 7.0; iteration 5's 7.0 ties the parent (a branch
    # that ties wins) but not the best's mean
    assert sels[4]["best"]["mean_score"] == pytest.approx(8.1)
    assert sels[5]["best"]["mean_score"] == pytest.approx(23.2 / 3) and sels[5]["since_best"] == 2
    assert (sels[6]["reverted_to"], sels[6]["eval_return"], sels[6]["since_best"]) == (3, 8.2, 0)
    assert deposits.load_selected_agent(paths, 6).to_bytes() == agent(3).to_bytes()
    # reverted to, it is the parent again and its re-score counts
    assert sels[7]["best"]["scores"] == 4 and sels[7]["best"]["mean_score"] == pytest.approx(31.1 / 4)


def test_best_score_mean_ignores_a_re_score_whose_sum_is_not_finite():
    prev = {"iteration": 5, "agent": "x", "agent_sha256": "b", "since_best": 1,
            "best": {"iteration": 4, "eval_return": 1.0, "score": 1.7e308, "agent": "x", "agent_sha256": "b",
                     "scores": 1, "score_sum": 1.7e308, "mean_score": 1.7e308}}
    out = {"iteration": 6, "parent": {"agent_sha256": "b", "score": 1.7e308}, "score": 5.0, "eval_return": 5.0,
           "agent": "y", "agent_sha256": "c", "winner": "branch", "member": 0}
    sel = selection.track_best(out, prev, 0, mean=True)
    assert sel["best"] == prev["best"] and fsutil.dumps(sel)  # still writable JSON


def test_best_score_mean_with_branches_re_scores_only_a_best(tmp_path):
    """Branches only: members re-score the parent when it is the best (just made the best, or
    reverted to); the re-score counts towards the best's mean and never competes."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=1, selection="branches", revert_after=2, best_score="mean")
    sels = {0: deposits.read_selected(paths, 0)}
    # (branch, the parent's re-score as reported; only a best's is read)
    for i, (branch, parent) in enumerate([(10.0, 1.0), (6.0, 7.0), (8.6, 100.0), (5.0, 6.0), (7.0, 100.0),
                                          (3.0, 8.0)], start=1):
        deposit(paths, i, 0, branch, seed=i, parent=parent)
        sels[i] = _decide(paths, cfg, i, {0})
    assert [selection.rescores_parent(cfg, sels[i]) for i in range(6)] == [False, True, False, True, False, True]
    assert [sels[i]["winner"] for i in range(1, 7)] == ["branch", "branch", "branch", "branch", "revert", "branch"]
    assert sels[2]["parent"]["eval_return"] == 7.0 and sels[2]["member"] == 0  # 7 > 6, yet no competition
    assert (sels[2]["best"]["scores"], sels[2]["best"]["mean_score"]) == (2, 8.5)
    assert sels[3]["parent"]["eval_return"] is None and sels[3]["best"]["iteration"] == 3  # 8.6 > 8.5
    assert sels[4]["best"]["mean_score"] == pytest.approx(7.3)
    assert sels[5]["reverted_to"] == 3  # 7.0 < 7.3, two iterations after the best
    assert sels[6]["best"]["scores"] == 3 and sels[6]["best"]["mean_score"] == pytest.approx(22.6 / 3)
    # the default ranks by first scores: no re-scores read with branches only
    paths2, cfg2 = make_pool(tmp_path / "q", pool_size=1, selection="branches", revert_after=2)
    deposit(paths2, 1, 0, 10.0, seed=1, parent=1.0)
    first = _decide(paths2, cfg2, 1, {0})
    assert not selection.rescores_parent(cfg2, first) and "mean_score" not in first["best"]


def test_with_a_reward_shift_selection_compares_the_training_objective(tmp_path):
    """Shifted pools train on r - c per step, so branches and parent compete on that score;
    eval_return keeps the env's own return."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=2, reward_shift=1.0)

    def dep(m, ret, score, parent_ret, parent_score, seed):
        prev = deposits.read_selected(paths, 1 if seed > 9 else 0)
        deposits.deposit(paths, 2 if seed > 9 else 1, m, agent(seed),
                     {"eval_return": ret, "eval_score": score, "parent_eval_return": parent_ret,
                      "parent_eval_score": parent_score, "parent_sha256": prev["agent_sha256"]})

    # member 0 lives longer (higher env return), member 1 moves better (higher shifted score)
    dep(0, 900.0, 50.0, 300.0, 20.0, seed=1)
    dep(1, 600.0, 80.0, 300.0, 20.0, seed=2)
    sel = _decide(paths, cfg, 1, {0, 1})
    assert (sel["winner"], sel["member"], sel["eval_return"], sel["score"]) == ("branch", 1, 600.0, 80.0)
    # the parent's shifted score beats both branches: it stays, with its env return recorded
    dep(0, 700.0, 60.0, 650.0, 95.0, seed=11)
    dep(1, 500.0, 70.0, 650.0, 95.0, seed=12)
    sel = _decide(paths, cfg, 2, {0, 1})
    assert (sel["winner"], sel["eval_return"], sel["score"]) == ("parent", 650.0, 95.0)
    # a deposit without a finite shifted score is skipped with its reason
    paths3, cfg3 = make_pool(tmp_path / "q", pool_size=2, reward_shift=1.0)
    deposits.deposit(paths3, 1, 0, agent(1), {"eval_return": 5.0})
    sel = pool.select(paths3, 1, cfg3, like_agent(paths3), {0}, "timeout", deposits.read_selected(paths3, 0))
    assert sel["winner"] == "carried" and "eval_score" in sel["skipped"][0]["reason"]


def test_read_only_commands_read_older_pools_members_refuse_them(tmp_path):
    paths, _cfg = make_pool(tmp_path / "p", pool_size=1)
    doc = json.loads(open(paths.pool_json).read())
    older = layout.Paths(tmp_path / "old")
    os.makedirs(older.root)
    open(older.pool_json, "w").write(json.dumps(doc | {"protocol": 2}))  # a protocol-2 pool: plain file
    assert pool.read_config(older, readonly=True).pool_size == 1
    with pytest.raises(UsageError, match="pool protocol 2, this one speaks 3"):
        pool.read_config(older)
    with pytest.raises(UsageError, match="another rl-pool version"):
        pool.open_pool(older, {}, fake_initial)


def test_selection_reads_n_metrics_and_only_the_winners_agent(tmp_path, monkeypatch):
    n = 8
    paths, cfg = make_pool(tmp_path / "p", pool_size=n)
    for m in range(n):
        deposit(paths, 1, m, float(m), parent=-1.0)
    # the best deposit's agent is broken: skipped with its reason, the next best wins
    open(paths.deposit_npz(1, n - 1), "wb").write(b"not an agent")
    # a lower-ranked broken agent is never read, so it cannot cost anything
    open(paths.deposit_npz(1, 0), "wb").write(b"not an agent either")
    like = like_agent(paths)
    opened = []
    real = fsutil.open_regular
    monkeypatch.setattr(fsutil, "open_regular", lambda path, *a, **k: opened.append(path) or real(path, *a, **k))
    sel = pool.select(paths, 1, cfg, like, set(range(n)), "complete", deposits.read_selected(paths, 0))
    assert (sel["winner"], sel["member"]) == ("branch", n - 2)
    assert sel["skipped"] == [{"member": n - 1, "reason": "agent does not match the hash in its metrics"}]
    assert [c["member"] for c in sel["considered"]] == list(range(n - 1))
    agents = [p for p in opened if p.endswith(".npz")]
    assert sorted(agents) == [paths.deposit_npz(1, n - 2), paths.deposit_npz(1, n - 1)]
    assert len(opened) <= n + 3


def test_pools_made_before_init_shape_still_read_and_it_shapes_the_initial_agent():
    from rl_pool.commands.member import make_initial
    from rl_pool.config import PoolConfig

    cfg = PoolConfig(env="Swimmer-v5", pool_size=2).validate()
    saved = cfg.to_json()
    del saved["init_shape"]  # a pool.json written before the option existed
    assert PoolConfig.from_json(saved) == cfg
    del saved["seed"]
    with pytest.raises(ValueError, match="missing seed"):
        PoolConfig.from_json(saved)
    with pytest.raises(UsageError, match="--init-shape"):
        PoolConfig(init_shape=0.5).validate()
    agent, _ = make_initial(PoolConfig(env="Swimmer-v5", init_shape=6.0).validate())
    x = np.zeros((1, agent.meta.obs_dim))
    alpha, beta = policy.beta_params(agent.params, x, agent.spec)
    np.testing.assert_allclose(alpha, 6.0)
    np.testing.assert_allclose(beta, 6.0)
    default, _ = make_initial(PoolConfig(env="Swimmer-v5").validate())
    assert default.to_bytes() != agent.to_bytes()


def test_paired_margin_against_numpy():
    rng = np.random.default_rng(3)
    b, p = rng.normal(5, 2, 7), rng.normal(4, 2, 7)
    mean, se = selection.paired_margin(list(b), list(p))
    d = b - p
    assert mean == pytest.approx(d.mean(), rel=1e-12)
    assert se == pytest.approx(d.std(ddof=1) / np.sqrt(len(d)), rel=1e-12)
    assert selection.paired_margin([3.0], [1.0]) == (2.0, 0.0)  # one episode: no spread to measure


def _margin_deposit(paths, i, m, branch_eps, parent_eps, seed, lengths=None, parent_lengths=None):
    prev = deposits.read_selected(paths, i - 1)
    lengths = lengths or [60] * len(branch_eps)
    parent_lengths = parent_lengths or [60] * len(parent_eps)
    doc = {"eval_return": float(np.mean(branch_eps)), "eval_returns": branch_eps, "eval_lengths": lengths,
           "eval_score": float(np.mean(np.subtract(branch_eps, lengths))),
           "parent_eval_return": float(np.mean(parent_eps)), "parent_eval_returns": parent_eps,
           "parent_eval_lengths": parent_lengths,
           "parent_eval_score": float(np.mean(np.subtract(parent_eps, parent_lengths))),
           "parent_sha256": prev["agent_sha256"]}
    deposits.deposit(paths, i, m, agent(seed), doc)


def test_with_a_selection_margin_a_branch_must_beat_the_parent_by_k_paired_standard_errors(tmp_path):
    parent = [10.0, 20.0, 30.0, 40.0]
    lucky = [30.0, 5.0, 45.0, 35.0]   # mean +3.75 over the parent, but se 7.2 of the differences
    steady = [11.0, 21.5, 31.0, 41.0]  # mean +1.125, se 0.125: better on every episode
    worse = [9.0, 19.0, 29.0, 39.0]
    for k, members, want in [(0, {0, 1}, ("branch", 0)),   # k = 0: today's rule, the best mean wins
                             (1, {0, 1}, ("branch", 1)),   # the steady gain clears 1 se, the lucky one not
                             (1, {0}, ("parent", None)),   # only the lucky branch: the parent stays
                             (9, {0, 1}, ("branch", 1)),   # +1.125 >= 9 x 0.125
                             (10, {0, 1}, ("parent", None))]:
        paths, cfg = make_pool(tmp_path / f"k{k}-{len(members)}", pool_size=2, selection_margin=k, eval_episodes=4)
        _margin_deposit(paths, 1, 0, lucky, parent, seed=1)
        _margin_deposit(paths, 1, 1, steady, parent, seed=2)
        sel = _decide(paths, cfg, 1, members)
        assert (sel["winner"], sel["member"]) == want, (k, members)
        if k:
            assert sel["margin"] == k
            diffs = {c["member"]: (c["diff"], c["se"]) for c in sel["considered"]}
            assert diffs[0] == pytest.approx((3.75, np.std([20, -15, 15, -5], ddof=1) / 2))
            if 1 in members:
                assert diffs[1] == pytest.approx((1.125, 0.125))
        else:
            assert "margin" not in sel and "diff" not in sel["considered"][0]
        if want[0] == "parent":  # the best-scoring branch is recorded, with its margin
            assert sel["best_branch"]["member"] == 0 and sel["best_branch"]["diff"] == pytest.approx(3.75)
    # a branch worse on every episode never clears a margin; equal to the parent (se 0) it does
    paths, cfg = make_pool(tmp_path / "w", pool_size=2, selection_margin=2, eval_episodes=4)
    _margin_deposit(paths, 1, 0, worse, parent, seed=1)
    _margin_deposit(paths, 1, 1, list(parent), parent, seed=2)
    sel = _decide(paths, cfg, 1, {0, 1})
    assert (sel["winner"], sel["member"]) == ("branch", 1)


def test_a_selection_margin_uses_shifted_episode_scores_and_needs_whole_episode_reports(tmp_path):
    paths, cfg = make_pool(tmp_path / "s", pool_size=2, selection_margin=1, reward_shift=1.0)
    parent, plens = [100.0, 100.0, 100.0], [30, 30, 30]  # scores 70 each
    # member 0 lives longer (returns +20 per episode) but its shifted scores are ~10 lower: no
    _margin_deposit(paths, 1, 0, [120.0, 121.0, 120.0], parent, seed=1, lengths=[60, 60, 60], parent_lengths=plens)
    # member 1 moves better in the same time: +30 per episode
    _margin_deposit(paths, 1, 1, [130.0, 131.0, 130.0], parent, seed=2, lengths=[30, 30, 30], parent_lengths=plens)
    doc = deposits.read_metrics(paths, 1, 1)
    assert selection.episode_scores(doc, 3, 1.0, 60) == [100.0, 101.0, 100.0]
    assert selection.episode_scores(doc, 3, 0.0, 60) == [130.0, 131.0, 130.0]
    assert selection.episode_scores(doc, 3, 1.0, 60, "parent_") == [70.0, 70.0, 70.0]
    assert selection.episode_scores(doc | {"eval_lengths": None}, 3, 1.0, 60) is None  # lengths needed with a shift
    assert selection.episode_scores(doc | {"eval_lengths": [30, 30, 61]}, 3, 1.0, 60) is None  # longer than an episode
    assert selection.episode_scores(doc | {"eval_returns": [1.0, float("nan"), 2.0]}, 3, 0.0, 60) is None
    assert selection.episode_scores(doc, 4, 0.0, 60) is None  # not the pool's number of episodes
    sel = _decide(paths, cfg, 1, {0, 1})
    assert (sel["winner"], sel["member"]) == ("branch", 1)
    assert [c["diff"] for c in sel["considered"]] == pytest.approx([-29 / 3, 30 + 1 / 3])
    # without the parent's episodes (deposits from before the margin): plain means decide
    paths2, cfg2 = make_pool(tmp_path / "old", pool_size=2, selection_margin=5)
    deposit(paths2, 1, 0, 3.0, parent=2.0)
    deposit(paths2, 1, 1, 1.0, parent=2.0)
    sel = _decide(paths2, cfg2, 1, {0, 1})
    assert (sel["winner"], sel["member"]) == ("branch", 0) and "margin" not in sel


@pytest.mark.parametrize("garbled", [
    {"eval_returns": [10 ** 400, 1, 2]},                     # an integer no float can hold
    {"eval_returns": [1e200, -1e200, 0.0]},                  # finite, but squares overflow
    {"eval_returns": [1.7e308, -1.7e308, 1.0]},
    {"eval_returns": ["1", 2, 3]}, {"eval_returns": {"a": 1}}, {"eval_returns": [True, 1, 2]},
    {"eval_lengths": [10 ** 400, 1, 2]}, {"eval_lengths": [-1, 1, 2]}, {"eval_lengths": [1.5, 1, 2]},
    {"parent_eval_returns": [1e308, 1e308, 1e308]}, {"parent_eval_lengths": "x"},
])
def test_a_garbled_episode_report_cannot_break_a_margin_selection(tmp_path, garbled):
    """Every member computes the same selection: a report that makes one raise would stop the pool."""
    paths, cfg = make_pool(tmp_path / "g", pool_size=2, selection_margin=1, reward_shift=0.5)
    parent = [10.0, 20.0, 30.0]
    _margin_deposit(paths, 1, 1, [11.0, 21.0, 31.0], parent, seed=2, lengths=[5, 5, 5], parent_lengths=[5, 5, 5])
    prev = deposits.read_selected(paths, 0)
    doc = {"eval_return": 1000.0, "eval_score": 1000.0, "eval_returns": [1000.0] * 3, "eval_lengths": [5] * 3,
           "parent_eval_return": 20.0, "parent_eval_score": 17.5, "parent_eval_returns": parent,
           "parent_eval_lengths": [5] * 3, "parent_sha256": prev["agent_sha256"]} | garbled
    deposits.deposit(paths, 1, 0, agent(1), doc)  # member 0 reports the parent first: its report counts
    sel = _decide(paths, cfg, 1, {0, 1})
    assert sel["winner"] in ("branch", "parent") and sel["margin"] == 1
    if "parent_eval_returns" in garbled or "parent_eval_lengths" in garbled:
        # member 1's report of the parent counts instead; member 0's own episodes are fine
        assert (sel["winner"], sel["member"]) == ("branch", 0)
        assert sel["considered"][0]["diff"] == pytest.approx(980.0)
    else:
        assert (sel["winner"], sel["member"]) == ("branch", 1)  # member 0 cannot clear the margin
        assert sel["considered"][0]["diff"] is None
    json.loads(open(paths.selected(1)).read())  # written, strict JSON


def test_the_selector_parses_the_winners_agent_once_and_shared_agents_are_read_only(tmp_path, monkeypatch):
    from rl_pool.maths.agent import Agent

    paths, cfg = make_pool(tmp_path / "p", pool_size=2)
    deposit(paths, 1, 0, 1.0, seed=11)
    deposit(paths, 1, 1, 2.0, seed=12)
    like = like_agent(paths)
    parsed = []
    monkeypatch.setattr(deposits, "_parsed", collections.OrderedDict())  # whatever earlier tests parsed
    real = Agent.from_bytes.__func__
    monkeypatch.setattr(Agent, "from_bytes", classmethod(lambda cls, data, source="agent":
                                                            parsed.append(source) or real(cls, data, source)))
    sel = pool.select(paths, 1, cfg, like, {0, 1}, "complete", deposits.read_selected(paths, 0))
    sel, _ = pool.publish_selection(paths, sel, by=0)
    trained_from = deposits.load_selected_agent(paths, 1, sel, like=like)
    assert parsed == ["member-001.npz"]  # select read it; training starts from the same parse
    assert trained_from.to_bytes() == agent(12).to_bytes()
    with pytest.raises(ValueError, match="read-only"):
        next(iter(trained_from.params.values()))[...] = 0.0
    # other bytes are parsed on their own, whatever the name
    deposit(paths, 2, 0, 5.0, seed=13)
    sel2 = pool.select(paths, 2, cfg, like, {0}, "complete", sel)
    sel2, _ = pool.publish_selection(paths, sel2, by=0)
    assert deposits.load_selected_agent(paths, 2, sel2).to_bytes() == agent(13).to_bytes()
    assert parsed == ["member-001.npz", "member-000.npz"]


def test_a_selection_margin_needs_the_parent_in_the_selection(tmp_path):
    from rl_pool.config import PoolConfig

    with pytest.raises(UsageError, match="needs --selection parent"):
        make_pool(tmp_path / "b", selection="branches", selection_margin=1)
    with pytest.raises(UsageError, match=">= 0"):
        PoolConfig(selection_margin=-1).validate()
    assert PoolConfig(selection_margin=2).validate().selection_margin == 2


def test_a_restart_publishes_the_plain_copy_a_decision_lacks(tmp_path):
    """A winner stopped (or found the disk full) between deciding and publishing ``selected.json``:
    members decide from the decision and would never write the copy; a restart writes it with the
    decided bytes, leaves an existing copy alone and writes nothing for an undecided iteration."""
    paths, cfg = make_pool(tmp_path / "p", pool_size=1)
    deposit(paths, 1, 0, 1.0)
    doc = _decide(paths, cfg, 1, [0])
    decided = paths.decision(paths.selected(1))
    os.unlink(paths.selected(1))
    deposits.make_iteration_dir(paths, 2)
    pool.publish_missing_selections(paths, [1, 2])
    with open(paths.selected(1), "rb") as fh:
        assert fh.read() == decided
    assert json.loads(decided)["agent_sha256"] == doc["agent_sha256"]
    assert not os.path.lexists(paths.selected(2))
    with open(paths.selected(1), "w") as fh:
        fh.write("left alone")
    pool.publish_missing_selections(paths, [1])
    with open(paths.selected(1)) as fh:
        assert fh.read() == "left alone"
