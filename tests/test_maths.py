"""Pure maths against independent references (scipy, plain loops, finite differences)."""

import dataclasses

import numpy as np
import pytest
import scipy.special
import scipy.stats

from rl_pool.maths import learner, normalizer, policy, returns

from .helpers import finite_differences


def test_beta_log_prob_matches_scipy():
    rng = np.random.default_rng(0)
    a = rng.uniform(1, 20, size=200)
    b = rng.uniform(1, 20, size=200)
    u = rng.uniform(0.001, 0.999, size=200)
    ours = policy.beta_log_prob(u, a, b)
    np.testing.assert_allclose(ours, scipy.stats.beta.logpdf(u, a, b), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("u", [0.0, 1.0])
def test_beta_log_prob_finite_at_exact_bounds(u):
    # A float Beta draw can be exactly 0 or 1; the clip keeps the log finite and
    # equal to the density at the clipped point.
    a, b = np.array([1.3, 5.0]), np.array([4.0, 1.0001])
    ours = policy.beta_log_prob(np.array([u, u]), a, b)
    assert np.all(np.isfinite(ours))
    clipped = np.clip(u, policy.EPS, 1 - policy.EPS)
    np.testing.assert_allclose(ours, scipy.stats.beta.logpdf(clipped, a, b), rtol=1e-9)


SPECS = [policy.PolicySpec("linear", (), "exp"), policy.PolicySpec("linear", (), "softplus"),
         policy.PolicySpec("mlp", (5,), "exp"), policy.PolicySpec("mlp", (6, 4), "softplus")]
LINKS = {"softplus": lambda z: np.log1p(np.exp(z)) + 1,
         "exp": lambda z: np.exp(np.minimum(z, policy.Z_MAX)) + 1}


def _random_params(spec, obs, act, seed, scale=1.0):
    rng = np.random.default_rng(seed)
    return {k: rng.normal(scale=scale, size=s) for k, s in policy.param_shapes(spec, obs, act).items()}


def _reference_z(spec, params, x):
    """The pre-activations by a plain per-row loop over the layers (independent of the vectorised code)."""
    out = []
    for row in x:
        if spec.kind == "linear":
            out.append(np.append(row, 1.0) @ params["w"])
            continue
        h = row
        for k in range(len(spec.hidden)):
            h = np.array([np.tanh(sum(h[i] * params[f"w{k}"][i, j] for i in range(len(h)))
                                  + params[f"b{k}"][j]) for j in range(spec.hidden[k])])
        last = len(spec.hidden)
        out.append(h @ params[f"w{last}"] + params[f"b{last}"])
    return np.array(out)


@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_beta_params_match_a_layer_by_layer_reference(spec):
    params = _random_params(spec, 4, 3, seed=1, scale=1.5)
    x = np.random.default_rng(1).normal(size=(7, 4))
    a, b = policy.beta_params(params, x, spec)
    z = _reference_z(spec, params, x)
    np.testing.assert_allclose(a, LINKS[spec.link](z[:, :3]), rtol=1e-12)
    np.testing.assert_allclose(b, LINKS[spec.link](z[:, 3:]), rtol=1e-12)
    assert a.min() >= 1 and b.min() >= 1


@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_log_prob_jax_equals_numpy(spec):
    import jax.numpy as jnp
    from jax.scipy.special import gammaln

    params = _random_params(spec, 3, 2, seed=2)
    rng = np.random.default_rng(2)
    x = rng.normal(size=(10, 3))
    u = rng.uniform(size=(10, 2))
    jparams = {k: jnp.asarray(v) for k, v in params.items()}
    np.testing.assert_allclose(policy.log_prob_unit(params, x, u, spec),
                               np.asarray(policy.log_prob_unit(jparams, jnp.asarray(x), jnp.asarray(u), spec,
                                                               xp=jnp, gammaln=gammaln)), rtol=1e-10)
    np.testing.assert_allclose(policy.preactivations(params, x, spec),
                               np.asarray(policy.preactivations(jparams, jnp.asarray(x), spec, xp=jnp)),
                               rtol=1e-12)


def test_mlp_log_density_matches_scipy():
    spec = policy.PolicySpec("mlp", (8, 8), "exp")
    params = _random_params(spec, 5, 3, seed=9, scale=0.7)
    rng = np.random.default_rng(9)
    x = rng.normal(size=(6, 5))
    u = rng.uniform(0.01, 0.99, size=(6, 3))
    z = _reference_z(spec, params, x)
    a, b = LINKS["exp"](z[:, :3]), LINKS["exp"](z[:, 3:])
    want = scipy.stats.beta.logpdf(u, a, b).sum(axis=1)
    np.testing.assert_allclose(policy.log_prob_unit(params, x, u, spec), want, rtol=1e-10)


def test_init_is_deterministic_from_the_seed_and_starts_at_the_same_policy():
    spec = policy.PolicySpec("mlp", (64, 64), "exp")
    p0 = policy.init_params(spec, 17, 6, seed=3)
    p0b = policy.init_params(spec, 17, 6, seed=3)
    p1 = policy.init_params(spec, 17, 6, seed=4)
    assert list(p0) == ["w0", "b0", "w1", "b1", "w2", "b2"]
    assert {k: v.shape for k, v in p0.items()} == policy.param_shapes(spec, 17, 6)
    for k in p0:
        np.testing.assert_array_equal(p0[k], p0b[k])
    assert not np.array_equal(p0["w0"], p1["w0"])
    # LeCun scaling of hidden weights; the output layer starts at zero: alpha = beta = 2 everywhere
    assert np.std(p0["w1"]) == pytest.approx(1 / 8, rel=0.1)
    x = np.random.default_rng(0).normal(size=(5, 17))
    for s in (spec, policy.PolicySpec()):
        a, b = policy.beta_params(policy.init_params(s, 17, 6, seed=3), x, s)
        np.testing.assert_array_equal(a, 2.0)
        np.testing.assert_array_equal(b, 2.0)


@pytest.mark.parametrize("kind, hidden", [("linear", ()), ("mlp", (16,))])
@pytest.mark.parametrize("link", ["exp", "softplus"])
def test_initial_shape_sets_alpha_and_beta_everywhere(kind, hidden, link):
    spec = policy.PolicySpec(kind, hidden, link)
    x = np.random.default_rng(1).normal(size=(7, 11))
    for shape in (1.5, 5.0, 30.0):
        a, b = policy.beta_params(policy.init_params(spec, 11, 3, seed=2, shape=shape), x, spec)
        np.testing.assert_allclose(a, shape, rtol=1e-12)
        np.testing.assert_allclose(b, shape, rtol=1e-12)
        # the action variance the docstring states, against scipy's Beta
        assert scipy.stats.beta(shape, shape).var() == pytest.approx(1 / (4 * (2 * shape + 1)))
    # no shape: the same parameters as ever (committed agents and histories replay)
    plain = policy.init_params(spec, 11, 3, seed=2)
    assert all(np.array_equal(plain[k], v) for k, v in policy.init_params(spec, 11, 3, seed=2, shape=None).items())
    for bad in (1.0, 0.5, float("nan"), 1e6):
        with pytest.raises(ValueError):
            policy.init_params(spec, 11, 3, seed=2, shape=bad)


def test_policy_spec_refuses_nonsense():
    for bad in [("conv", ()), ("linear", (3,)), ("mlp", ()), ("mlp", (0,)), ("mlp", (10**6,))]:
        with pytest.raises(ValueError):
            policy.PolicySpec(*bad)
    assert policy.PolicySpec.from_json("linear-exp") == policy.PolicySpec("linear", (), "exp")
    assert policy.PolicySpec.from_json("linear") == policy.PolicySpec("linear", (), "softplus")
    spec = policy.PolicySpec("mlp", (3, 2), "softplus")
    assert policy.PolicySpec.from_json(spec.to_json()) == spec


def _loop_returns(r, gamma):
    out = []
    for t in range(len(r)):
        out.append(sum(gamma ** (k - t) * r[k] for k in range(t, len(r))))
    return out


@pytest.mark.parametrize("gamma", [1.0, 0.99, 0.5, 0.0])
def test_returns_match_python_loop(gamma):
    rng = np.random.default_rng(3)
    lengths = [7, 3, 7, 1]
    rewards = rng.normal(size=(4, 7))
    mask = np.zeros((4, 7))
    for b, n in enumerate(lengths):
        mask[b, :n] = 1
    g = returns.discounted_returns(rewards, mask, gamma)
    for b, n in enumerate(lengths):
        np.testing.assert_allclose(g[b, :n], _loop_returns(list(rewards[b, :n]), gamma), rtol=1e-12)
        assert np.all(g[b, n:] == 0)


def test_time_baseline_leaves_own_episode_out():
    g = np.array([[3.0, 2.0, 1.0], [5.0, 4.0, 0.0], [7.0, 0.0, 0.0]])
    mask = np.array([[1, 1, 1], [1, 1, 0], [1, 0, 0]], dtype=float)
    b = returns.time_baseline(g, mask)
    for i in range(3):
        for t in range(3):
            others = [g[j, t] for j in range(3) if j != i and mask[j, t]]
            want = np.mean(others) if (mask[i, t] and others) else 0.0
            assert b[i, t] == pytest.approx(want)


def _ragged_batch(rng, B=6, T=9, d=3):
    lengths = rng.integers(3, T + 1, B)
    mask = (np.arange(T)[None, :] < lengths[:, None]).astype(float)
    obs = rng.normal(size=(B, T, d)) * 3
    g = rng.normal(size=(B, T)) * mask
    return g, mask, obs


def test_linear_baseline_matches_a_ridge_fit_written_out_per_step():
    rng = np.random.default_rng(5)
    g, mask, obs = _ragged_batch(rng)
    got = returns.linear_baseline(g, mask, obs, reg=1e-3)
    B, T = obs.shape[:2]
    want = np.zeros((B, T))
    for fold in (0, 1):
        rows, ys = [], []
        for b in range(B):
            if b % 2 == fold:
                continue
            for t in range(T):
                if mask[b, t]:
                    o = np.clip(obs[b, t], -10, 10)
                    rows.append([*o, *(o ** 2), t / 100, (t / 100) ** 2, (t / 100) ** 3, 1.0])
                    ys.append(g[b, t])
        x, y = np.array(rows), np.array(ys)
        k = x.shape[1]
        lam = 1e-3 * max(1.0, np.trace(x.T @ x) / k)
        # ridge as least squares on the augmented system [x; sqrt(lam) I] w = [y; 0]
        w = np.linalg.lstsq(np.vstack([x, np.sqrt(lam) * np.eye(k)]), np.concatenate([y, np.zeros(k)]),
                            rcond=None)[0]
        for b in range(B):
            if b % 2 == fold:
                for t in range(T):
                    if mask[b, t]:
                        o = np.clip(obs[b, t], -10, 10)
                        want[b, t] = np.array([*o, *(o ** 2), t / 100, (t / 100) ** 2, (t / 100) ** 3, 1.0]) @ w
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)


