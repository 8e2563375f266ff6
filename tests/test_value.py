"""The learned state-value baseline (``--baseline value``): its network, targets and scale against
plain loops, its gradient against finite differences, its files, and real pools that train it."""

import dataclasses
import io
import json
import pathlib

import numpy as np
import pytest

from rl_pool.config import PoolConfig
from rl_pool.errors import UsageError
from rl_pool.learning import envs, trainer
from rl_pool.maths import learner, policy, returns
from rl_pool.maths.agent import Agent, AgentMeta

from .conftest import ROOT, SHORT, rl_pool
from .helpers import finite_differences, random_opt_state

SPEC = policy.PolicySpec("mlp", (5,), "exp", (6, 4))
LINEAR_SPEC = policy.PolicySpec("linear", (), "exp", (3,))


def _params(spec, obs=3, act=2, seed=0, scale=0.5):
    rng = np.random.default_rng(seed)
    return {k: rng.normal(scale=scale, size=s) for k, s in policy.param_shapes(spec, obs, act).items()}


def _value_by_loop(params, spec, row, t_frac):
    """One observation's value, unit by unit (independent of the vectorised code)."""
    h = [*row, t_frac]
    for k in range(len(spec.value)):
        w, b = params[f"v_w{k}"], params[f"v_b{k}"]
        h = [np.tanh(sum(h[i] * w[i, j] for i in range(len(h))) + b[j]) for j in range(w.shape[1])]
    last = len(spec.value)
    w, b = params[f"v_w{last}"], params[f"v_b{last}"]
    return sum(h[i] * w[i, 0] for i in range(len(h))) + b[0]


@pytest.mark.parametrize("spec", [SPEC, LINEAR_SPEC], ids=str)
def test_value_network_matches_a_unit_by_unit_loop(spec):
    params = _params(spec)
    x = np.random.default_rng(1).normal(size=(2, 4, 3))
    v = learner.values(params, x, spec)
    want = [[_value_by_loop(params, spec, x[b, t], t / 4) for t in range(4)] for b in range(2)]
    np.testing.assert_allclose(v, want, rtol=1e-12)
    # the policy's own numbers do not see the value network
    plain = dataclasses.replace(spec, value=())
    np.testing.assert_array_equal(policy.beta_params(params, x, spec)[0], policy.beta_params(params, x, plain)[0])


def test_value_network_starts_at_zero_and_leaves_the_policy_draws_alone():
    with_v = policy.init_params(SPEC, 3, 2, seed=4, shape=20.0)
    without = policy.init_params(dataclasses.replace(SPEC, value=()), 3, 2, seed=4, shape=20.0)
    assert set(with_v) - set(without) == {"v_w0", "v_b0", "v_w1", "v_b1", "v_w2", "v_b2"}
    for k in without:
        np.testing.assert_array_equal(with_v[k], without[k])
    assert np.all(learner.values(with_v, np.ones((1, 3, 3)), SPEC) == 0.0)
    assert np.std(with_v["v_w0"]) > 0.1  # hidden layers start random, as the policy's


def test_value_targets_standardise_the_valid_steps():
    rng = np.random.default_rng(2)
    g = rng.normal(5.0, 3.0, size=(3, 6))
    mask = np.ones((3, 6))
    mask[2, 2:] = 0
    y = returns.value_targets(g, mask)
    valid = [g[b, t] for b in range(3) for t in range(6) if mask[b, t]]
    mean = sum(valid) / len(valid)
    sd = (sum((v - mean) ** 2 for v in valid) / len(valid)) ** 0.5
    for b in range(3):
        for t in range(6):
            assert y[b, t] == pytest.approx((g[b, t] - mean) / sd if mask[b, t] else 0.0, abs=1e-12)


def test_value_baseline_scales_with_the_other_episodes_only():
    rng = np.random.default_rng(3)
    g = rng.normal(10.0, 4.0, size=(4, 5))
    mask = np.ones((4, 5))
    mask[1, 3:] = 0
    v = rng.normal(size=(4, 5))
    b = returns.value_baseline(g, mask, v)
    for i in range(4):
        others = [g[j, t] for j in range(4) if j != i for t in range(5) if mask[j, t]]
        mean, sd = np.mean(others), np.std(others)
        for t in range(5):
            assert b[i, t] == pytest.approx((mean + sd * v[i, t]) * mask[i, t], abs=1e-12)
    # an episode's own returns do not move its baseline
    g2 = g.copy()
    g2[0] += 100.0
    np.testing.assert_allclose(returns.value_baseline(g2, mask, v)[0], b[0], rtol=1e-12)
    assert np.all(returns.value_baseline(g[:1], mask[:1], v[:1]) == 0.0)  # nothing to scale with


