"""The merge: its maths against plain references, the rule as a table of cases, and the store's
part (every member computes the same bytes; a deposit that fails its checks has no weight)."""

import itertools
import json
import multiprocessing
import os
import shutil

import numpy as np
import pytest

from rl_pool import fsutil
from rl_pool.config import PoolConfig
from rl_pool.errors import UsageError
from rl_pool.maths import merge, normalizer
from rl_pool.maths.agent import Agent, AgentMeta
from rl_pool.maths.normalizer import NormState
from rl_pool.protocol import deposits, layout, pool, selection

from .helpers import agent, make_pool

P = "p" * 64


# ---------------------------------------------------------------- maths
def test_weighted_update_matches_a_plain_loop():
    rng = np.random.default_rng(0)
    parent = {"w": rng.normal(size=(3, 4)), "b": rng.normal(size=5)}
    branches = [{k: v + rng.normal(size=v.shape) for k, v in parent.items()} for _ in range(3)]
    weights, scale = [0.5, 1 / 3, 1 / 6], 3.0
    got = merge.weighted_update(parent, branches, weights, scale)
    for name, p in parent.items():
        flat = p.ravel()
        want = []
        for j in range(flat.size):
            step = sum(w * (float(b[name].ravel()[j]) - float(flat[j])) for b, w in zip(branches, weights))
            want.append(float(flat[j]) + scale * step)
        np.testing.assert_allclose(got[name].ravel(), want, rtol=1e-12, atol=1e-12)


def test_one_branch_with_weight_one_and_scale_one_is_that_branch():
    rng = np.random.default_rng(1)
    parent = {"w": rng.normal(size=(2, 3))}
    branch = {"w": rng.normal(size=(2, 3))}
    np.testing.assert_allclose(merge.weighted_update(parent, [branch], [1.0], 1.0)["w"], branch["w"], rtol=1e-12)


def test_pooled_statistics_are_those_of_every_observation():
    """Each branch's statistics are the parent's plus its own batches (as training makes them);
    pooled, they must equal the mean and variance of all the observations together."""
    rng = np.random.default_rng(2)
    seen = rng.normal(3.0, 2.0, size=(500, 4))
    parent = normalizer.update(normalizer.init(4), seen)
    own = [rng.normal(float(k), 1.0 + k, size=(200 + 50 * k, 4)) for k in range(3)]
    branches = []
    for data in own:
        s = parent
        for part in np.array_split(data, 4):  # several gradient steps' batches
            s = normalizer.update(s, part)
        branches.append(s)
    pooled = merge.pooled_statistics(parent, branches)
    everything = np.concatenate([seen, *own])
    assert pooled.count == len(everything)
    np.testing.assert_allclose(pooled.mean, everything.mean(axis=0), rtol=1e-10)
    np.testing.assert_allclose(pooled.m2 / pooled.count, everything.var(axis=0), rtol=1e-9)


def test_a_branch_that_added_nothing_adds_nothing():
    parent = NormState(10.0, np.ones(2), np.full(2, 3.0))
    pooled = merge.pooled_statistics(parent, [parent, parent])
    assert pooled.count == 10.0
    np.testing.assert_array_equal(pooled.mean, parent.mean)


def test_merged_agent_moments_are_the_weighted_mean():
    parent = agent(0)
    a, b = agent(1), agent(2)
    a = a.evolve(opt_m={k: np.full_like(v, 1.0) for k, v in a.params.items()}, opt_t=4.0)
    b = b.evolve(opt_m={k: np.full_like(v, 4.0) for k, v in b.params.items()}, opt_t=4.0)
    m = merge.merge_agents(parent, [a, b], [2 / 3, 1 / 3], 2.0, [a, b])
    assert m.opt_t == 4.0
    np.testing.assert_allclose(m.opt_m["w"], 2.0)
    np.testing.assert_allclose(m.params["w"], parent.params["w"] + 2.0 * (
        2 / 3 * (a.params["w"] - parent.params["w"]) + 1 / 3 * (b.params["w"] - parent.params["w"])))


def test_momentum_matches_a_plain_loop():
    rng = np.random.default_rng(3)
    before = {"w": rng.normal(size=(2, 3)), "b": rng.normal(size=4)}
    parent = {k: v + rng.normal(size=v.shape) for k, v in before.items()}
    merged = {k: v + rng.normal(size=v.shape) for k, v in parent.items()}
    got = merge.with_momentum(merged, parent, before, 0.5)
    for name in parent:
        want = [float(m) + 0.5 * (float(p) - float(b)) for m, p, b in
                zip(merged[name].ravel(), parent[name].ravel(), before[name].ravel())]
        np.testing.assert_allclose(got[name].ravel(), want, rtol=1e-12, atol=1e-12)


def test_a_merge_with_momentum_adds_beta_times_the_pools_last_step():
    before, parent, a, b = agent(0), agent(1), agent(2), agent(3)
    plain = merge.merge_agents(parent, [a, b], [2 / 3, 1 / 3], 1.0, [a, b])
    moved = merge.merge_agents(parent, [a, b], [2 / 3, 1 / 3], 1.0, [a, b], momentum=(0.25, before))
    for name in parent.params:
        np.testing.assert_allclose(moved.params[name], plain.params[name] + 0.25 * (
            parent.params[name] - before.params[name]), rtol=1e-12, atol=1e-12)
    # only the parameters: statistics and Adam moments are the merge's own
    np.testing.assert_array_equal(moved.norm.mean, plain.norm.mean)
    np.testing.assert_array_equal(moved.opt_m["w"], plain.opt_m["w"])


@pytest.mark.parametrize("k", [1, 2, 3, 7, 16])
def test_rank_weights_fall_with_rank_and_sum_to_one(k):
    w = selection.merge_weights(k)
    assert len(w) == k and abs(sum(w) - 1.0) < 1e-12
    assert all(a > b for a, b in itertools.pairwise(w))
    assert selection.merge_scale("sum", k) == k and selection.merge_scale("mean", k) == 1.0


