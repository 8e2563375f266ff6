"""PPO's minibatches for the extra passes (``--minibatch-steps``): the plan of which steps each
minibatch takes, the Adam steps against a plain loop over the plan, the options' checks, and a
real pool that takes them and replays byte for byte."""

import dataclasses
import json

import numpy as np
import pytest

from rl_pool.config import PoolConfig
from rl_pool.errors import UsageError
from rl_pool.learning import envs, trainer
from rl_pool.maths import learner, policy
from rl_pool.maths.agent import Agent, AgentMeta

from .conftest import SHORT, rl_pool
from .helpers import adam_ascent_by_hand, random_opt_state

SPEC = policy.PolicySpec("mlp", (5,), "exp", (4,))


def _batch(seed=0, b=3, t=7, obs=3, act=2):
    rng = np.random.default_rng(seed)
    params = {k: rng.normal(scale=0.5, size=s) for k, s in policy.param_shapes(SPEC, obs, act).items()}
    x = rng.normal(size=(b, t, obs))
    u = rng.uniform(0.05, 0.95, size=(b, t, act))
    mask = np.ones((b, t))
    mask[0, 5:] = 0
    mask[b - 1, 2:] = 0
    adv = rng.normal(size=(b, t)) * mask
    return params, x, u, adv, mask


def test_every_pass_takes_each_valid_step_once_in_a_fresh_order():
    _, _, _, _, mask = _batch()  # 5 + 7 + 2 = 14 valid steps of 21
    order, count = learner.minibatch_plan(mask, 4, 3, np.random.default_rng(0))
    valid = set(np.flatnonzero(mask.reshape(-1)).tolist())
    assert count == 3 * 4 and order.shape == (3 * 6, 4)  # room for 3 passes over 21 steps
    assert (order[count:] == mask.size).all()
    passes = [order[p * 4:(p + 1) * 4].reshape(-1) for p in range(3)]
    for taken in passes:
        real = taken[taken != mask.size]
        assert sorted(real.tolist()) == sorted(valid)  # each valid step once, padding never
        assert (taken[-2:] == mask.size).all()  # the last minibatch of a pass is filled up with the pad row
    assert not np.array_equal(passes[0], passes[1])
    again, _ = learner.minibatch_plan(mask, 4, 3, np.random.default_rng(0))
    assert np.array_equal(order, again)
    whole, n = learner.minibatch_plan(mask, 100, 2, np.random.default_rng(0))
    assert n == 2 and whole.shape == (2, 100)


def test_minibatch_steps_are_adam_steps_on_each_minibatch_written_out():
    params, x, u, adv, mask = _batch(3)
    opt = random_opt_state(params, 4, 2.0)
    logp_old = learner.log_prob({k: v - 0.02 for k, v in params.items()}, x, u, SPEC)
    p1, opt1 = learner.policy_minibatches(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 2, 4,
                                          np.random.default_rng(7), SPEC)
    order, count = learner.minibatch_plan(mask, 4, 2, np.random.default_rng(7))
    import jax

    p, m, v = dict(params), dict(opt.m), dict(opt.v)
    for step in range(count):
        rows = [i for i in order[step] if i < mask.size]  # the padding row adds nothing
        bi, ti = np.divmod(np.asarray(rows), mask.shape[1])
        g = jax.grad(learner.clipped_objective)(p, x[bi, ti][None], u[bi, ti][None], adv[bi, ti][None],
                                                mask[bi, ti][None], logp_old[bi, ti][None], 0.2, SPEC)
        adam_ascent_by_hand(p, m, v, g, 2.0 + 1 + step, 0.01)
    for k in params:
        np.testing.assert_allclose(p1[k], p[k], rtol=1e-10, atol=1e-14, err_msg=k)
        np.testing.assert_allclose(opt1.m[k], m[k], rtol=1e-10, atol=1e-16, err_msg=k)
        if k.startswith("v_"):  # the value network and its moments stay where they were
            assert np.array_equal(p1[k], params[k]) and np.array_equal(opt1.m[k], opt.m[k])
    assert opt1.t == 2.0 + count == 10.0
    same, same_opt = learner.policy_minibatches(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 0, 4,
                                                np.random.default_rng(7), SPEC)
    assert same is params and same_opt is opt