def test_linear_baseline_is_fitted_on_the_other_episodes_and_finds_a_linear_return():
    rng = np.random.default_rng(6)
    g, mask, obs = _ragged_batch(rng)
    b0 = returns.linear_baseline(g, mask, obs)
    g2 = g.copy()
    g2[2] += 100.0 * mask[2]  # episode 2 (even) is fitted on the odd ones: its baseline does not move
    b2 = returns.linear_baseline(g2, mask, obs)
    np.testing.assert_array_equal(b2[::2], b0[::2])
    assert not np.allclose(b2[1::2], b0[1::2])
    # a return that is a linear function of the features is predicted (almost) exactly
    _, mask3, obs3 = _ragged_batch(rng, B=8, T=200)
    w = rng.normal(size=2 * obs3.shape[2] + 4)
    exact = (returns.baseline_features(obs3, mask3) @ w) * mask3
    np.testing.assert_allclose(returns.linear_baseline(exact, mask3, obs3, reg=1e-12), exact, rtol=1e-6, atol=1e-6)
    assert not returns.linear_baseline(g[:1], mask[:1], obs[:1]).any()  # one episode: nothing to fit on
    adv = returns.advantages(g, mask, 1.0, "linear", obs)
    assert adv.shape == g.shape and np.all(adv[mask == 0] == 0)
    with pytest.raises(ValueError, match="observations"):
        returns.advantages(g, mask, 1.0, "linear")


