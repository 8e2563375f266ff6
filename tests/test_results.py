"""The committed result still holds: the best Swimmer agent loads and swims >= 350 on fresh episodes."""

import csv
import json
import os

import pytest

from rl_pool import Agent, threads
from rl_pool.commands.evaluate import evaluate_bytes

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results", "swimmer-v5")


def test_committed_best_agent_scores_at_least_350_on_fresh_episodes():
    path = os.path.join(RESULTS, "best.npz")
    agent = Agent.load(path)
    assert agent.meta.env == "Swimmer-v5" and agent.meta.max_episode_steps == 1000
    with open(path, "rb") as fh:
        res = evaluate_bytes(fh.read(), episodes=4, workers=1, seed=2_000_000)
    assert min(res["returns"]) >= 350, res["returns"]


def test_committed_history_matches_best():
    with open(os.path.join(RESULTS, "history.csv"), newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(os.path.join(RESULTS, "best.json")) as fh:
        best = json.load(fh)
    top = max(rows, key=lambda r: float(r["eval_return"]))
    assert int(top["iteration"]) == best["iteration"] and float(top["eval_return"]) == best["eval_return"]


#: the 2-member HalfCheetah run of 2026-11-23, kept whole beside the 8-member result that replaced it
HALFCHEETAH = os.path.join(os.path.dirname(RESULTS), "halfcheetah-v5", "screening", "two-members-seed0")


def _versions_as_committed(task: str) -> bool:
    from rl_pool import versions

    with open(os.path.join(task, "versions.txt")) as fh:
        made = dict(ln.split(None, 1) for ln in fh.read().split("\n") if ln.strip())
    now = versions.versions()
    return all(now.get(k) == v.strip() for k, v in made.items())


@pytest.mark.skipif(not threads.cpu_runs_v3(), reason="the portable level needs an x86-64-v3 CPU")
@pytest.mark.skipif(not _versions_as_committed(HALFCHEETAH), reason="installed versions differ from the lock")
def test_committed_re_score_replays_bit_for_bit_here():
    """results/halfcheetah-v5/screening/two-members-seed0/rescore.json was made on a machine without
    AVX-512. With numpy, OpenBLAS and XLA held to x86-64-v3 code (rl_pool.threads), the real CLI
    gives the same returns to the last bit on this machine, whatever its CPU has (without the cap
    an AVX-512 CPU gave other returns for every one of the 50 episodes)."""
    from .conftest import rl_pool

    with open(os.path.join(HALFCHEETAH, "rescore.json")) as fh:
        committed = json.load(fh)["returns"]
    env = {k: v for k, v in os.environ.items() if k not in (*threads.VARIABLES, "RL_POOL_NATIVE_SIMD")}
    out = rl_pool("evaluate", os.path.join(HALFCHEETAH, "best.npz"), "--episodes", 3, "--json", check=0, env=env)
    assert json.loads(out.stdout)["returns"] == committed[:3]