# ---------------------------------------------------------------- the rule, as a table
def _cfg(merge_kind="sum", n=4, **kw):
    return PoolConfig(pool_size=n, merge=merge_kind, max_episode_steps=100, **kw).validate()


def _report(m, ret, parent=None, fallback=None, fb_sha="f" * 64):
    doc = {"iteration": 1, "member": m, "eval_return": ret, "agent_sha256": f"{m}" * 64}
    if parent is not None:
        doc |= {"parent_eval_return": parent, "parent_sha256": P}
    if fallback is not None:
        doc |= {"fallback_eval_return": fallback, "fallback_sha256": fb_sha}
    return doc


PREVIOUS = {"iteration": 0, "member": None, "agent": "iterations/000000/initial.npz", "agent_sha256": P}
AFTER_MERGE = PREVIOUS | {"winner": "merge", "next_fallback": {
    "agent": "iterations/000000/member-003.npz", "agent_sha256": "f" * 64, "member": 3, "iteration": 0}}

CASES = [
    # (name, merge, selection, previous, [(member, return, parent report, fallback report)], expected)
    ("two beat the parent: merged, best first", "sum", "parent", PREVIOUS,
     [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 3.0, None, None), (3, 6.0, None, None)],
     {"winner": "merge", "members": [1, 3, 0], "weights": [0.5, 1 / 3, 1 / 6], "scale": 3.0, "needs": [0, 1, 2, 3],
      "eval_return": 7.0}),
    ("mean steps one mean update", "mean", "parent", PREVIOUS,
     [(0, 5.0, 4.0, None), (1, 7.0, None, None)],
     {"winner": "merge", "members": [1, 0], "weights": [2 / 3, 1 / 3], "scale": 1.0, "needs": [0, 1]}),
    ("one beats the parent: that branch", "sum", "parent", PREVIOUS,
     [(0, 3.0, 4.0, None), (1, 7.0, None, None), (2, 2.0, None, None)],
     {"winner": "branch", "member": 1, "needs": [1], "agent": "iterations/000001/member-001.npz"}),
    ("a tie with the parent counts as beating it", "sum", "parent", PREVIOUS,
     [(0, 4.0, 4.0, None), (1, 3.0, None, None)],
     {"winner": "branch", "member": 0, "needs": [0]}),
    ("none beats the parent: it stays", "sum", "parent", PREVIOUS,
     [(0, 3.0, 4.0, None), (1, 2.0, None, None)],
     {"winner": "parent", "needs": [], "eval_return": 4.0, "agent_sha256": P}),
    ("the fallback beats the merged parent and every branch: back to it", "sum", "parent", AFTER_MERGE,
     [(0, 3.0, 4.0, 6.0), (1, 5.0, None, None)],
     {"winner": "fallback", "needs": [], "eval_return": 6.0, "agent_sha256": "f" * 64}),
    ("branches must beat the fallback too", "sum", "parent", AFTER_MERGE,
     [(0, 5.5, 4.0, 5.0), (1, 4.5, None, None), (2, 6.0, None, None)],
     {"winner": "merge", "members": [2, 0], "needs": [0, 1, 2]}),
    ("no report of the parent: the better half is merged", "sum", "parent", PREVIOUS,
     [(0, 5.0, None, None), (1, 7.0, None, None), (2, 1.0, None, None), (3, 6.0, None, None)],
     {"winner": "merge", "members": [1, 3], "scale": 2.0}),
    ("branches only: the better half", "sum", "branches", PREVIOUS,
     [(0, 5.0, 9.0, None), (1, 7.0, None, None), (2, 1.0, None, None)],
     {"winner": "merge", "members": [1, 0]}),
    ("merge none: the best branch alone, as before", "none", "parent", PREVIOUS,
     [(0, 5.0, 4.0, None), (1, 7.0, None, None)],
     {"winner": "branch", "member": 1, "needs": [1]}),
]


@pytest.mark.parametrize("name,kind,sel,previous,rows,want", CASES, ids=[c[0] for c in CASES])
def test_the_rule(name, kind, sel, previous, rows, want):
    cfg = _cfg(kind, n=4, selection=sel)
    reports = [_report(m, r, p, f) for m, r, p, f in rows]
    out, needs = selection.decide(cfg, 1, previous, reports, [], "complete")
    assert out["winner"] == want["winner"]
    assert needs == want.get("needs", needs)
    if out["winner"] == "merge":
        assert out["merge"]["members"] == want["members"]
        assert out["merge"]["statistics_from"] == [m for m, *_ in rows]
        if "weights" in want:
            assert out["merge"]["weights"] == pytest.approx(want["weights"])
        if "scale" in want:
            assert out["merge"]["scale"] == want["scale"]
        # the merge is scored next iteration; its best evaluated branch is its fallback
        top = max(rows, key=lambda r: (r[1], -r[0]))
        assert out["next_fallback"]["member"] == top[0]
        assert out["evaluated"]["agent"] == f"iterations/000001/member-{top[0]:03d}.npz"
    for key in ("member", "eval_return", "agent", "agent_sha256"):
        if key in want:
            assert out[key] == want[key]


def test_the_best_tracks_the_evaluated_agent_not_the_unscored_merge():
    cfg = _cfg("sum", n=2)
    out, _ = selection.decide(cfg, 1, PREVIOUS, [_report(0, 5.0, 4.0), _report(1, 7.0)], [], "complete")
    assert out["best"]["agent"] == "iterations/000001/member-001.npz" and out["best"]["score"] == 7.0