def _loop_gae(r, v, gamma, lam):
    """GAE of one episode written out as the double sum: sum_k (gamma lam)^k delta_{t+k}."""
    n = len(r)
    nxt = [v[t + 1] if t + 1 < n else 0.0 for t in range(n)]
    delta = [r[t] + gamma * nxt[t] - v[t] for t in range(n)]
    return [sum((gamma * lam) ** (k - t) * delta[k] for k in range(t, n)) for t in range(n)]


@pytest.mark.parametrize("gamma,lam", [(1.0, 0.95), (0.99, 0.9), (0.99, 0.0), (0.5, 1.0)])
def test_gae_matches_the_double_sum_per_episode(gamma, lam):
    rng = np.random.default_rng(8)
    _, mask, _ = _ragged_batch(rng)
    rewards = rng.normal(size=mask.shape) * 2 + 100.0 * (1 - mask)  # junk past the end must not count
    values = rng.normal(size=mask.shape) + 50.0 * (1 - mask)
    got = returns.gae(rewards, mask, values, gamma, lam)
    for b in range(mask.shape[0]):
        n = int(mask[b].sum())
        np.testing.assert_allclose(got[b, :n], _loop_gae(rewards[b, :n], values[b, :n], gamma, lam),
                                   rtol=1e-10, atol=1e-10)
        assert np.all(got[b, n:] == 0)