def test_advantages_with_the_value_baseline_need_the_values():
    g = np.ones((2, 3))
    with pytest.raises(ValueError, match="value"):
        returns.advantages(g, np.ones((2, 3)), 1.0, "value")


def test_gradient_with_a_value_network_matches_finite_differences():
    import scipy.special

    rng = np.random.default_rng(6)
    params = _params(SPEC, seed=6)
    B, T = 3, 4
    x = rng.normal(size=(B, T, 3))
    u = rng.uniform(0.01, 0.99, size=(B, T, 2))
    adv, targets = rng.normal(size=(B, T)), rng.normal(size=(B, T))
    mask = np.ones((B, T))
    mask[1, 2:] = 0
    tf = np.broadcast_to(np.arange(T) / T, (B, T))

    def J(p):
        logp = policy.log_prob_unit(p, x, u, SPEC, gammaln=scipy.special.gammaln)
        err = np.array([[_value_by_loop(p, SPEC, x[b, t], tf[b, t]) for t in range(T)] for b in range(B)]) - targets
        return ((logp * adv * mask).sum() - 0.5 * (err * err * mask).sum()) / mask.sum()

    g = learner.policy_gradient(params, x, u, adv, mask, SPEC, targets)
    for name, fd in finite_differences(J, params).items():
        np.testing.assert_allclose(np.asarray(g[name]), fd, rtol=1e-6, atol=1e-8, err_msg=name)
    with pytest.raises(ValueError, match="targets"):
        learner.update(params, learner.init_opt_state(params), x, u, adv, mask, 0.1, "adam", SPEC)


def test_value_epochs_step_the_value_network_alone_as_adam_written_out():
    rng = np.random.default_rng(8)
    params = _params(SPEC, seed=8)
    x, targets = rng.normal(size=(3, 4, 3)), rng.normal(size=(3, 4))
    mask = np.ones((3, 4))
    mask[2, 1:] = 0
    opt = learner.OptState({k: rng.normal(size=v.shape) * 0.01 for k, v in params.items()},
                           {k: rng.uniform(0, 0.01, size=v.shape) for k, v in params.items()}, 3.0)
    p1, opt1 = learner.fit_value(params, opt, x, targets, mask, 0.02, 4, SPEC)
    # reference: Adam by hand up the gradient of the objective with no advantage (minus the value
    # loss; checked against finite differences above), as the combined step goes, so the moments
    # it leaves keep their sign; the step count held at 3
    p, m, v = dict(params), dict(opt.m), dict(opt.v)
    zero = np.zeros((3, 4))
    for _ in range(4):
        g = {k: np.asarray(a) for k, a in learner.policy_gradient(p, x, np.full((3, 4, 2), 0.5), zero, mask,
                                                                   SPEC, targets).items()}
        for k in params:
            if not k.startswith("v_"):
                continue
            m[k] = 0.9 * m[k] + 0.1 * g[k]
            v[k] = 0.999 * v[k] + 0.001 * g[k] * g[k]
            p[k] = p[k] + 0.02 * (m[k] / (1 - 0.9**3)) / (np.sqrt(v[k] / (1 - 0.999**3)) + learner.ADAM_EPS)
    for k in params:
        np.testing.assert_allclose(p1[k], p[k], rtol=1e-10, atol=1e-14, err_msg=k)
        np.testing.assert_allclose(opt1.m[k], m[k], rtol=1e-10, atol=1e-14, err_msg=k)
        if not k.startswith("v_"):  # the policy and its moments stay where they were
            assert np.array_equal(p1[k], params[k]) and np.array_equal(opt1.v[k], opt.v[k])
    assert opt1.t == 3.0
    assert float(learner.value_loss(p1, x, targets, mask, SPEC)) < float(learner.value_loss(params, x, targets,
                                                                                             mask, SPEC))


