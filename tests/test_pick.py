"""``rl-pool pick``: candidates from a real pool, every one on the same held-out episodes."""

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from rl_pool import Agent
from rl_pool.commands import pick
from rl_pool.protocol import layout

from .conftest import SHORT, rl_pool
from .helpers import reference_episode

ITERS = 5
RESULTS = Path(__file__).resolve().parent.parent / "results"


@pytest.fixture(scope="module")
def pool_dir(tmp_path_factory):
    # branches only: a new agent nearly every iteration, so there is something to choose from
    d = tmp_path_factory.mktemp("pick") / "pool"
    rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--learning-rates", "0.03,0.3", "--iterations", ITERS,
            "--selection", "branches", *SHORT, "--quiet", check=0)
    return d


def _selections(d):
    """Each iteration's selection as written, read straight from the files."""
    out = []
    for i in range(ITERS + 1):
        doc = json.loads((d / "iterations" / f"{i:06d}" / "selected.json").read_bytes())
        out.append(doc)
    return out


def _sha(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_every_selected_agent_on_the_same_held_out_episodes_and_the_highest_mean_is_picked(pool_dir, tmp_path):
    out = tmp_path / "mine.npz"
    res = json.loads(rl_pool("pick", pool_dir, "--top", 0, "--episodes", 3, "--out", out, "--json", check=0).stdout)
    sels = _selections(pool_dir)
    assert {c["agent_sha256"] for c in res["candidates"]} == {s["agent_sha256"] for s in sels}
    assert res["distinct_agents"] == len(res["candidates"]) >= 3
    # ranked by the best evaluation return each agent reached (the initial agent has none: last)
    best_ret = {}
    for s in sels:
        if s.get("eval_return") is not None:
            best_ret[s["agent_sha256"]] = max(best_ret.get(s["agent_sha256"], -np.inf), s["eval_return"])
    ranked = [c["agent_sha256"] for c in res["candidates"] if c["eval_return"] is not None]
    assert ranked == sorted(best_ret, key=lambda h: -best_ret[h])
    assert res["candidates"][-1]["eval_return"] is None
    # each candidate's episodes equal an independent loop on the wrapped env, held-out seeds 2,000,000 + k
    for c in res["candidates"]:
        agent = Agent.load(pool_dir / c["agent"])
        ref = [reference_episode(agent, 2_000_000 + k)[0] for k in range(3)]
        np.testing.assert_allclose(c["returns"], ref, rtol=1e-12)
    means = [c["mean_return"] for c in res["candidates"]]
    top = res["candidates"][int(np.argmax(means))]
    assert res["picked"]["agent_sha256"] == top["agent_sha256"] == _sha(out)
    written = json.loads((tmp_path / "mine.json").read_bytes())
    assert written["picked"] == res["picked"] and len(written["candidates"]) == len(means)
    assert not (pool_dir / "picked.npz").exists()  # --out: the pool is only read


def test_top_k_with_workers_gives_the_same_numbers_and_adds_the_last_selected(pool_dir):
    full = json.loads(rl_pool("pick", pool_dir, "--top", 0, "--episodes", 3, "--json", check=0).stdout)
    two = json.loads(rl_pool("pick", pool_dir, "--top", 2, "--episodes", 3, "--workers", 2, "--json",
                             check=0).stdout)
    last = _selections(pool_dir)[-1]["agent_sha256"]
    expect = [c["agent_sha256"] for c in full["candidates"][:2]]
    if last not in expect:
        expect.append(last)
    assert [c["agent_sha256"] for c in two["candidates"]] == expect
    by_sha = {c["agent_sha256"]: c["returns"] for c in full["candidates"]}
    for c in two["candidates"]:
        assert c["returns"] == by_sha[c["agent_sha256"]]  # the worker split changes no number
    assert two["candidates"][-1]["last"] or last in expect[:2]
    # written into the pool by default, and `evaluate` on the pick gives its held-out mean back
    assert _sha(pool_dir / "picked.npz") == two["picked"]["agent_sha256"]
    again = json.loads(rl_pool("evaluate", pool_dir / "picked.npz", "--episodes", 3, "--seed", 2_000_000, "--json",
                               check=0).stdout)
    assert again["mean_return"] == pytest.approx(two["picked"]["mean_return"], rel=1e-12)


def test_finalists_play_the_episodes_that_follow_and_the_best_mean_over_all_of_them_is_picked(pool_dir, tmp_path):
    out = tmp_path / "final.npz"
    one = json.loads(rl_pool("pick", pool_dir, "--top", 0, "--episodes", 2, "--out", tmp_path / "one.npz", "--json",
                             check=0).stdout)
    res = json.loads(rl_pool("pick", pool_dir, "--top", 0, "--episodes", 2, "--finalists", 2, "--final-episodes", 3,
                             "--workers", 2, "--out", out, "--json", check=0).stdout)
    assert (res["finalists"], res["final_episodes"]) == (2, 3)
    # the first round is the plain pick's; its two best (ties: the higher-ranked) play on
    firsts = [c["mean_return"] for c in one["candidates"]]
    leaders = sorted(range(len(firsts)), key=lambda j: (-firsts[j], j))[:2]
    for j, c in enumerate(res["candidates"]):
        assert c["agent_sha256"] == one["candidates"][j]["agent_sha256"]
        if j in leaders:
            assert c["finalist"] and c["first_mean_return"] == firsts[j] and c["episodes"] == 5
            agent = Agent.load(pool_dir / c["agent"])
            ref = [reference_episode(agent, 2_000_000 + k)[0] for k in range(5)]
            np.testing.assert_allclose(c["returns"], ref, rtol=1e-12)
            assert c["mean_return"] == pytest.approx(np.mean(ref), rel=1e-12)
        else:
            assert "finalist" not in c and c["returns"] == one["candidates"][j]["returns"] and c["episodes"] == 2
    # the pick: the finalist with the highest mean over its 5 episodes, whatever the others scored on 2
    finals = [res["candidates"][j] for j in leaders]
    chosen = max(finals, key=lambda c: c["mean_return"])
    assert res["picked"]["agent_sha256"] == chosen["agent_sha256"] == _sha(out)
    assert res["picked"]["episodes"] == 5
    again = json.loads(rl_pool("evaluate", out, "--episodes", 5, "--seed", 2_000_000, "--json", check=0).stdout)
    assert again["mean_return"] == pytest.approx(res["picked"]["mean_return"], rel=1e-12)
    written = json.loads((tmp_path / "final.json").read_bytes())["candidates"]
    assert [c.get("first_mean_return") for c in written] == [c.get("first_mean_return") for c in res["candidates"]]
    # more finalists than candidates: every candidate plays on, and the record says how many did
    every = json.loads(rl_pool("pick", pool_dir, "--top", 0, "--episodes", 1, "--finalists", 99, "--final-episodes",
                               1, "--out", tmp_path / "every.npz", "--json", check=0).stdout)
    assert every["finalists"] == len(every["candidates"]) and all(c["finalist"] for c in every["candidates"])
    text = rl_pool("pick", pool_dir, "--top", 0, "--episodes", 2, "--finalists", 2, "--final-episodes", 3,
                   "--out", out, check=0).stdout
    assert "the 2 best of them on 3 more (reset seeds 2000002..2000004)" in text
    assert text.count("(finalist)") + text.count("<- picked") == 2


def test_unreadable_candidates_are_skipped_with_the_reason(pool_dir, tmp_path):
    # a copy of the pool in which one selected agent is garbage and another is a FIFO (never read)
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(pool_dir, d)
    sels = [s for s in _selections(d) if s.get("winner") == "branch"]
    garbage, fifo = d / sels[0]["agent"], d / sels[-1]["agent"]
    garbage.write_bytes(b"not an agent")
    os.unlink(fifo)
    os.mkfifo(fifo)
    proc = rl_pool("pick", d, "--top", 0, "--episodes", 2, timeout=120, check=0)
    assert f"skipped iteration {sels[0]['iteration']}'s agent {sels[0]['agent']}: does not match" in proc.stdout
    assert f"skipped iteration {sels[-1]['iteration']}'s agent {sels[-1]['agent']}" in proc.stdout
    picked = json.loads((d / "picked.json").read_bytes())["picked"]
    assert picked["agent_sha256"] not in {sels[0]["agent_sha256"], sels[-1]["agent_sha256"]}


def test_forged_selections_read_without_the_key_are_skipped(pool_dir, tmp_path):
    """Read without the pool's key, a selection is unverified: one that names garbage (with its
    hash) or an agent for another task is skipped with the reason, not run."""
    import shutil

    from rl_pool.protocol import claim

    d = tmp_path / "copy"
    shutil.copytree(pool_dir, d)
    foreign = d / "iterations" / "000001" / "foreign.npz"
    shutil.copy(RESULTS / "hopper-v5" / "best.npz", foreign)
    garbage = d / "iterations" / "000001" / "garbage.npz"
    garbage.write_bytes(b"PK not an agent")
    for i, agent in ((ITERS - 1, foreign), (ITERS, garbage)):
        sel = d / "iterations" / f"{i:06d}" / "selected.json"
        doc = json.loads(sel.read_bytes()) | {"agent": str(agent.relative_to(d)), "agent_sha256": _sha(agent),
                                               "eval_return": 1e6}
        shutil.rmtree(sel.parent / ".selected.json.once")
        claim.create_once(sel, json.dumps(doc).encode())
    env = {k: v for k, v in os.environ.items() if not k.startswith("RL_POOL_KEY")}
    proc = rl_pool("pick", d, "--top", 0, "--episodes", 1, "--workers", 2, check=0,
                   env=env | {"XDG_CONFIG_HOME": str(tmp_path / "no-key")})
    assert "pool files unverified (no key)" in proc.stdout
    assert f"skipped iteration {ITERS}'s agent iterations/000001/garbage.npz: not an rl-pool agent file" in proc.stdout
    assert (f"skipped iteration {ITERS - 1}'s agent iterations/000001/foreign.npz: an agent for Hopper-v5"
            in proc.stdout)
    assert _sha(d / "picked.npz") not in {_sha(foreign), _sha(garbage)}


def test_a_directory_at_the_pick_is_set_aside(pool_dir, tmp_path):
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(pool_dir, d)
    (d / "picked.npz").unlink(missing_ok=True)  # an earlier test's pick
    (d / "picked.npz").mkdir()
    rl_pool("pick", d, "--top", 1, "--episodes", 1, check=0)
    assert (d / "picked.npz").is_file() and Agent.load(d / "picked.npz") is not None


def test_a_pool_directory_means_its_pick_while_the_pick_covers_its_last_iteration(pool_dir, tmp_path):
    """``evaluate POOL`` (and replay, --init-agent) take ``picked.npz`` once a pick covers the
    pool's last selection; a pick whose file no longer holds the agent it names, or a pool that
    trained on after it, gives ``best.npz`` back."""
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(pool_dir, d)
    for f in ("picked.npz", "picked.json"):
        (d / f).unlink(missing_ok=True)

    def agent_of(target):
        return json.loads(rl_pool("evaluate", target, "--episodes", 1, "--json", check=0).stdout)["agent"]

    assert agent_of(d) == str(d / "best.npz")  # no pick yet
    rl_pool("pick", d, "--top", 0, "--episodes", 2, check=0)
    doc = json.loads((d / "picked.json").read_bytes())
    assert doc["pool_iteration"] == ITERS
    assert agent_of(d) == str(d / "picked.npz")
    text = rl_pool("evaluate", d, "--episodes", 1, check=0).stdout
    assert text.startswith(f"{d / 'picked.npz'}: 1 episodes: mean ")
    # a file that is not the agent its JSON names does not count
    good = (d / "picked.npz").read_bytes()
    shutil.copy(RESULTS / "hopper-v5" / "best.npz", d / "picked.npz")
    assert agent_of(d) == str(d / "best.npz")
    (d / "picked.npz").write_bytes(good)
    assert agent_of(d) == str(d / "picked.npz")
    # a pick that does not say which iteration it saw (written before picks recorded it) does not count,
    # nor does one whose JSON will not parse
    text = (d / "picked.json").read_text()
    (d / "picked.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "pool_iteration"}))
    assert agent_of(d) == str(d / "best.npz")
    (d / "picked.json").write_text("[" * 200_000)
    assert agent_of(d) == str(d / "best.npz")
    (d / "picked.json").write_text(text)
    assert agent_of(d) == str(d / "picked.npz")
    # the pool trains on: its new agents were never in the pick
    rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--learning-rates", "0.03,0.3", "--iterations", ITERS + 1,
            "--selection", "branches", *SHORT, "--quiet", check=0)
    assert agent_of(d) == str(d / "best.npz")


@pytest.mark.parametrize("args, message", [
    (["--top", "-1"], "--top and --finalists must be >= 0"),
    (["--episodes", "0"], "--episodes, --final-episodes and --workers positive"),
    (["--episodes", "10000000000"], "--episodes (plus --final-episodes) must be at most 1000000"),
    (["--finalists", "-1"], "--top and --finalists must be >= 0"),
    (["--finalists", "2", "--final-episodes", "0"], "--final-episodes and --workers positive"),
    (["--episodes", "999999", "--finalists", "1", "--final-episodes", "2"], "must be at most 1000000"),
])
def test_bad_arguments_get_one_line(pool_dir, args, message):
    proc = rl_pool("pick", pool_dir, *args, check=2)
    assert proc.stderr.count("\n") == 1 and message in proc.stderr and "Traceback" not in proc.stderr


def test_not_a_pool_gets_one_line(tmp_path):
    proc = rl_pool("pick", tmp_path, check=2)
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_a_launch_ends_with_a_pick_of_the_pool_it_ran(tmp_path):
    d = tmp_path / "picked-at-the-end"
    proc = rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--learning-rates", "0.03,0.3", "--iterations", 3,
                   "--selection", "branches", *SHORT, "--pick", "--quiet", check=0)
    res = json.loads((d / "picked.json").read_bytes())
    shas = {s["agent_sha256"] for s in (json.loads((d / "iterations" / f"{i:06d}" / "selected.json").read_bytes())
                                        for i in range(4))}
    assert res["picked"]["agent_sha256"] == _sha(d / "picked.npz") and res["picked"]["agent_sha256"] in shas
    assert {c["agent_sha256"] for c in res["candidates"]} == shas  # fewer than pick's default top: all
    assert (res["episodes"], res["seed"], res["top"]) == (pick.DEFAULT_EPISODES, pick.DEFAULT_SEED, pick.DEFAULT_TOP)
    p = res["picked"]
    assert f"picked the agent of iteration {p['iteration']} on {p['episodes']} held-out episodes: mean " \
           f"{p['mean_return']:.2f}" in proc.stdout
    again = json.loads(rl_pool("pick", d, "--out", tmp_path / "again.npz", "--json", check=0).stdout)
    assert again["picked"]["agent_sha256"] == p["agent_sha256"]  # what `rl-pool pick POOL` picks
    # what a launch with a budget keeps for one candidate: its held-out episodes at the pool's length
    assert pick.episode_steps(layout.Paths(str(d))) == pick.DEFAULT_EPISODES * 60


