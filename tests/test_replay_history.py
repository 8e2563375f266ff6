"""A pool made by an earlier rl-pool (before merges; picking one branch was the only rule) is
replayed with today's code: every selection decided again must come out bit for bit as that
version wrote it, and every deposit trained again as it did, to the bit on a machine that compiles
the gradient alike (:func:`test_every_deposit_trains_again`).

``tests/data/pool-before-merge`` holds that pool: Swimmer-v5, 3 members at rates 0.01, 0.1, 0.1,
5 iterations of 4 training episodes of 100 steps, 3 evaluation episodes, made by
``rl-pool launch --pool-size 3 --iterations 5 --max-episode-steps 100 --train-episodes 4
--eval-episodes 3`` with the test key below and numpy 2.4.6, jax 0.10.2, mujoco 4.0.0,
gymnasium 1.4.0. Its ``pool.json`` has no ``merge`` (it predates the option), so it reads as
``none``.
"""

import json
import os
import shutil

import numpy as np
import pytest

from rl_pool.learning import envs, trainer
from rl_pool.protocol import deposits, layout, pool
from rl_pool.versions import versions

DATA = os.path.join(os.path.dirname(__file__), "data", "pool-before-merge")
KEY = "5e" * 32
#: Floating-point results replay exactly only with the libraries that made them.
MADE_WITH = {"numpy": "2.4.6", "jax": "0.10.2", "mujoco": "4.0.0", "gymnasium": "1.4.0"}
UNSIGNED = ("signature", "selected_by", "time")


@pytest.fixture
def old_pool(tmp_path, monkeypatch):
    monkeypatch.setenv("RL_POOL_KEY", KEY)
    root = tmp_path / "pool"
    shutil.copytree(DATA, root)
    paths = layout.Paths(str(root))
    cfg = pool.read_config(paths)
    pool.attach_key(paths)
    return paths, cfg


def _decided(paths, i):
    return {k: v for k, v in deposits.read_selected(paths, i).items() if k not in UNSIGNED}


def test_the_old_pool_reads_as_the_rule_it_ran(old_pool):
    _, cfg = old_pool
    assert cfg.merge == "none" and cfg.pool_size == 3


def test_every_selection_decides_again_bit_for_bit(old_pool):
    paths, cfg = old_pool
    like = deposits.load_selected_agent(paths, 0)
    last = deposits.last_selected(paths)
    assert last == 5
    for i in range(1, last + 1):
        again = pool.select(paths, i, cfg, like, deposits.present(paths, i, cfg.pool_size), "complete",
                            deposits.read_selected(paths, i - 1))
        assert json.loads(json.dumps(again)) == _decided(paths, i), f"iteration {i}"


@pytest.mark.skipif(any(versions().get(k) != v for k, v in MADE_WITH.items()),
                    reason=f"deposits replay only with {MADE_WITH}")
def test_every_deposit_trains_again(old_pool):
    """Every member's training and evaluation of the old pool, done again from the agent it started
    from: bit for bit on a machine that rounds as the maker's did. XLA compiles the gradient for
    the host's CPU model, and on another (an AMD EPYC with AVX-512, with the portable SIMD level on)
    its last bits differ: there every trained array (parameters and Adam's moments) agrees with the
    deposited one within 1e-9 of its size and every evaluation return within 1e-9 relative, which a
    change in what a member computes would break. (Exact replay on one machine, kills included, is
    the multi-process tests'.)"""
    paths, cfg = old_pool
    kwargs = dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps)
    env_list = [envs.make(cfg.env, kwargs)[0] for _ in range(max(cfg.batch_episodes, cfg.eval_episodes))]
    for i in range(1, deposits.last_selected(paths) + 1):
        start = deposits.load_selected_agent(paths, i - 1)
        for m in range(cfg.pool_size):
            doc = paths.read_json(paths.deposit_json(i, m))
            tr = trainer.train(start, env_list, cfg, doc["learning_rate"], m, i)
            ev = trainer.evaluate(tr.agent, env_list, cfg, i)
            if layout.sha256(tr.agent.to_bytes()) == doc["agent_sha256"]:
                assert ev.returns == doc["eval_returns"], f"iteration {i}, member {m}"
                continue
            made = deposits.read_agent(paths, i, m, doc, like=start)
            for tree in ("params", "opt_m", "opt_v"):
                again, then = getattr(tr.agent, tree), getattr(made, tree)
                assert sorted(again) == sorted(then)
                for k in then:
                    scale = float(np.max(np.abs(then[k]))) or 1.0
                    np.testing.assert_allclose(np.asarray(again[k]), then[k], rtol=0, atol=1e-9 * scale,
                                               err_msg=f"iteration {i}, member {m}, {tree}.{k}")
            np.testing.assert_allclose(ev.returns, doc["eval_returns"], rtol=1e-9, atol=0,
                                       err_msg=f"iteration {i}, member {m}")