def test_a_revert_drops_the_merge():
    cfg = _cfg("sum", n=2, revert_after=1)
    best = {"iteration": 0, "eval_return": 99.0, "score": 99.0, "agent": "x.npz", "agent_sha256": "b" * 64}
    out, _ = selection.decide(cfg, 1, PREVIOUS | {"best": best}, [_report(0, 5.0, 4.0), _report(1, 7.0)], [],
                              "complete")
    assert out["winner"] == "revert" and "merge" not in out and "next_fallback" not in out
    assert out["agent_sha256"] == "b" * 64


# ---------------------------------------------------------------- the adaptive scale, as a table
SCALE_CASES = [
    # (name, previous, [(member, return, parent report, fallback report)], carried scale, merge scale)
    ("a pool's first merge steps one mean update", PREVIOUS,
     [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)], 1.0, 1.0),
    ("the merge beat its fallback: the scale doubles", AFTER_MERGE | {"merge_scale": 2.0},
     [(0, 5.0, 4.0, 3.0), (1, 7.0, None, None), (2, 6.0, None, None)], 4.0, 3.0),
    ("a tie with the fallback counts as holding", AFTER_MERGE | {"merge_scale": 1.0},
     [(0, 5.0, 4.0, 4.0), (1, 7.0, None, None), (2, 6.0, None, None)], 2.0, 2.0),
    ("the merge lost to its fallback: the scale halves", AFTER_MERGE | {"merge_scale": 4.0},
     [(0, 5.0, 4.0, 4.5), (1, 7.0, None, None), (2, 6.0, None, None)], 2.0, 2.0),
    ("never below the mean update", AFTER_MERGE | {"merge_scale": 1.0},
     [(0, 5.0, 4.0, 4.5), (1, 7.0, None, None), (2, 6.0, None, None)], 1.0, 1.0),
    ("never above the pool size", AFTER_MERGE | {"merge_scale": 4.0},
     [(0, 5.0, 4.0, 3.0), (1, 7.0, None, None), (2, 6.0, None, None), (3, 8.0, None, None)], 4.0, 4.0),
    ("no verdict without the fallback's re-score: it stays", AFTER_MERGE | {"merge_scale": 2.0},
     [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)], 2.0, 2.0),
    ("after a branch won there is no verdict: it stays", PREVIOUS | {"winner": "branch", "merge_scale": 2.0},
     [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)], 2.0, 2.0),
    ("a garbled carried scale starts again at 1", PREVIOUS | {"merge_scale": float("nan")},
     [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)], 1.0, 1.0),
]


@pytest.mark.parametrize("name,previous,rows,carried,scale", SCALE_CASES, ids=[c[0] for c in SCALE_CASES])
def test_the_adaptive_scale(name, previous, rows, carried, scale):
    out, _ = selection.decide(_cfg("adaptive", n=4), 1, previous, [_report(*r) for r in rows], [], "complete")
    assert out["merge_scale"] == carried
    assert out["winner"] == "merge" and out["merge"]["kind"] == "adaptive"
    # capped at the number of branches merged: those at or above the parent and the fallback
    assert out["merge"]["scale"] == scale


def test_an_adaptive_merge_needs_three_branches_at_the_bar():
    cfg = _cfg("adaptive", n=4)
    out, needs = selection.decide(cfg, 1, PREVIOUS, [_report(0, 5.0, 4.0), _report(1, 7.0), _report(2, 3.0)], [],
                                  "complete")
    assert (out["winner"], out["member"], needs) == ("branch", 1, [1])
    # mean and sum merge two
    out, _ = selection.decide(_cfg("mean", n=4), 1, PREVIOUS, [_report(0, 5.0, 4.0), _report(1, 7.0)], [],
                              "complete")
    assert out["winner"] == "merge"


@pytest.mark.parametrize("rows", [
    [(0, 5.0, 4.0), (1, 7.0, None)], [(0, 3.0, 4.0), (1, 2.0, None)], [(0, 4.0, 4.0), (1, 4.0, None)],
    [(0, 5.0, None), (1, 7.0, None)], [(0, 9.0, 4.0)]])
def test_two_members_with_the_adaptive_merge_decide_as_without_a_merge(rows):
    reports = [_report(m, r, p) for m, r, p in rows]
    plain, plain_needs = selection.decide(_cfg("none", n=2), 1, PREVIOUS, reports, [], "complete")
    adaptive, needs = selection.decide(_cfg("adaptive", n=2), 1, PREVIOUS, reports, [], "complete")
    assert adaptive.pop("merge_scale") == 1.0
    assert (adaptive, needs) == (plain, plain_needs)


@pytest.mark.parametrize("sel,parent", [("branches", 4.0), ("parent", None)])
def test_an_adaptive_pool_without_a_bar_takes_the_best_branch(sel, parent):
    """With --selection branches, or with no report of the parent's score (its scorers missing),
    nothing could judge a merge in the next iteration: the best branch wins, at any carried scale."""
    rows = [(0, 5.0, parent, None), (1, 7.0, None, None), (2, 6.0, None, None), (3, 1.0, None, None)]
    out, needs = selection.decide(_cfg("adaptive", n=4, selection=sel), 1, PREVIOUS | {"merge_scale": 4.0},
                                  [_report(*r) for r in rows], [], "complete")
    assert (out["winner"], out["member"], needs) == ("branch", 1, [1])
    assert out["merge_scale"] == 4.0 and "next_fallback" not in out


def test_the_adaptive_scale_is_carried_when_nothing_is_merged():
    previous = PREVIOUS | {"merge_scale": 4.0}
    out, _ = selection.decide(_cfg("adaptive", n=4), 1, previous, [_report(0, 3.0, 4.0), _report(1, 2.0)], [],
                              "complete")
    assert out["winner"] == "parent" and out["merge_scale"] == 4.0
    out, _ = selection.decide(_cfg("adaptive", n=4), 1, previous, [], [{"member": 0, "reason": "missing"}],
                              "quorum")
    assert out["winner"] == "carried" and out["merge_scale"] == 4.0