def test_a_launch_can_end_with_a_pick_that_has_a_final_round(tmp_path):
    d = tmp_path / "final-round"
    proc = rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--learning-rates", "0.03,0.3", "--iterations", 3,
                   "--selection", "branches", *SHORT, "--pick", "--pick-finalists", 2, "--pick-final-episodes", 3,
                   "--quiet", check=0)
    res = json.loads((d / "picked.json").read_bytes())
    assert (res["finalists"], res["final_episodes"]) == (2, 3) and "2 of them played on" in proc.stdout
    assert sum(bool(c.get("finalist")) for c in res["candidates"]) == 2
    assert res["picked"]["episodes"] == pick.DEFAULT_EPISODES + 3
    # the pick `rl-pool pick POOL --finalists 2 --final-episodes 3` makes
    again = json.loads(rl_pool("pick", d, "--finalists", 2, "--final-episodes", 3, "--out", tmp_path / "again.npz",
                               "--json", check=0).stdout)
    assert again["picked"]["agent_sha256"] == res["picked"]["agent_sha256"] == _sha(d / "picked.npz")


@pytest.mark.parametrize("args, message", [
    (["--pick-finalists", "2"], "--pick-finalists sets the final round of a pick: add --pick"),
    (["--pick-final-episodes", "5"], "--pick-final-episodes sets the final round of a pick: add --pick"),
    (["--pick", "--pick-finalists", "-1"], "--pick-finalists must be >= 0"),
    (["--pick", "--pick-finalists", "2", "--pick-final-episodes", "0"], "--pick-final-episodes 1 to 999980"),
    (["--pick", "--pick-final-episodes", "5"], "--pick-final-episodes sets the final round's episodes: add "
                                              "--pick-finalists K"),
])
def test_a_launchs_final_round_without_sense_gets_one_line(tmp_path, args, message):
    proc = rl_pool("launch", "--pool-dir", tmp_path / "p", "--iterations", 1, *SHORT, *args, check=2)
    assert proc.stderr.count("\n") == 1 and message in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "p").exists()  # refused before any pool or member