def test_gae_at_lambda_one_is_the_return_minus_the_baseline():
    rng = np.random.default_rng(9)
    _, mask, obs = _ragged_batch(rng, B=8, T=30)
    rewards = rng.normal(size=mask.shape)
    for gamma in (1.0, 0.97):
        g = returns.discounted_returns(rewards, mask, gamma)
        b = returns.linear_baseline(g, mask, obs)
        np.testing.assert_allclose(returns.gae(rewards, mask, b, gamma, 1.0), (g - b) * mask, atol=1e-9)
        # lam = 1 is the plain difference exactly (pools made before lambda replay bit for bit)
        plain = (g - b) * mask
        np.testing.assert_array_equal(returns.advantages(rewards, mask, gamma, "linear", obs, lam=1.0),
                                      plain / plain[mask > 0].std() * mask)
        low = returns.advantages(rewards, mask, gamma, "linear", obs, lam=0.9)
        want = returns.gae(rewards, mask, b, gamma, 0.9)
        np.testing.assert_allclose(low, want / want[mask > 0].std() * mask, rtol=1e-12)
    # lam = 0: one-step temporal differences with the time baseline as the value
    g = returns.discounted_returns(rewards, mask, 1.0)
    b = returns.time_baseline(g, mask)
    nxt = np.concatenate([b[:, 1:], np.zeros((b.shape[0], 1))], axis=1)
    td = (rewards + nxt - b) * mask
    np.testing.assert_allclose(returns.gae(rewards, mask, b, 1.0, 0.0), td, atol=1e-12)


def test_advantages_unit_std_on_valid_steps():
    rng = np.random.default_rng(4)
    rewards = rng.normal(size=(5, 20))
    mask = np.ones((5, 20))
    mask[2, 12:] = 0
    adv = returns.advantages(rewards, mask, 1.0, "time")
    assert adv[mask > 0].std() == pytest.approx(1.0)
    assert np.all(adv[mask == 0] == 0)