def test_value_epochs_skip_the_padding_after_the_longest_episode(monkeypatch):
    rng = np.random.default_rng(9)
    params = _params(SPEC, seed=9)
    x, targets = rng.normal(size=(3, 250, 3)), rng.normal(size=(3, 250))
    mask = np.zeros((3, 250))
    for b, n in enumerate((30, 120, 80)):
        mask[b, :n] = 1
    opt = learner.OptState({k: np.zeros_like(v) for k, v in params.items()},
                           {k: np.zeros_like(v) for k, v in params.items()}, 1.0)
    cut, _ = learner.fit_value(params, opt, x, targets, mask, 0.01, 3, SPEC)  # fitted on 200 steps
    monkeypatch.setattr(learner, "FIT_BUCKET", 10**6)
    whole, _ = learner.fit_value(params, opt, x, targets, mask, 0.01, 3, SPEC)  # on all 250
    for k in params:
        np.testing.assert_allclose(cut[k], whole[k], rtol=1e-9, atol=1e-13, err_msg=k)
    # the time input is the step over the episode limit (250), not over the cut
    np.testing.assert_allclose(learner.values(params, x[:, :200], SPEC, limit=250),
                               learner.values(params, x, SPEC)[:, :200], rtol=1e-12)


def test_an_update_on_a_batch_cut_after_its_longest_episode_is_the_update_on_the_whole_batch():
    """The trainer cuts each batch after its longest episode (rounded up to FIT_BUCKET) before the
    update: with the episodes' time limit given, the step is the whole padded batch's step."""
    rng = np.random.default_rng(11)
    params = _params(SPEC, seed=11)
    x, u = rng.normal(size=(3, 250, 3)), rng.uniform(0.05, 0.95, size=(3, 250, 2))
    mask = np.zeros((3, 250))
    for b, n in enumerate((30, 120, 80)):
        mask[b, :n] = 1
    adv, targets = rng.normal(size=(3, 250)) * mask, rng.normal(size=(3, 250)) * mask
    opt = random_opt_state(params, 11, 4.0)
    cut = learner.cut_length(mask)
    assert cut == 200
    whole = learner.update(params, opt, x, u, adv, mask, 0.01, "adam", SPEC, targets)
    short = learner.update(params, opt, x[:, :cut], u[:, :cut], adv[:, :cut], mask[:, :cut], 0.01, "adam", SPEC,
                           targets[:, :cut], limit=250)
    for k in params:
        np.testing.assert_allclose(short[0][k], whole[0][k], rtol=1e-12, atol=1e-15, err_msg=k)
        np.testing.assert_allclose(short[1].v[k], whole[1].v[k], rtol=1e-9, atol=1e-20, err_msg=k)
    assert short[2] == pytest.approx(whole[2], rel=1e-12)
    # without the limit the value network's time input would be the step over 200, not over 250
    wrong = learner.update(params, opt, x[:, :cut], u[:, :cut], adv[:, :cut], mask[:, :cut], 0.01, "adam", SPEC,
                           targets[:, :cut])
    assert not np.allclose(wrong[0]["v_w0"], whole[0]["v_w0"], rtol=1e-9, atol=0)


def test_a_member_trains_on_batches_cut_as_on_whole_ones(monkeypatch):
    """On real InvertedPendulum episodes, which end long before their limit of 250 steps: a
    member's training (value network, its extra epochs, clipped passes) on batches cut after the
    longest episode takes the same steps as on batches padded to the limit, up to rounding."""
    cfg = PoolConfig(env="InvertedPendulum-v5", max_episode_steps=250, train_episodes=4, batch_episodes=4,
                     baseline="value", gamma=0.99, gae_lambda=0.95, policy_epochs=2, value_hidden="8").validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 250})[0] for _ in range(4)]
    meta = AgentMeta(cfg.env, {}, 250, 4, 1, (-3.0,), (3.0,), cfg.spec)
    start = Agent.initial(meta, seed=0)
    cut = trainer.train(start, env_list, cfg, 0.01, 0, 0)
    monkeypatch.setattr(learner, "FIT_BUCKET", 10**6)  # nothing is cut: every batch padded to 250
    whole = trainer.train(start, env_list, cfg, 0.01, 0, 0)
    assert max(cut.episode_returns) < 100  # the episodes ended early, so the batch was cut
    assert cut.episode_returns == whole.episode_returns and cut.steps == whole.steps
    for k in start.params:
        np.testing.assert_allclose(cut.agent.params[k], whole.agent.params[k], rtol=1e-9, atol=1e-12, err_msg=k)
    assert cut.agent.opt_t == whole.agent.opt_t


def test_agent_files_carry_the_value_network_and_agents_without_one_keep_their_bytes():
    meta = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0), SPEC)
    a = Agent.initial(meta, seed=1)
    b = Agent.from_bytes(a.to_bytes())
    assert b.meta.spec == SPEC and set(b.params) == set(a.params)
    assert b.to_bytes() == a.to_bytes()
    plain = Agent.initial(dataclasses.replace(meta, spec=dataclasses.replace(SPEC, value=())), seed=1)
    assert json.loads(str(np.load(io.BytesIO(plain.to_bytes()))["meta"]))["policy"] == {
        "kind": "mlp", "hidden": [5], "link": "exp"}
    # an agent written before value networks existed (a HalfCheetah result committed then) reads and
    # writes back byte for byte
    before = "results/halfcheetah-v5/screening/preset-before-revert-sharpen-seed0/best.npz"
    committed = pathlib.Path(ROOT, before).read_bytes()
    assert Agent.from_bytes(committed).to_bytes() == committed