def test_a_launchs_budget_keeps_time_for_the_pick_and_its_final_round_at_the_pools_episode_length(pool_dir):
    from rl_pool.commands.launch import pick_budget

    paths = layout.Paths(str(pool_dir))
    b = pick_budget(paths, 1.0, True, 6, 100)
    assert (b.pick_steps, b.finalists, b.final_steps) == (pick.DEFAULT_EPISODES * 60, 6, 100 * 60)
    assert pick_budget(paths, 1.0, True, 0, 100).reserve(1e4, 50) < b.reserve(1e4, 50)
    assert pick_budget(paths, 1.0, False, 6, 100).reserve(1e4, 50) == 0.0  # no pick: nothing kept


def test_a_launch_with_a_budget_stops_in_time_for_its_pick_and_a_launch_resumes(tmp_path):
    d = tmp_path / "budget"
    budget = 0.6  # minutes: the pick of 21 x 20 short episodes keeps 10-20 s of it
    t0 = time.monotonic()
    proc = rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--iterations", 100000, *SHORT,
                   "--minutes", budget, "--pick", "--quiet", check=0)
    took = time.monotonic() - t0
    assert f"(stopped at the budget of {budget:g} minutes)" in proc.stdout and "picked the agent" in proc.stdout
    # the pick fits in the budget by the pool's pace; a loaded machine gets a few seconds of slack
    assert took < 60 * budget + 15, (took, proc.stdout)
    st = json.loads(rl_pool("status", d, "--json", check=0).stdout)
    done = st["iterations_completed"]
    assert all(m["state"] != "training" for m in st["members"]) and done < 100000
    # the members trained for most of what the pick left them, not only at the start
    ran = st["history"][-1]["elapsed_seconds"]
    assert ran > 60 * budget / 4, (ran, proc.stdout)
    assert json.loads((d / "picked.json").read_bytes())["picked"]["agent_sha256"] == _sha(d / "picked.npz")
    # stopped as Ctrl-C stops it: the next launch resumes the pool, not a new one
    rl_pool("launch", "--pool-dir", d, "--iterations", done + 1, "--quiet", check=0)
    assert json.loads(rl_pool("status", d, "--json", check=0).stdout)["iterations_completed"] == done + 1