def test_one_minibatch_of_the_whole_batch_is_a_plain_pass():
    """With room for the whole batch in one minibatch, a pass is :func:`learner.policy_epochs`' step."""
    params, x, u, adv, mask = _batch(5)
    opt = learner.OptState({k: np.zeros_like(v) for k, v in params.items()},
                           {k: np.zeros_like(v) for k, v in params.items()}, 1.0)
    logp_old = learner.log_prob(params, x, u, SPEC)
    mini, mopt = learner.policy_minibatches(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 3, mask.size,
                                            np.random.default_rng(0), SPEC)
    whole, wopt = learner.policy_epochs(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 3, SPEC)
    for k in params:
        np.testing.assert_allclose(mini[k], whole[k], rtol=1e-9, atol=1e-13, err_msg=k)
    assert mopt.t == wopt.t == 4.0


@pytest.mark.parametrize("name", ["minibatch_steps", "value_minibatch_steps"])
def test_minibatch_sizes_are_bounded_and_older_pools_read_without_them(name):
    d = PoolConfig().validate().to_json()
    d.pop(name)
    assert getattr(PoolConfig.from_json(d), name) == 0
    for bad in (-1, 10**6 + 1):
        with pytest.raises(UsageError, match=f"--{name.replace('_', '-')} must be in"):
            PoolConfig(**{name: bad}).validate()


def test_options_are_checked_without_policy_epochs():
    with pytest.raises(UsageError, match="--minibatch-steps needs --policy-epochs above 1"):
        PoolConfig.merged({"minibatch_steps": 64}, None)
    assert PoolConfig.merged({"minibatch_steps": 64, "policy_epochs": 2}, None).minibatch_steps == 64


def _swimmer_member_three_ways(change: dict, **options):
    """A real Swimmer member's first iteration (4 episodes of 60 steps, one batch) with ``options``
    and with ``change`` on top, twice: ``(start, whole, changed, changed again)``."""
    cfg = PoolConfig(max_episode_steps=60, train_episodes=4, batch_episodes=4, **options).validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 60})[0] for _ in range(4)]
    meta = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0), cfg.spec)
    start = Agent.initial(meta, seed=0)
    changed = dataclasses.replace(cfg, **change)
    return (start, trainer.train(start, env_list, cfg, 0.01, 0, 0), trainer.train(start, env_list, changed, 0.01, 0, 0),
            trainer.train(start, env_list, changed, 0.01, 0, 0))


def test_a_member_with_minibatches_moves_further_and_replays_exactly():
    """On real Swimmer episodes: minibatches take more steps than whole-batch passes, from a
    stream of their own, and the same seeds give the same bytes."""
    start, whole, mini, again = _swimmer_member_three_ways({"minibatch_steps": 40}, policy_epochs=3)
    assert mini.agent.to_bytes() == again.agent.to_bytes()
    assert mini.episode_returns == whole.episode_returns  # the same episodes: the shuffle has its own stream
    assert (whole.agent.opt_t, mini.agent.opt_t) == (3.0, 1.0 + 2 * 6)  # 240 steps in minibatches of 40
    step = lambda a: np.linalg.norm(a.params["w"] - start.params["w"])  # noqa: E731
    assert step(mini.agent) > step(whole.agent)


def test_a_pool_with_minibatches_records_them_and_replays_byte_for_byte(tmp_path):
    runs = []
    for name in ("a", "b"):
        d = tmp_path / name
        rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--policy-epochs", 3, "--minibatch-steps", 50,
                *SHORT, "--iterations", 2, "--quiet", check=0)
        runs.append(d)
    a, b = runs
    made = json.loads((a / "pool.json").read_text())
    assert (made["policy_epochs"], made["minibatch_steps"]) == (3, 50)
    assert (a / "best.npz").read_bytes() == (b / "best.npz").read_bytes()
    r = rl_pool("launch", "--pool-dir", tmp_path / "c", "--pool-size", 2, "--minibatch-steps", 50, *SHORT,
                "--iterations", 1, "--quiet", check=2)
    assert r.stderr.strip().splitlines() == ["rl-pool: error: --minibatch-steps needs --policy-epochs above 1"]


# The value network's epochs in minibatches (--value-minibatch-steps)


