"""More passes over each batch (``--policy-epochs``): PPO's clipped surrogate against a plain loop,
its gradient at the policy that drew the batch against REINFORCE's, the extra Adam steps against
Adam written out, the options' checks, and a real pool that takes them."""

import dataclasses
import json
import math

import numpy as np
import pytest

from rl_pool.config import PoolConfig
from rl_pool.errors import UsageError
from rl_pool.learning import envs, trainer
from rl_pool.maths import learner, policy
from rl_pool.maths.agent import Agent, AgentMeta

from .conftest import SHORT, rl_pool
from .helpers import adam_ascent_by_hand, finite_differences, random_opt_state

SPEC = policy.PolicySpec("mlp", (5,), "exp", (4,))
PLAIN = dataclasses.replace(SPEC, value=())


def _batch(seed=0, b=3, t=4, obs=3, act=2):
    rng = np.random.default_rng(seed)
    params = {k: rng.normal(scale=0.5, size=s) for k, s in policy.param_shapes(SPEC, obs, act).items()}
    x = rng.normal(size=(b, t, obs))
    u = rng.uniform(0.05, 0.95, size=(b, t, act))
    adv = rng.normal(size=(b, t))
    mask = np.ones((b, t))
    mask[b - 1, t // 2:] = 0
    return params, x, u, adv * mask, mask


def _log_beta_pdf(u, a, b):
    return (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
            + (a - 1) * math.log(u) + (b - 1) * math.log(1 - u))


def _surrogate_by_loop(params, x, u, adv, mask, logp_old, clip):
    alpha, beta = policy.beta_params(params, x, PLAIN)
    total, n = 0.0, 0.0
    for i in range(mask.shape[0]):
        for t in range(mask.shape[1]):
            if not mask[i, t]:
                continue
            logp = sum(_log_beta_pdf(u[i, t, j], alpha[i, t, j], beta[i, t, j]) for j in range(u.shape[2]))
            r = math.exp(logp - logp_old[i, t])
            total += min(r * adv[i, t], min(max(r, 1 - clip), 1 + clip) * adv[i, t])
            n += 1
    return total / n


def test_the_clipped_surrogate_matches_a_step_by_step_loop():
    params, x, u, adv, mask = _batch()
    other = {k: v + 0.3 * np.random.default_rng(1).normal(size=v.shape) for k, v in params.items()}
    logp_old = learner.log_prob(other, x, u, SPEC)  # ratios far from 1: both sides of the clip
    r = np.exp(learner.log_prob(params, x, u, SPEC) - logp_old)[mask > 0]
    assert (r > 1.2).any() and (r < 0.8).any() and ((r > 0.8) & (r < 1.2)).any()
    a = adv[mask > 0]
    assert ((r > 1.2) & (a > 0)).any() and ((r < 0.8) & (a < 0)).any()  # where the clip changes the min
    got = float(learner.clipped_objective(params, x, u, adv, mask, logp_old, 0.2, SPEC))
    assert got == pytest.approx(_surrogate_by_loop(params, x, u, adv, mask, logp_old, 0.2), rel=1e-12)


def test_at_the_policy_that_drew_the_batch_the_gradient_is_reinforces():
    params, x, u, adv, mask = _batch(2)
    logp_old = learner.log_prob(params, x, u, SPEC)
    import jax

    g = jax.grad(learner.clipped_objective)(params, x, u, adv, mask, logp_old, 0.2, SPEC)
    want = learner.policy_gradient(params, x, u, adv, mask, PLAIN)
    for k in want:
        np.testing.assert_allclose(np.asarray(g[k]), np.asarray(want[k]), rtol=1e-10, atol=1e-14, err_msg=k)
    # and away from it, the gradient is the surrogate's own (finite differences)
    moved = {k: v + 0.05 for k, v in params.items() if not k.startswith("v_")}
    g = jax.grad(learner.clipped_objective)(moved, x, u, adv, mask, logp_old, 0.2, SPEC)
    fd = finite_differences(lambda p: float(learner.clipped_objective(p, x, u, adv, mask, logp_old, 0.2, SPEC)),
                            moved)
    for k, want_k in fd.items():
        np.testing.assert_allclose(np.asarray(g[k]), want_k, rtol=1e-5, atol=1e-8, err_msg=k)


def test_policy_epochs_are_adam_steps_of_the_policy_alone_written_out():
    params, x, u, adv, mask = _batch(3)
    opt = random_opt_state(params, 4, 2.0)
    logp_old = learner.log_prob({k: v - 0.02 for k, v in params.items()}, x, u, SPEC)
    p1, opt1 = learner.policy_epochs(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 3, SPEC)
    import jax

    p, m, v = dict(params), dict(opt.m), dict(opt.v)
    for step in range(3):
        g = jax.grad(learner.clipped_objective)(p, x, u, adv, mask, logp_old, 0.2, SPEC)
        adam_ascent_by_hand(p, m, v, g, 2.0 + 1 + step, 0.01)
    for k in params:
        np.testing.assert_allclose(p1[k], p[k], rtol=1e-10, atol=1e-14, err_msg=k)
        np.testing.assert_allclose(opt1.m[k], m[k], rtol=1e-10, atol=1e-16, err_msg=k)
        np.testing.assert_allclose(opt1.v[k], v[k], rtol=1e-10, atol=1e-16, err_msg=k)
        if k.startswith("v_"):  # the value network and its moments stay where they were
            assert np.array_equal(p1[k], params[k]) and np.array_equal(opt1.m[k], opt.m[k])
    assert opt1.t == 5.0
    same, same_opt = learner.policy_epochs(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 0, SPEC)
    assert same is params and same_opt is opt


def test_policy_epochs_skip_the_padding_after_the_longest_episode(monkeypatch):
    params, _, _, _, _ = _batch(5)
    rng = np.random.default_rng(6)
    x, u = rng.normal(size=(2, 230, 3)), rng.uniform(0.05, 0.95, size=(2, 230, 2))
    mask = np.zeros((2, 230))
    mask[0, :40], mask[1, :130] = 1, 1
    adv = rng.normal(size=(2, 230)) * mask
    opt = learner.OptState({k: np.zeros_like(v) for k, v in params.items()},
                           {k: np.zeros_like(v) for k, v in params.items()}, 1.0)
    logp_old = learner.log_prob(params, x, u, SPEC)
    assert learner.cut_length(mask) == 200
    cut, _ = learner.policy_epochs(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 2, SPEC)  # 200 steps
    monkeypatch.setattr(learner, "FIT_BUCKET", 10**6)
    whole, _ = learner.policy_epochs(params, opt, x, u, adv, mask, logp_old, 0.01, 0.2, 2, SPEC)
    for k in params:
        np.testing.assert_allclose(cut[k], whole[k], rtol=1e-9, atol=1e-13, err_msg=k)


def test_options_are_checked_and_older_pools_read_as_reinforce_alone():
    d = PoolConfig().validate().to_json()
    d.pop("policy_epochs")
    d.pop("clip")
    old = PoolConfig.from_json(d)
    assert (old.policy_epochs, old.clip) == (1, 0.2)
    for kw, word in (({"policy_epochs": 0}, "--policy-epochs"), ({"policy_epochs": 1001}, "--policy-epochs"),
                     ({"clip": 0.0}, "--clip"), ({"clip": float("nan")}, "--clip"),
                     ({"policy_epochs": 3, "optimizer": "normalized"}, "--policy-epochs")):
        with pytest.raises(UsageError, match=word):
            PoolConfig(**kw).validate()
    with pytest.raises(UsageError, match="--clip needs --policy-epochs above 1"):
        PoolConfig.merged({"clip": 0.1}, None)
    assert PoolConfig.merged({"clip": 0.1, "policy_epochs": 2}, None).clip == 0.1


def test_a_member_with_policy_epochs_moves_further_and_replays_exactly():
    """On real Swimmer episodes: one epoch is the REINFORCE step as before; more epochs step the
    policy further from it, and the same seeds give the same bytes."""
    cfg = PoolConfig(max_episode_steps=60, train_episodes=4, batch_episodes=4).validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 60})[0] for _ in range(4)]
    meta = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0), cfg.spec)
    start = Agent.initial(meta, seed=0)
    one = trainer.train(start, env_list, cfg, 0.01, 0, 0).agent
    more_cfg = dataclasses.replace(cfg, policy_epochs=4)
    more = trainer.train(start, env_list, more_cfg, 0.01, 0, 0).agent
    again = trainer.train(start, env_list, more_cfg, 0.01, 0, 0).agent
    assert more.to_bytes() == again.to_bytes()
    step = lambda a: np.linalg.norm(a.params["w"] - start.params["w"])  # noqa: E731
    assert step(more) > 2 * step(one)
    assert (one.opt_t, more.opt_t) == (1.0, 4.0)