# ---------------------------------------------------------------- momentum, as a table
GRAND = {"iteration": 0, "member": None, "agent": "iterations/000000/initial.npz", "agent_sha256": "g" * 64}
MERGED_BEFORE = AFTER_MERGE | {"iteration": 1, "agent": "iterations/000001/merged-0123.npz", "parent": GRAND}
MOMENTUM_CASES = [
    # (name, --merge-momentum, previous, expected momentum record or None)
    ("a merge after a merge: beta times the step from the previous merge's parent", 0.5, MERGED_BEFORE,
     {"beta": 0.5, "from": {"iteration": 0, "agent": GRAND["agent"], "agent_sha256": "g" * 64}}),
    ("beta 0: none", 0.0, MERGED_BEFORE, None),
    ("after a branch won: none (the pool's step was a pick)", 0.5, MERGED_BEFORE | {"winner": "branch"}, None),
    ("after the parent stayed: none", 0.5, MERGED_BEFORE | {"winner": "parent"}, None),
    ("a previous selection that does not name its parent's file: none", 0.5,
     MERGED_BEFORE | {"parent": {k: v for k, v in GRAND.items() if k != "agent"}}, None),
    ("a garbled parent record: none", 0.5, MERGED_BEFORE | {"parent": "x"}, None),
    ("after a fallback took over: none", 0.5, MERGED_BEFORE | {"winner": "fallback"}, None),
    ("after a revert: none", 0.5, MERGED_BEFORE | {"winner": "revert"}, None),
    ("after an iteration without a valid deposit: none", 0.5, MERGED_BEFORE | {"winner": "carried"}, None),
    ("after a merge of sharpened starts: none (its step holds the sharpening)", 0.5,
     MERGED_BEFORE | {"merge": {"kind": "momentum", "sharpened_starts": True}}, None),
]


@pytest.mark.parametrize("name,beta,previous,want", MOMENTUM_CASES, ids=[c[0] for c in MOMENTUM_CASES])
def test_the_momentum_term(name, beta, previous, want):
    rows = [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)]
    prev = previous | {"next_fallback": AFTER_MERGE["next_fallback"]} if previous["winner"] == "merge" else previous
    out, _ = selection.decide(_cfg("momentum", n=4, merge_momentum=beta), 2, prev, [_report(*r) for r in rows],
                              [], "complete")
    assert out["winner"] == "merge" and out["merge"]["scale"] == 1.0
    assert out["merge"].get("momentum") == want
    # the other rules take no momentum, whatever the setting
    other, _ = selection.decide(_cfg("adaptive", n=4, merge_momentum=0.5), 2, prev, [_report(*r) for r in rows],
                                [], "complete")
    assert "momentum" not in other["merge"]
    # a momentum pool's selection names the file of the agent it started from (the next merge's
    # momentum needs it); other pools' records stay as they were
    assert out["parent"]["agent"] == previous["agent"]
    assert "agent" not in other["parent"]


def test_momentum_is_a_pool_setting_in_zero_to_one():
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(UsageError, match="--merge-momentum"):
            _cfg("momentum", merge_momentum=bad)
    with pytest.raises(UsageError, match="--merge-momentum needs --merge momentum"):
        PoolConfig.merged({"merge": "adaptive", "merge_momentum": 0.5}, None)
    assert PoolConfig.merged({"merge": "momentum", "merge_momentum": 0.7}, None).merge_momentum == 0.7
    # pools made before the setting existed read as they were made: they cannot merge with momentum
    d = _cfg("adaptive").to_json()
    d.pop("merge_momentum")
    assert PoolConfig.from_json(d).merge == "adaptive"


@pytest.mark.parametrize("rows", [
    [(0, 5.0, 4.0), (1, 7.0, None)], [(0, 3.0, 4.0), (1, 2.0, None)], [(0, 5.0, None), (1, 7.0, None)]])
def test_two_members_with_the_momentum_merge_decide_as_without_a_merge(rows):
    reports = [_report(m, r, p) for m, r, p in rows]
    for previous in (PREVIOUS, MERGED_BEFORE):
        plain = selection.decide(_cfg("none", n=2), 1, previous, reports, [], "complete")
        out, needs = selection.decide(_cfg("momentum", n=2), 1, previous, reports, [], "complete")
        assert out["parent"].pop("agent") == previous["agent"]  # the record names the parent's file too
        assert (out, needs) == plain


# ---------------------------------------------------------------- the store
def _deposits(paths, n, returns, parent_return, seed0=10):
    prev = deposits.read_selected(paths, 0)
    for m in range(n):
        extra = {"parent_eval_return": parent_return, "parent_sha256": prev["agent_sha256"]} if m == 0 else {}
        a = agent(seed0 + m)
        a = a.evolve(norm=normalizer.update(a.norm, np.random.default_rng(m).normal(size=(20 + m, 8))))
        deposits.deposit(paths, 1, m, a, {"eval_return": returns[m], **extra})


def _select_in_fresh_process(root, key_hex, out, i=1):
    os.environ["RL_POOL_KEY"] = key_hex
    paths = layout.Paths(root)
    cfg = pool.read_config(paths)
    pool.attach_key(paths)
    sel = pool.select(paths, i, cfg, deposits.load_selected_agent(paths, i - 1), {0, 1, 2}, "complete",
                      deposits.read_selected(paths, i - 1))
    with open(out, "w") as fh:
        json.dump(sel, fh)