def test_value_minibatch_steps_are_adam_steps_on_each_minibatch_written_out():
    import jax
    import jax.numpy as jnp

    params, x, _, _, mask = _batch(4)
    targets = np.random.default_rng(5).normal(size=mask.shape) * mask
    opt = random_opt_state(params, 6, 3.0)
    limit = 10  # the episodes' limit: the time input is t / 10, not t / 7
    p1, opt1 = learner.value_minibatches(params, opt, x, targets, mask, 0.01, 2, 4, np.random.default_rng(9),
                                         SPEC, limit=limit)
    order, count = learner.minibatch_plan(mask, 4, 2, np.random.default_rng(9))
    assert count == 2 * 4
    names = [k for k in params if k.startswith("v_")]
    p, m, v = ({k: d[k] for k in names} for d in (params, opt.m, opt.v))
    for step in range(count):
        rows = [i for i in order[step] if i < mask.size]
        bi, ti = np.divmod(np.asarray(rows), mask.shape[1])

        def mse(q, bi=bi, ti=ti):
            err = policy.value(params | q, x[bi, ti], ti / limit, SPEC, jnp) - targets[bi, ti]
            return 0.5 * (err * err).mean()

        g = jax.grad(lambda q: -mse(q))(p)
        adam_ascent_by_hand(p, m, v, g, 3.0, 0.01, skip="-")  # the step count stays at 3
    for k in params:
        if k in p:
            np.testing.assert_allclose(p1[k], p[k], rtol=1e-10, atol=1e-14, err_msg=k)
            np.testing.assert_allclose(opt1.v[k], v[k], rtol=1e-10, atol=1e-16, err_msg=k)
        else:  # the policy and its moments stay where they were
            assert np.array_equal(p1[k], params[k]) and np.array_equal(opt1.m[k], opt.m[k])
    assert opt1.t == 3.0
    before = float(learner.value_loss(params, x, targets, mask, SPEC, limit))
    assert float(learner.value_loss(p1, x, targets, mask, SPEC, limit)) < before
    same, same_opt = learner.value_minibatches(params, opt, x, targets, mask, 0.01, 0, 4,
                                               np.random.default_rng(9), SPEC)
    assert same is params and same_opt is opt


def test_one_value_minibatch_of_the_whole_batch_is_a_value_epoch():
    """With room for the whole batch in one minibatch, a pass is :func:`learner.fit_value`'s step."""
    params, x, _, _, mask = _batch(6)
    targets = np.random.default_rng(7).normal(size=mask.shape) * mask
    opt = random_opt_state(params, 8, 2.0)
    mini, mopt = learner.value_minibatches(params, opt, x, targets, mask, 0.02, 3, mask.size,
                                           np.random.default_rng(0), SPEC)
    whole, wopt = learner.fit_value(params, opt, x, targets, mask, 0.02, 3, SPEC)
    for k in params:
        np.testing.assert_allclose(mini[k], whole[k], rtol=1e-9, atol=1e-13, err_msg=k)
        np.testing.assert_allclose(mopt.m[k], wopt.m[k], rtol=1e-9, atol=1e-15, err_msg=k)
    assert mopt.t == wopt.t == 2.0


def test_value_minibatch_options_need_a_critic():
    need = "--value-minibatch-steps needs --baseline value and --value-epochs above 1"
    with pytest.raises(UsageError, match=need):
        PoolConfig.merged({"value_minibatch_steps": 64}, None)
    with pytest.raises(UsageError, match=need):
        PoolConfig.merged({"value_minibatch_steps": 64, "baseline": "value", "value_epochs": 1}, None)
    made = PoolConfig.merged({"value_minibatch_steps": 64, "baseline": "value"}, None)
    assert made.value_minibatch_steps == 64


def test_a_member_with_value_minibatches_fits_its_critic_further_and_replays_exactly():
    """On real Swimmer episodes: the critic's minibatches take more steps than its whole-batch
    epochs, from a stream of their own (the episodes and the policy's step are the same), and the
    same seeds give the same bytes."""
    start, whole, mini, again = _swimmer_member_three_ways({"value_minibatch_steps": 40}, baseline="value",
                                                           value_epochs=3)
    assert mini.agent.to_bytes() == again.agent.to_bytes()
    assert mini.episode_returns == whole.episode_returns
    assert whole.agent.opt_t == mini.agent.opt_t == 1.0  # the critic's steps leave the count alone
    policy_arrays = [k for k in start.params if not k.startswith("v_")]
    for k in policy_arrays:  # the same REINFORCE step: the critic's later steps do not touch the policy
        assert np.array_equal(mini.agent.params[k], whole.agent.params[k]), k
    moved = lambda a: sum(np.linalg.norm(a.params[k] - start.params[k])  # noqa: E731
                          for k in start.params if k.startswith("v_"))
    assert moved(mini.agent) > moved(whole.agent)  # 2 passes of 6 minibatches against 2 whole-batch steps


def test_a_pool_refuses_value_minibatches_without_a_critic(tmp_path):
    r = rl_pool("launch", "--pool-dir", tmp_path / "p", "--pool-size", 2, "--value-minibatch-steps", 50, *SHORT,
                "--iterations", 1, "--quiet", check=2)
    assert r.stderr.strip().splitlines() == [
        "rl-pool: error: --value-minibatch-steps needs --baseline value and --value-epochs above 1"]
    assert not (tmp_path / "p").exists()