def test_the_member_hands_the_drawing_policy_its_clip_and_k_minus_1_steps(monkeypatch):
    """The extra steps get the log-probabilities of the policy *before* the batch's REINFORCE step,
    the pool's clip and K - 1, and come after that step; with a value network too."""
    cfg = PoolConfig(max_episode_steps=60, train_episodes=4, batch_episodes=2, policy="mlp", hidden="4",
                     baseline="value", value_hidden="4", gamma=0.9, policy_epochs=3, clip=0.15).validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 60})[0] for _ in range(2)]
    meta = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0), cfg.spec)
    start = Agent.initial(meta, seed=0)
    calls, real = [], learner.policy_epochs

    def spy(params, opt, x, u, adv, mask, logp_old, lr, clip, steps, spec):
        calls.append((params, opt.t, x, u, logp_old, lr, clip, steps))
        return real(params, opt, x, u, adv, mask, logp_old, lr, clip, steps, spec)

    monkeypatch.setattr(learner, "policy_epochs", spy)
    first = start.params
    out = trainer.train(start, env_list, cfg, 0.01, 0, 0).agent
    assert len(calls) == 2 and [c[5:] for c in calls] == [(0.01, 0.15, 2)] * 2
    params, t, x, u, logp_old, *_ = calls[0]
    assert t == 1.0 and not np.array_equal(params["w1"], first["w1"])  # after the REINFORCE step
    np.testing.assert_array_equal(logp_old, learner.log_prob(first, x, u, cfg.spec))  # before it
    assert out.opt_t == 2 * 3 and "v_w0" in out.params


def test_a_pool_with_policy_epochs_records_them_and_replays_byte_for_byte(tmp_path):
    runs = []
    for name in ("a", "b"):
        d = tmp_path / name
        rl_pool("launch", "--pool-dir", d, "--pool-size", 2, "--policy-epochs", 3, "--clip", 0.1, *SHORT,
                "--iterations", 2, "--quiet", check=0)
        runs.append(d)
    a, b = runs
    made = json.loads((a / "pool.json").read_text())
    assert (made["policy_epochs"], made["clip"]) == (3, 0.1)
    assert (a / "best.npz").read_bytes() == (b / "best.npz").read_bytes()