def test_two_members_compute_the_same_merged_bytes(tmp_path, monkeypatch):
    key_hex = "a7" * 32
    monkeypatch.setenv("RL_POOL_KEY", key_hex)
    paths, cfg = make_pool(tmp_path / "p", pool_size=3, merge="sum")
    _deposits(paths, 3, [5.0, 7.0, 6.0], 4.0)
    mine = pool.select(paths, 1, cfg, deposits.load_selected_agent(paths, 0), {0, 1, 2}, "complete",
                       deposits.read_selected(paths, 0))
    assert mine["winner"] == "merge" and mine["merge"]["members"] == [1, 2, 0]
    first = fsutil.read_bytes(os.path.join(paths.root, mine["agent"]), 1 << 20)
    os.remove(os.path.join(paths.root, mine["agent"]))
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(target=_select_in_fresh_process, args=(str(paths.root), key_hex, str(tmp_path / "sel.json")))
    proc.start()
    proc.join(120)
    assert proc.exitcode == 0
    theirs = json.loads((tmp_path / "sel.json").read_text())
    assert theirs["agent_sha256"] == mine["agent_sha256"] and theirs == json.loads(json.dumps(mine))
    again = fsutil.read_bytes(os.path.join(paths.root, theirs["agent"]), 1 << 20)
    assert again == first and layout.sha256(again) == mine["agent_sha256"]
    # and the bytes are the merge of the deposits, computed here from their files
    merged = deposits.load_selected_agent(paths, 1, mine)
    parent = deposits.load_selected_agent(paths, 0)
    branches = {m: deposits.read_deposit(paths, 1, m)[1] for m in range(3)}
    w = selection.merge_weights(3)
    want = parent.params["w"] + 3.0 * sum(wk * (branches[m].params["w"] - parent.params["w"])
                                          for wk, m in zip(w, [1, 2, 0]))
    np.testing.assert_allclose(merged.params["w"], want, rtol=1e-12)
    assert merged.norm.count == parent.norm.count + sum(20 + m for m in range(3))


@pytest.mark.parametrize("forgery", ["agent swapped after its hash was signed", "metrics unsigned"])
def test_a_deposit_that_fails_its_checks_has_no_weight(tmp_path, forgery):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3, merge="sum")
    _deposits(paths, 3, [5.0, 7.0, 6.0], 4.0)
    if forgery.startswith("agent"):
        fsutil.atomic_write(paths.deposit_npz(1, 2), agent(99).to_bytes())  # the best-but-one branch
    else:
        doc = json.loads(open(paths.deposit_json(1, 2)).read())
        doc.pop("signature")
        fsutil.write_json(paths.deposit_json(1, 2), doc | {"eval_return": 1e9})
    sel = pool.select(paths, 1, cfg, deposits.load_selected_agent(paths, 0), {0, 1, 2}, "complete",
                      deposits.read_selected(paths, 0))
    assert sel["merge"]["members"] == [1, 0] and sel["merge"]["statistics_from"] == [0, 1]
    assert [s["member"] for s in sel["skipped"]] == [2]
    merged = deposits.load_selected_agent(paths, 1, sel)
    assert merged.norm.count == deposits.load_selected_agent(paths, 0).norm.count + 20 + 21


def test_gc_keeps_the_merged_agent_and_its_fallback(tmp_path):
    paths, cfg = make_pool(tmp_path / "p", pool_size=3, merge="sum")
    _deposits(paths, 3, [5.0, 7.0, 6.0], 4.0)
    sel = pool.select(paths, 1, cfg, deposits.load_selected_agent(paths, 0), {0, 1, 2}, "complete",
                      deposits.read_selected(paths, 0))
    pool.publish_selection(paths, sel, by=0)
    stray = os.path.join(paths.iteration(1), "merged-0123456789abcdef.npz")
    shutil.copy(os.path.join(paths.root, sel["agent"]), stray)
    pool.collect_garbage(paths, 1)
    left = sorted(n for n in os.listdir(paths.iteration(1)) if n.endswith(".npz"))
    assert left == sorted([os.path.basename(sel["agent"]), "member-001.npz"])
    assert pool.update_best(paths, deposits.read_selected(paths, 1))
    assert json.loads(open(paths.best_json).read())["agent"] == "iterations/000001/member-001.npz"


def _deposit_iteration(paths, i, n, returns, parent_return, seed0):
    """Deposits of iteration ``i`` whose member 0 re-scores the parent (the selection of ``i - 1``)."""
    prev = deposits.read_selected(paths, i - 1)
    for m in range(n):
        extra = {"parent_eval_return": parent_return, "parent_sha256": prev["agent_sha256"]} if m == 0 else {}
        deposits.deposit(paths, i, m, agent(seed0 + m), {"iteration": i, "eval_return": returns[m], **extra})


