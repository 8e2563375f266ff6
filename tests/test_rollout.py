"""Lockstep rollouts against one env stepped at a time in a plain loop (real MuJoCo)."""

import numpy as np
import pytest

from rl_pool.learning import envs
from rl_pool.learning.rollout import run_episodes
from rl_pool.maths import normalizer, policy


def _one_at_a_time(env, params, spec, norm, low, high, seed, max_steps):
    """The reference: one episode, one env, the policy's Beta mean, nothing batched."""
    mean, inv_std = normalizer.scale(norm)
    o, _ = env.reset(seed=seed)
    obs, rewards = [], []
    for _ in range(max_steps):
        x = np.clip((o - mean) * inv_std, -normalizer.CLIP, normalizer.CLIP)[None]
        alpha, beta = policy.beta_params(params, x, spec)
        u = policy.mean_unit(alpha, beta)[0]
        obs.append(o)
        o, r, terminated, _, _ = env.step(policy.to_action(u, low, high))
        rewards.append(r)
        if terminated:
            break
    return np.array(obs), np.array(rewards)


@pytest.mark.parametrize("env_id", ["Hopper-v5", "Swimmer-v5"])
def test_lockstep_episodes_equal_episodes_run_alone(env_id):
    """Hopper's episodes end at different steps: the envs still running keep their own states."""
    n, max_steps = 5, 120
    kwargs = {"reset_noise_scale": 0.3}  # starts far apart: Hopper's episodes end at different steps
    made = [envs.make(env_id, kwargs) for _ in range(n)]
    env_list, info = [e for e, _ in made], made[0][1]
    spec = policy.PolicySpec("mlp", (8,), "exp")
    rng = np.random.default_rng(0)
    params = {k: v + rng.normal(0, 0.5, v.shape)
              for k, v in policy.init_params(spec, info.obs_dim, info.act_dim, 1).items()}
    norm = normalizer.update(normalizer.init(info.obs_dim), rng.normal(0, 2, (50, info.obs_dim)))
    seeds = [11, 12, 13, 14, 15]
    got = run_episodes(env_list, params, spec, norm, info.low, info.high, seeds, max_steps, None, True)
    if env_id == "Hopper-v5":
        assert len(set(got.lengths.tolist())) > 1 and got.lengths.max() < max_steps  # ends differ
    ref_env = envs.make(env_id, kwargs)[0]
    for k, seed in enumerate(seeds):
        obs, rewards = _one_at_a_time(ref_env, params, spec, norm, info.low, info.high, seed, max_steps)
        T = len(rewards)
        assert got.lengths[k] == T
        np.testing.assert_allclose(got.obs[k, :T], obs, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.rewards[k, :T], rewards, rtol=0, atol=1e-12)
        assert got.returns[k] == pytest.approx(rewards.sum(), rel=1e-12)
        assert got.mask[k].sum() == T and not got.rewards[k, T:].any()