def test_the_budget_keeps_time_for_the_pick_by_the_pools_pace_and_its_candidates():
    from rl_pool.commands.launch import PICK_MARGIN, PICK_OVERHEAD, SLOW_PACE, Budget

    plain = Budget(1.0, None, now=100.0)
    assert not plain.due(5e4, 50, now=159.9) and plain.due(5e4, 50, now=160.0)
    assert not Budget(None, 20_000, now=100.0).due(1.0, 0, now=1e9)
    hc = 20 * 1000  # HalfCheetah: 20 held-out episodes of 1000 steps a candidate
    with_pick = Budget(1.0, hc, now=100.0)
    # 21 candidates at most: the top 20 and the last selected
    keep = PICK_OVERHEAD + PICK_MARGIN * 21 * hc / 50_000
    assert with_pick.reserve(50_000, 300) == with_pick.reserve(50_000, 20) == pytest.approx(keep)
    assert not with_pick.due(50_000, 300, now=160.0 - keep - 0.01) and with_pick.due(50_000, 300, now=160.0 - keep)
    # a young pool has fewer agents to pick from (one new one an iteration at most, and the first)
    assert with_pick.reserve(50_000, 3) == pytest.approx(PICK_OVERHEAD + PICK_MARGIN * 4 * hc / 50_000)
    # before the pool has a pace, a slow one is assumed
    assert with_pick.reserve(None, 0) == pytest.approx(PICK_OVERHEAD + PICK_MARGIN * hc / SLOW_PACE)
    # a final round: its finalists' episodes too, as many finalists as there are candidates at most
    final = 100 * 1000
    with_final = Budget(1.0, hc, now=100.0, finalists=6, final_steps=final)
    assert with_final.reserve(50_000, 300) == pytest.approx(keep + PICK_MARGIN * 6 * final / 50_000)
    assert with_final.reserve(50_000, 3) == pytest.approx(PICK_OVERHEAD + PICK_MARGIN * 4 * (hc + final) / 50_000)