@pytest.mark.parametrize("grandparent", ["intact", "replaced by another agent", "missing"])
def test_a_second_merge_in_a_row_takes_momentum_from_the_files(tmp_path, monkeypatch, grandparent):
    key_hex = "b8" * 32
    monkeypatch.setenv("RL_POOL_KEY", key_hex)
    paths, cfg = make_pool(tmp_path / "p", pool_size=3, merge="momentum", merge_momentum=0.5)
    _deposit_iteration(paths, 1, 3, [5.0, 7.0, 6.0], 4.0, seed0=10)
    first = pool.select(paths, 1, cfg, deposits.load_selected_agent(paths, 0), {0, 1, 2}, "complete",
                        deposits.read_selected(paths, 0))
    assert first["winner"] == "merge" and "momentum" not in first["merge"]
    pool.publish_selection(paths, first, by=0)
    first = deposits.read_selected(paths, 1)
    _deposit_iteration(paths, 2, 3, [9.0, 8.0, 8.5], 7.5, seed0=20)
    g = deposits.load_selected_agent(paths, 0)
    if grandparent != "intact":
        deposits._parsed.clear()  # as in a member that never parsed it
        if grandparent == "missing":
            os.remove(paths.initial())
        else:
            fsutil.atomic_write(paths.initial(), agent(99).to_bytes())
    parent = deposits.load_selected_agent(paths, 1, first)
    second = pool.select(paths, 2, cfg, parent, {0, 1, 2}, "complete", first)
    assert second["winner"] == "merge" and second["merge"]["members"] == [0, 2, 1]
    merged = deposits.load_selected_agent(paths, 2, second)
    branches = [deposits.read_deposit(paths, 2, m)[1] for m in (0, 2, 1)]
    w = selection.merge_weights(3)
    for name in parent.params:
        want = parent.params[name] + sum(wk * (b.params[name] - parent.params[name]) for wk, b in zip(w, branches))
        if grandparent == "intact":
            assert second["merge"]["momentum"]["from"]["agent_sha256"] == layout.sha256(g.to_bytes())
            want = want + 0.5 * (parent.params[name] - g.params[name])
        else:  # a file that fails its hash or is gone adds nothing, and the record says why
            why = second["merge"]["momentum"]["skipped"]
            assert ("does not match the hash" if grandparent.startswith("replaced") else "No such file") in why
            # naming the file as the pool does, not as this host mounts it
            assert "iterations/000000/initial.npz" in why and str(paths.root) not in why
        np.testing.assert_allclose(merged.params[name], want, rtol=1e-12, atol=1e-12)
    # another process, from the same files, makes the same bytes
    mine = fsutil.read_bytes(os.path.join(paths.root, second["agent"]), 1 << 20)
    os.remove(os.path.join(paths.root, second["agent"]))
    proc = multiprocessing.get_context("spawn").Process(
        target=_select_in_fresh_process, args=(str(paths.root), key_hex, str(tmp_path / "sel.json"), 2))
    proc.start()
    proc.join(120)
    assert proc.exitcode == 0
    theirs = json.loads((tmp_path / "sel.json").read_text())
    assert theirs == json.loads(json.dumps(second))
    assert fsutil.read_bytes(os.path.join(paths.root, theirs["agent"]), 1 << 20) == mine


# ---------------------------------------------------------------- patience with the parent, as a table
PATIENCE_CASES = [
    # (name, merge, previous streak, [(member, return, parent report)], winner, streak after, patience recorded)
    ("the parent keeps the pool: the streak grows", "none", 1, [(0, 3.0, 4.0), (1, 2.0, None)], "parent", 2, None),
    ("a branch at the bar wins: the streak ends", "none", 2, [(0, 5.0, 4.0), (1, 2.0, None)], "branch", 0, None),
    ("K parent wins in a row: the best branch wins below the parent", "none", 3,
     [(0, 3.0, 4.0), (1, 3.5, None)], "branch", 0, 3),
    ("the same with merges: the best branch, not a merge of branches below the bar", "momentum", 3,
     [(0, 3.0, 4.0), (1, 3.5, None), (2, 3.2, None)], "branch", 0, 3),
    ("a garbled streak counts as none", "none", "x", [(0, 3.0, 4.0), (1, 2.0, None)], "parent", 1, None),
]


@pytest.mark.parametrize("name,kind,streak,rows,winner,after,patience", PATIENCE_CASES,
                         ids=[c[0] for c in PATIENCE_CASES])
def test_parent_patience(name, kind, streak, rows, winner, after, patience):
    cfg = _cfg(kind, n=4, parent_patience=3)
    out, _ = selection.decide(cfg, 1, PREVIOUS | {"parent_streak": streak}, [_report(*r) for r in rows], [],
                              "complete")
    assert out["winner"] == winner and out["parent_streak"] == after and out.get("patience") == patience
    if patience:
        assert out["member"] == max(rows, key=lambda r: r[1])[0]


def test_without_patience_the_records_carry_no_streak():
    out, _ = selection.decide(_cfg("none", n=2), 1, PREVIOUS | {"parent_streak": 9},
                              [_report(0, 3.0, 4.0), _report(1, 2.0)], [], "complete")
    assert out["winner"] == "parent" and "parent_streak" not in out and "patience" not in out
    for bad, why in ((-1, "--parent-patience must be"), (3, "--parent-patience needs --selection parent")):
        with pytest.raises(UsageError, match=why):
            _cfg("none", parent_patience=bad, selection="branches" if bad > 0 else "parent")


def test_a_momentum_source_of_other_shapes_adds_nothing(tmp_path):
    paths, _ = make_pool(tmp_path / "p", pool_size=3, merge="momentum")
    other = Agent.initial(AgentMeta("Swimmer-v5", {}, 60, 9, 2, (-1.0, -1.0), (1.0, 1.0)))
    data = other.to_bytes()
    fsutil.atomic_write(os.path.join(paths.iteration(0), "other.npz"), data)
    term = {"beta": 0.5, "from": {"iteration": 0, "agent": "iterations/000000/other.npz",
                                  "agent_sha256": layout.sha256(data)}}
    got, why = pool._momentum_term(paths, 2, term, agent(1))
    assert got is None and "other shapes" in why
    term["from"] = {"iteration": 0, "agent": "../outside.npz", "agent_sha256": "0" * 64}
    got, why = pool._momentum_term(paths, 2, term, agent(1))
    assert got is None and "outside the pool" in why


def test_a_revert_ends_the_parent_streak_and_nothing_deposited_keeps_it():
    best = {"iteration": 0, "eval_return": 99.0, "score": 99.0, "agent": "x.npz", "agent_sha256": "b" * 64}
    cfg = _cfg("none", n=2, parent_patience=5, revert_after=1)
    out, _ = selection.decide(cfg, 1, PREVIOUS | {"best": best, "parent_streak": 2},
                              [_report(0, 3.0, 4.0), _report(1, 2.0)], [], "complete")
    assert out["winner"] == "revert" and out["parent_streak"] == 0
    out, _ = selection.decide(_cfg("none", n=2, parent_patience=5), 1, PREVIOUS | {"parent_streak": 2}, [],
                              [{"member": 0, "reason": "missing"}, {"member": 1, "reason": "missing"}], "quorum")
    assert out["winner"] == "carried" and out["parent_streak"] == 2