def test_value_hidden_is_a_pool_setting_that_older_pools_read_as_the_default():
    d = PoolConfig().validate().to_json()
    d.pop("value_hidden")
    d.pop("value_epochs")
    old = PoolConfig.from_json(d)
    # a pool made before the value epochs stepped its value network once per batch
    assert (old.value_hidden, old.value_epochs, PoolConfig().value_epochs) == ("64,64", 1, 10)
    assert PoolConfig().validate().spec.value == ()  # only --baseline value has the network
    assert PoolConfig(baseline="value", value_hidden="32").validate().spec.value == (32,)
    for bad in (0, 1001):
        with pytest.raises(UsageError, match="--value-epochs"):
            PoolConfig(baseline="value", value_epochs=bad).validate()
    for bad in ("", "64,,64", "0", "a,b"):
        with pytest.raises(UsageError, match="--value-hidden"):
            PoolConfig(baseline="value", value_hidden=bad).validate()


def test_the_value_network_learns_the_return_to_go():
    """On Swimmer with a discount, the network's standardised predictions on fresh episodes come
    to explain most of the targets' variance (a zero prediction explains none)."""
    cfg = PoolConfig(max_episode_steps=60, train_episodes=8, batch_episodes=8, gamma=0.9,
                     baseline="value", value_hidden="16,16", value_epochs=1).validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 60})[0] for _ in range(8)]
    meta = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0), cfg.spec)
    a = Agent.initial(meta, seed=0)

    def unexplained(agent, iteration):
        seeds, rng = trainer.train_streams(99, 0, iteration, 8)
        from rl_pool.learning.rollout import run_episodes
        batch = run_episodes(env_list, agent.params, agent.spec, agent.norm, agent.low, agent.high, seeds,
                             60, rng, deterministic=False)
        x = agent.normalize(batch.obs)
        y = returns.value_targets(returns.discounted_returns(batch.rewards, batch.mask, cfg.gamma), batch.mask)
        err = learner.values(agent.params, x, agent.spec) - y
        return float((err * err * batch.mask).sum() / (y * y * batch.mask).sum())

    start = a
    assert unexplained(start, 0) == pytest.approx(1.0)
    for it in range(40):
        a = trainer.train(a, env_list, cfg, 0.01, 0, it).agent
    one = unexplained(a, 1000)
    assert one < 0.5
    # more steps on each batch fit closer
    b, more = start, dataclasses.replace(cfg, value_epochs=10)
    for it in range(40):
        b = trainer.train(b, env_list, more, 0.01, 0, it).agent
    assert unexplained(b, 1000) < one


@pytest.mark.multiprocess
def test_a_merging_pool_with_the_value_baseline_replays_byte_for_byte(tmp_path):
    runs = []
    for name in ("a", "b"):
        d = tmp_path / name
        rl_pool("launch", "--pool-dir", d, "--pool-size", 4, "--learning-rates", "0.003,0.01,0.01,0.01",
                "--policy", "mlp", "--hidden", "8", "--baseline", "value", "--value-hidden", "8",
                "--gamma", 0.99, "--gae-lambda", 0.95, "--merge", "mean", "--selection", "branches", *SHORT, "--iterations", 3,
                "--quiet", check=0)
        runs.append(d)
    a, b = runs
    merged = 0
    for i in (1, 2, 3):
        # who wrote the decision, when, and its signature differ; the decision may not
        sel_a, sel_b = (json.loads((d / f"iterations/{i:06d}/selected.json").read_text()) for d in (a, b))
        for sel in (sel_a, sel_b):
            for key in ("selected_by", "time", "signature"):
                sel.pop(key)
        assert sel_a == sel_b
        merged += sel_a["winner"] == "merge"
    assert merged >= 1  # the value network went through a merge
    best = Agent.load(a / "best.npz")
    assert best.spec.value == (8,) and "v_w0" in best.params
    assert (a / "best.npz").read_bytes() == (b / "best.npz").read_bytes()
    out = json.loads(rl_pool("evaluate", a / "best.npz", "--episodes", 2, "--json", check=0).stdout)
    assert np.isfinite(out["mean_return"])
