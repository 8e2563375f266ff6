"""Episodes between gymnasium and NumPy: several envs stepped in lockstep.

The policy forward pass and the Beta draws are batched over the envs still
running, so their cost per env step shrinks with the batch while MuJoCo does
the real work. Observations are recorded raw; since the normaliser is frozen
during a rollout, the features the policy acted on are recomputed exactly
afterwards in one vectorised pass (the same elementwise operations).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rl_pool.maths import normalizer, policy


class Batch(NamedTuple):
    """A batch of episodes padded to ``T`` steps; ``mask`` is 1 on real steps."""

    obs: np.ndarray  # [B, T, obs_dim] raw observations the actions were taken on
    u: np.ndarray  # [B, T, act_dim] Beta samples in (0, 1)
    rewards: np.ndarray  # [B, T]
    mask: np.ndarray  # [B, T]
    returns: np.ndarray  # [B] undiscounted episode returns
    lengths: np.ndarray  # [B]

    @property
    def steps(self) -> int:
        return int(self.lengths.sum())

    def cut(self, n: int) -> Batch:
        """The batch padded only to ``n`` steps (at least its longest episode): what comes after is
        padding, and every sum over the batch skips it. Views, not copies."""
        if n >= self.mask.shape[1]:
            return self
        return self._replace(obs=self.obs[:, :n], u=self.u[:, :n], rewards=self.rewards[:, :n], mask=self.mask[:, :n])


def run_episodes(envs, params: dict, spec: policy.PolicySpec, norm, low, high, seeds, max_steps: int,
                 rng: np.random.Generator | None, deterministic: bool, record: bool = True):
    """Run one episode in each of ``envs[:len(seeds)]`` in lockstep.

    ``params``/``spec``: the policy (any kind of the family); ``norm``: frozen
    normaliser; ``seeds``: one reset seed per episode. Actions are Beta means if
    ``deterministic``, else draws from ``rng``. Returns a :class:`Batch`
    (arrays only when ``record``; otherwise ``obs``/``u``/``rewards``/``mask`` are None).
    """
    n = len(seeds)
    if n > len(envs):
        raise ValueError(f"{n} episodes need {n} envs, have {len(envs)}")
    obs_dim = norm.mean.shape[0]
    act_dim = low.shape[0]
    mean, inv_std = normalizer.scale(norm)
    span = high - low
    clip = normalizer.CLIP

    cur = np.empty((n, obs_dim))
    for k in range(n):
        o, _ = envs[k].reset(seed=int(seeds[k]))
        cur[k] = o
    if record:
        obs_buf = np.zeros((n, max_steps, obs_dim))
        u_buf = np.full((n, max_steps, act_dim), 0.5)
        rew_buf = np.zeros((n, max_steps))
        mask = np.zeros((n, max_steps))
    returns = np.zeros(n)
    lengths = np.zeros(n, dtype=np.int64)
    active = np.arange(n)
    live = active.tolist()  # ``active`` as Python ints, for the per-env loop
    all_active = True
    step_fns = [env.step for env in envs[:n]]

    # np.minimum/np.maximum rather than np.clip (the same numbers): with one env and a small
    # policy each step is a dozen tiny NumPy calls, and np.clip's Python wrapper costs as much
    # as the arithmetic (docs/cluster.md: where a member's CPU goes).
    for t in range(max_steps):
        o_act = cur if all_active else cur[active]
        x = (o_act - mean) * inv_std
        np.minimum(np.maximum(x, -clip, out=x), clip, out=x)
        ab = policy.shapes(policy.preactivations(params, x, spec), spec.link)
        a, b = ab[:, :act_dim], ab[:, act_dim:]
        if deterministic:
            u = a / (a + b)
        else:
            u = rng.beta(a, b)
            policy.clip_unit(u, out=u)
        actions = low + u * span
        at = slice(None) if all_active else active
        if record:
            obs_buf[at, t] = o_act
            u_buf[at, t] = u
            mask[at, t] = 1.0
        # The envs are stepped in a plain loop (MuJoCo's work); everything per step that NumPy
        # can do for the whole batch is done once, after it.
        obs_t, rew_t, ended = [], [], []
        for k, idx in enumerate(live):
            o, r, terminated, _, _ = step_fns[idx](actions[k])
            obs_t.append(o)
            rew_t.append(r)
            if terminated:
                ended.append(k)
        cur[at] = obs_t
        rew = np.asarray(rew_t, dtype=np.float64)
        returns[at] += rew
        if record:
            rew_buf[at, t] = rew
        lengths[at] += 1
        if ended:
            active = np.delete(active, ended)
            live = active.tolist()
            all_active = False
            if active.size == 0:
                break
    if not record:
        return Batch(None, None, None, None, returns, lengths)
    return Batch(obs_buf, u_buf, rew_buf, mask, returns, lengths)