def test_merge_steps_benchmark_prints_the_cosine_of_consecutive_merges(tmp_path, capsys):
    import importlib.util

    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "merge_steps.py")
    spec = importlib.util.spec_from_file_location("merge_steps_benchmark", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    paths, cfg = make_pool(tmp_path / "p", pool_size=3, merge="momentum")
    for i, (returns, parent_return, seed0) in enumerate([([5.0, 7.0, 6.0], 4.0, 10), ([9.0, 8.0, 8.5], 7.5, 20)], 1):
        _deposit_iteration(paths, i, 3, returns, parent_return, seed0)
        sel = pool.select(paths, i, cfg, deposits.load_selected_agent(paths, i - 1), {0, 1, 2}, "complete",
                          deposits.read_selected(paths, i - 1))
        assert sel["winner"] == "merge"
        pool.publish_selection(paths, sel, by=0)
    a = [mod.flat(deposits.load_selected_agent(paths, i)) for i in range(3)]
    s1, s2 = a[1] - a[0], a[2] - a[1]
    capsys.readouterr()
    assert mod.main([str(paths.root)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[1:]]
    assert [int(r[0]) for r in rows] == [1, 2]
    assert float(rows[0][1]) == pytest.approx(np.linalg.norm(s1), abs=1e-4)
    assert float(rows[0][2]) == pytest.approx(s1 @ s2 / np.linalg.norm(s1) / np.linalg.norm(s2), abs=1e-3)

    # --branches: inside iteration 1 (iteration 2 lacks an agent, so it is left out)
    os.remove(paths.deposit_npz(2, 1))
    steps = [mod.flat(deposits.read_deposit(paths, 1, m)[1]) - a[0] for m in range(3)]
    lengths = [float(np.sqrt(sum(x * x for x in s))) for s in steps]
    mean = [sum(col) / 3 for col in zip(*steps, strict=True)]
    pairs = [(0, 1), (0, 2), (1, 2)]
    cosine = sum(float(steps[j] @ steps[k]) / (lengths[j] * lengths[k]) for j, k in pairs) / 3
    capsys.readouterr()
    assert mod.main([str(paths.root), "--branches"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[1:]]
    assert len(rows) == 1 and rows[0][:2] == ["1", "3"]
    branch, length = sum(lengths) / 3, float(np.sqrt(sum(x * x for x in mean)))
    assert [float(x) for x in rows[0][2:]] == pytest.approx([branch, length, length / branch, cosine], abs=2e-3)
    # the parent's file gone: that iteration is left out, without a traceback
    deposits._parsed.clear()
    os.remove(paths.initial())
    capsys.readouterr()
    assert mod.main([str(paths.root), "--branches"]) == 0
    assert capsys.readouterr().out.splitlines()[1:] == []
    # iteration 2 made whole again: it is shown; with a branch that did not move, it is left out
    for branch, shown in ((agent(99), True), (deposits.load_selected_agent(paths, 1), False)):
        for f in (paths.deposit_npz(2, 1), paths.deposit_json(2, 1)):
            if os.path.exists(f):
                os.remove(f)
        deposits.deposit(paths, 2, 1, branch, {"iteration": 2, "eval_return": 8.0})
        capsys.readouterr()
        assert mod.main([str(paths.root), "--branches"]) == 0
        assert [r.split()[0] for r in capsys.readouterr().out.splitlines()[1:]] == (["2"] if shown else [])
    # not a pool: one line, exit 2
    assert mod.main([str(tmp_path / "nothing"), "--branches"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


# ---------------------------------------------------------------- learning rates that follow the pool's progress
RATE_CASES = [
    # (name, previous rate, best iteration after the selection, expected rate)
    ("a pool's first plateau iteration counts", None, 0, {"scale": 1.0, "since": 1}),
    ("K iterations without a new best halve the rates", {"scale": 1.0, "since": 2}, 0, {"scale": 0.5, "since": 0}),
    ("a new best doubles them back", {"scale": 0.25, "since": 1}, 1, {"scale": 0.5, "since": 0}),
    ("never above the rates given", {"scale": 1.0, "since": 2}, 1, {"scale": 1.0, "since": 0}),
    ("never below the floor", {"scale": selection.MIN_RATE_SCALE, "since": 2}, 0,
     {"scale": selection.MIN_RATE_SCALE, "since": 0}),
    ("a garbled record counts as the rates given", {"scale": "x", "since": -4}, 0, {"scale": 1.0, "since": 1}),
]


@pytest.mark.parametrize("name,rate,best_at,want", RATE_CASES, ids=[c[0] for c in RATE_CASES])
def test_rate_patience(name, rate, best_at, want):
    best = {"iteration": 0, "eval_return": 9.0, "score": 9.0, "agent": "x.npz", "agent_sha256": "b" * 64}
    previous = PREVIOUS | {"best": best} | ({"rate": rate} if rate is not None else {})
    rows = [_report(0, 10.0 if best_at else 3.0), _report(1, 2.0)]  # 10 beats the best of 9: a new best
    out, _ = selection.decide(_cfg("none", n=2, selection="branches", rate_patience=3), 1, previous, rows, [],
                              "complete")
    assert out["best"]["iteration"] == best_at and out["rate"] == want


def test_a_revert_is_no_new_best_for_the_rates():
    best = {"iteration": 0, "eval_return": 99.0, "score": 99.0, "agent": "x.npz", "agent_sha256": "b" * 64}
    cfg = _cfg("none", n=2, revert_after=2, rate_patience=2)
    out, _ = selection.decide(cfg, 1, PREVIOUS | {"best": best, "since_best": 1, "rate": {"scale": 1.0, "since": 1}},
                              [_report(0, 3.0, 4.0), _report(1, 2.0)], [], "complete")
    assert out["winner"] == "revert" and out["rate"] == {"scale": 0.5, "since": 0}
    assert selection.rate_scale(out) == 0.5 and selection.rate_scale(PREVIOUS) == 1.0


def test_without_rate_patience_the_records_carry_no_rate():
    out, _ = selection.decide(_cfg("none", n=2), 1, PREVIOUS | {"rate": {"scale": 0.5, "since": 0}},
                              [_report(0, 3.0, 4.0), _report(1, 2.0)], [], "complete")
    assert "rate" not in out
    for kw, why in (({"rate_patience": -1}, "--rate-patience must be"),
                    ({"rate_patience": 2, "rate_decay": 1.0}, "--rate-decay must be in"),
                    ({"rate_patience": 2, "rate_decay": 0.0}, "--rate-decay must be in")):
        with pytest.raises(UsageError, match=why):
            _cfg("none", **kw)
    with pytest.raises(UsageError, match="--rate-decay needs --rate-patience"):
        PoolConfig.merged({"rate_decay": 0.7}, None)


@pytest.mark.parametrize("k, want", [
    (0, [1.0] * 7),  # no decay
    (4, [1.0, 0.75, 0.5, 0.25, 0.01, 0.01, 0.01]),  # 1 - (I-1)/4, down to the floor
    (400, [1.0 - (i - 1) / 400 for i in range(1, 8)])])
def test_rate_anneal_decays_linearly_to_the_floor(k, want):
    cfg = _cfg("none", n=2, rate_anneal=k)
    got = [selection.anneal_scale(cfg, i) for i in range(1, 8)]
    assert got == pytest.approx(want, rel=1e-15, abs=0)
    assert selection.anneal_scale(cfg, 10 ** 6) == (selection.MIN_RATE_SCALE if k else 1.0)
    with pytest.raises(UsageError, match="--rate-anneal must be >= 0"):
        _cfg("none", rate_anneal=-1)


@pytest.mark.parametrize("winner", ["revert", "branch", "parent", "merge", "carried", None])
def test_revert_sharpen_sharpens_every_member_after_a_revert_only(winner):
    previous = PREVIOUS | ({"winner": winner} if winner else {})
    cfg = _cfg("none", n=3, selection="branches", revert_after=5, revert_sharpen=10.0)
    want = 10.0 if winner == "revert" else 1.0
    assert [selection.sharpening(cfg, previous, m) for m in range(3)] == [want] * 3
    plain = _cfg("none", n=3, selection="branches", revert_after=5)
    assert [selection.sharpening(plain, previous, m) for m in range(3)] == [1.0] * 3
    for kw, why in (({"revert_after": 5, "revert_sharpen": 0.5}, "--revert-sharpen must be in"),
                    ({"revert_after": 5, "revert_sharpen": float("nan")}, "--revert-sharpen must be in"),
                    ({"revert_sharpen": 3.0}, "--revert-sharpen needs --revert-after"),
                    ({"revert_after": 5, "revert_sharpen": 3.0, "link": "softplus"}, "--revert-sharpen needs --link exp")):
        with pytest.raises(UsageError, match=why):
            _cfg("none", **kw)


def test_a_merge_from_sharpened_starts_says_so():
    rows = [(0, 5.0, 4.0, None), (1, 7.0, None, None), (2, 6.0, None, None)]
    for cfg, previous, want in ((_cfg("momentum", n=4, revert_after=3, revert_sharpen=2.0), PREVIOUS | {"winner": "revert"}, True),
                                (_cfg("momentum", n=4, sharpen=4.0), PREVIOUS | {"winner": "parent"}, True),
                                (_cfg("momentum", n=4, sharpen=4.0), PREVIOUS | {"winner": "branch"}, None),
                                (_cfg("momentum", n=4), PREVIOUS | {"winner": "revert"}, None)):
        out, _ = selection.decide(cfg, 1, previous, [_report(*r) for r in rows], [], "complete")
        assert out["winner"] == "merge" and out["merge"].get("sharpened_starts") is want


# ---------------------------------------------------------------- sharper branches after a lock (--sharpen)
@pytest.mark.parametrize("winner, want", [
    ("parent", [1.0, 10 ** (1 / 3), 10 ** (2 / 3), 10.0]), ("fallback", [1.0, 10 ** (1 / 3), 10 ** (2 / 3), 10.0]),
    ("branch", [1.0] * 4), ("merge", [1.0] * 4), ("revert", [1.0] * 4), ("carried", [1.0] * 4), (None, [1.0] * 4)])
def test_sharpening_ladder_after_the_parent_was_kept(winner, want):
    previous = PREVIOUS | ({"winner": winner} if winner else {})
    got = [selection.sharpening(_cfg("momentum", n=4, sharpen=10.0), previous, m) for m in range(4)]
    assert got == pytest.approx(want, rel=1e-12)
    assert got[0] == 1.0  # member 0 (the guard) trains from the agent as it is
    assert [selection.sharpening(_cfg("momentum", n=4), previous, m) for m in range(4)] == [1.0] * 4


def test_sharpen_is_a_pool_setting_of_at_least_one_with_the_exp_link():
    for bad in (0.5, float("nan"), float("inf"), 1e4):
        with pytest.raises(UsageError, match="--sharpen must be"):
            _cfg("momentum", sharpen=bad)
    with pytest.raises(UsageError, match="--sharpen needs --link exp"):
        _cfg("momentum", sharpen=3.0, link="softplus")
    with pytest.raises(UsageError, match="--sharpen needs --selection parent"):
        _cfg("momentum", sharpen=3.0, selection="branches")
    d = _cfg("momentum").to_json()
    d.pop("sharpen")  # pools made before the setting never sharpen
    assert PoolConfig.from_json(d).sharpen == 1.0