def test_normalizer_matches_numpy_for_any_batching():
    rng = np.random.default_rng(5)
    data = rng.normal(3.0, 2.5, size=(1000, 6))
    st = normalizer.init(6)
    for chunk in np.array_split(data, [1, 2, 50, 333, 334, 999]):
        st = normalizer.update(st, chunk)
    assert st.count == 1000
    np.testing.assert_allclose(st.mean, data.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(normalizer.std(st), np.sqrt(data.var(axis=0) + normalizer.VAR_EPS), rtol=1e-12)


def test_normalizer_clips_and_starts_as_identity():
    st = normalizer.init(2)
    np.testing.assert_array_equal(normalizer.normalize(st, np.array([1.0, -2.0])), [1.0, -2.0])
    st = normalizer.update(st, np.array([[0.0, 0.0], [2.0, 2.0]]))
    assert normalizer.normalize(st, np.array([1e6, -1e6])).tolist() == [normalizer.CLIP, -normalizer.CLIP]


def _batch(seed=6, B=3, T=5, obs=3, act=2, spec=SPECS[0]):
    rng = np.random.default_rng(seed)
    params = _random_params(spec, obs, act, seed, scale=0.5)
    x = rng.normal(size=(B, T, obs))
    u = rng.uniform(0.01, 0.99, size=(B, T, act))
    adv = rng.normal(size=(B, T))
    mask = np.ones((B, T))
    mask[1, 3:] = 0
    return params, x, u, adv, mask


@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_policy_gradient_matches_finite_differences(spec):
    params, x, u, adv, mask = _batch(spec=spec)

    def J(p):
        logp = policy.log_prob_unit(p, x, u, spec, gammaln=scipy.special.gammaln)
        return (logp * adv * mask).sum() / mask.sum()

    g = learner.policy_gradient(params, x, u, adv, mask, spec)
    assert set(g) == set(params)
    for name, fd in finite_differences(J, params).items():
        np.testing.assert_allclose(np.asarray(g[name]), fd, rtol=1e-6, atol=1e-8, err_msg=name)


def test_padding_does_not_change_the_gradient():
    spec = SPECS[2]
    params, x, u, adv, mask = _batch(spec=spec)
    g1 = learner.policy_gradient(params, x, u, adv, mask, spec)
    x2, u2, adv2 = x.copy(), u.copy(), adv.copy()
    x2[mask == 0] = 123.0
    u2[mask == 0] = 0.5
    adv2[mask == 0] = -9.0
    g2 = learner.policy_gradient(params, x2, u2, adv2, mask, spec)
    for k in params:
        np.testing.assert_array_equal(np.asarray(g1[k]), np.asarray(g2[k]))


@pytest.mark.parametrize("spec", [SPECS[0], SPECS[3]], ids=str)
def test_adam_and_normalized_steps_match_hand_computation(spec):
    params, x, u, adv, mask = _batch(spec=spec)
    g = {k: np.asarray(v) for k, v in learner.policy_gradient(params, x, u, adv, mask, spec).items()}
    gnorm_want = np.sqrt(sum((v * v).sum() for v in g.values()))
    opt = learner.init_opt_state(params)
    p1, opt1, gnorm = learner.update(params, opt, x, u, adv, mask, 0.01, "adam", spec)
    for k in params:
        m = 0.1 * g[k]
        v = 0.001 * g[k] * g[k]
        want = params[k] + 0.01 * (m / 0.1) / (np.sqrt(v / 0.001) + learner.ADAM_EPS)
        np.testing.assert_allclose(p1[k], want, rtol=1e-10)
        np.testing.assert_allclose(opt1.m[k], m, rtol=1e-12)
    assert opt1.t == 1 and gnorm == pytest.approx(gnorm_want)
    p2, _, _ = learner.update(params, opt, x, u, adv, mask, 0.05, "normalized", spec)
    step = np.sqrt(sum(((p2[k] - params[k]) ** 2).sum() for k in params))
    assert step == pytest.approx(0.05, rel=1e-10)
    for k in params:
        np.testing.assert_allclose((p2[k] - params[k]) / 0.05, g[k] / gnorm_want, rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("spec", [SPECS[0], SPECS[2]], ids=str)
def test_gradient_ascent_raises_objective(spec):
    params, x, u, adv, mask = _batch(seed=7, spec=spec)
    j0 = float(learner.objective(params, x, u, adv, mask, spec))
    p1, _, _ = learner.update(params, learner.init_opt_state(params), x, u, adv, mask, 1e-3, "normalized", spec)
    assert float(learner.objective(p1, x, u, adv, mask, spec)) > j0


def test_update_refuses_mismatched_shapes():
    params, x, u, adv, mask = _batch()
    with pytest.raises(ValueError):
        learner.update(params, learner.init_opt_state(params), x[:, :-1], u, adv, mask, 0.1, "adam", SPECS[0])


def test_adapted_learning_rate_rule():
    from rl_pool.learning.trainer import LR_BOUNDS, adapted_learning_rate

    assert adapted_learning_rate(0, 1, 5, 0.03, 0.003, won=True, factor=2) == 0.03
    assert adapted_learning_rate(0, 1, 5, 0.03, 0.003, won=False, factor=0) == 0.03
    seen = {round(adapted_learning_rate(0, 1, i, 0.03, 0.01, won=False, factor=2), 12) for i in range(40)}
    assert seen == {0.02, 0.005}
    # reproducible: a function of (seed, member, iteration) only
    assert [adapted_learning_rate(3, 0, i, 1, 1, False, 1.5) for i in range(10)] == \
        [adapted_learning_rate(3, 0, i, 9, 1, False, 1.5) for i in range(10)]
    assert adapted_learning_rate(0, 0, 0, 1, 100.0, False, 4) <= LR_BOUNDS[1]


def test_random_streams_common_for_evaluation_distinct_for_training():
    from rl_pool.learning.trainer import eval_streams, train_streams

    s0, r0 = train_streams(7, 0, 3, 4)
    s1, r1 = train_streams(7, 1, 3, 4)
    s0b, r0b = train_streams(7, 0, 3, 4)
    assert s0 == s0b and r0.random() == r0b.random()  # reproducible
    assert s0 != s1 and r0.random() != r1.random()  # members explore differently
    assert train_streams(7, 0, 4, 4)[0] != s0  # and differently each iteration
    e3, _ = eval_streams(7, 3, 5)
    assert e3 == eval_streams(7, 3, 5)[0] and e3 != eval_streams(7, 4, 5)[0]
    assert not set(e3) & set(s0 + s1)  # evaluation episodes are not training episodes


def test_gae_lambda_is_a_pool_setting_that_reaches_training_and_older_pools_read_as_one():
    from rl_pool.config import PoolConfig
    from rl_pool.errors import UsageError
    from rl_pool.learning import envs, trainer

    from .helpers import agent

    d = PoolConfig().validate().to_json()
    d.pop("gae_lambda")  # a pool made before the setting trained on the return minus the baseline
    assert PoolConfig.from_json(d).gae_lambda == 1.0
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(UsageError, match="--gae-lambda"):
            PoolConfig(gae_lambda=bad).validate()
    cfg = PoolConfig(max_episode_steps=60, train_episodes=4, batch_episodes=4, baseline="linear").validate()
    env_list = [envs.make(cfg.env, {"max_episode_steps": 60})[0] for _ in range(4)]
    start = agent(3)
    plain, again, low = (trainer.train(start, env_list, c, 0.05, 0, 1).agent
                         for c in (cfg, cfg, dataclasses.replace(cfg, gae_lambda=0.8)))
    assert all(np.array_equal(plain.params[n], again.params[n]) for n in plain.params)
    assert not all(np.array_equal(plain.params[n], low.params[n]) for n in plain.params)


@pytest.mark.parametrize("kind, hidden", [("linear", ()), ("mlp", (16, 8))])
def test_sharpened_multiplies_each_shapes_excess_over_one(kind, hidden):
    spec = policy.PolicySpec(kind, hidden, "exp")
    params = _random_params(spec, 5, 3, seed=4, scale=0.5)
    x = np.random.default_rng(4).normal(size=(9, 5))
    a, b = policy.beta_params(params, x, spec)
    for factor in (1.0, 2.5, 10.0):
        sharp = policy.sharpened(params, spec, factor)
        z = _reference_z(spec, sharp, x)  # the layer-by-layer reference, on the sharpened parameters
        np.testing.assert_allclose(np.exp(z[:, :3]) + 1, factor * (a - 1) + 1, rtol=1e-12)
        np.testing.assert_allclose(np.exp(z[:, 3:]) + 1, factor * (b - 1) + 1, rtol=1e-12)
        # less action noise: the Beta's variance falls (scipy's, at every state and action)
        if factor > 1:
            assert (scipy.stats.beta(factor * (a - 1) + 1, factor * (b - 1) + 1).var()
                    < scipy.stats.beta(a, b).var()).all()
    changed = [k for k in params if not np.array_equal(sharp[k], params[k])]  # only the output bias moves
    assert changed == (["w"] if kind == "linear" else [f"b{len(hidden)}"])
    if kind == "linear":  # the linear policy's bias is the last row of its weights
        np.testing.assert_array_equal(sharp["w"][:-1], params["w"][:-1])
    with pytest.raises(ValueError, match="exp link"):
        policy.sharpened(params, policy.PolicySpec(kind, hidden, "softplus"), 2.0)
