"""One iteration of one member: train for E episodes, then evaluate without updates.

Random streams are derived from ``(root seed, member, iteration)`` with
NumPy's ``SeedSequence``, so an iteration re-run after a crash draws exactly
the same numbers. Evaluation seeds depend on ``(root seed, iteration)`` only:
every member of an iteration is evaluated on the same episodes (common random
numbers), so selection compares branches on equal terms.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from rl_pool.config import PoolConfig
from rl_pool.learning.rollout import run_episodes
from rl_pool.maths import learner, normalizer, returns
from rl_pool.maths.agent import Agent

# Stream tags, so the same (seed, member, iteration) never feeds two purposes.
_TRAIN_ENV, _TRAIN_ACT, _EVAL_ENV, _EVAL_ACT, _LR_ADAPT, _MINIBATCH, _VALUE_MINIBATCH = 0, 1, 2, 3, 4, 5, 6
LR_BOUNDS = (1e-5, 10.0)


def _seq(*words: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(w) for w in words])


def env_seeds(seq: np.random.SeedSequence, n: int) -> list[int]:
    return [int(s) for s in seq.generate_state(n, dtype=np.uint32)]


def train_streams(seed: int, member: int, iteration: int, n_episodes: int):
    """``(env reset seeds, action generator)`` for a member's training in an iteration."""
    seeds = env_seeds(_seq(seed, member, iteration, _TRAIN_ENV), n_episodes)
    return seeds, np.random.Generator(np.random.PCG64(_seq(seed, member, iteration, _TRAIN_ACT)))


def eval_streams(seed: int, iteration: int, n_episodes: int):
    """The evaluation episodes of an iteration, shared by all members."""
    seeds = env_seeds(_seq(seed, 2**31 - 1, iteration, _EVAL_ENV), n_episodes)
    return seeds, np.random.Generator(np.random.PCG64(_seq(seed, 2**31 - 1, iteration, _EVAL_ACT)))


def adapted_learning_rate(seed: int, member: int, iteration: int, own: float, winner: float | None,
                          won: bool, factor: float) -> float:
    """The learning rate for ``iteration + 1`` under population-based adaptation.

    A member whose branch won keeps its rate; one that lost takes the winner's
    rate times ``factor`` or ``1 / factor`` (a fair coin from its own seeded
    stream), so the pool keeps probing rates around what currently works.
    """
    if factor <= 0 or won or winner is None:
        return own
    coin = np.random.Generator(np.random.PCG64(_seq(seed, member, iteration, _LR_ADAPT))).random()
    lr = winner * (factor if coin < 0.5 else 1.0 / factor)
    return float(min(max(lr, LR_BOUNDS[0]), LR_BOUNDS[1]))


@dataclass
class TrainResult:
    agent: Agent
    steps: int
    seconds: float
    episode_returns: list[float]
    grad_norms: list[float]


@dataclass
class EvalResult:
    returns: list[float]
    steps: int
    seconds: float
    lengths: list[int]
    shift: float = 0.0

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def score(self) -> float:
        """What selection compares: the mean return of the *training* objective, i.e. with
        ``reward_shift`` taken off every step (the env's own return when the shift is 0)."""
        return float(np.mean(np.asarray(self.returns) - self.shift * np.asarray(self.lengths)))

    def summary(self) -> dict:
        r = np.asarray(self.returns)
        return {"eval_return": float(r.mean()), "eval_std": float(r.std()),
                "eval_min": float(r.min()), "eval_max": float(r.max()),
                "eval_returns": [float(x) for x in r], "eval_score": self.score,
                "eval_lengths": [int(n) for n in self.lengths]}


def train(agent: Agent, envs, cfg: PoolConfig, lr: float, member: int, iteration: int) -> TrainResult:
    """REINFORCE on ``cfg.train_episodes`` episodes in batches of ``cfg.batch_episodes``."""
    t0 = time.perf_counter()
    seeds, rng = train_streams(cfg.seed, member, iteration, cfg.train_episodes)
    low, high = agent.low, agent.high
    params, norm, spec = agent.params, agent.norm, agent.spec
    opt = learner.OptState(agent.opt_m, agent.opt_v, agent.opt_t)
    T = agent.meta.max_episode_steps
    steps, ep_returns, gnorms = 0, [], []
    B = cfg.batch_episodes
    shuffle = (np.random.Generator(np.random.PCG64(_seq(cfg.seed, member, iteration, _MINIBATCH)))
               if cfg.minibatch_steps else None)
    value_shuffle = (np.random.Generator(np.random.PCG64(_seq(cfg.seed, member, iteration, _VALUE_MINIBATCH)))
                     if cfg.value_minibatch_steps else None)
    for k in range(cfg.updates_per_iteration):
        batch = run_episodes(envs, params, spec, norm, low, high, seeds[k * B:(k + 1) * B], T, rng,
                             deterministic=False)
        batch = batch.cut(learner.cut_length(batch.mask))  # padded to its longest episode, not to T
        x = normalizer.normalize(norm, batch.obs)
        # The shift (e.g. a survival bonus) only shapes training; returns reported stay the env's.
        rewards = batch.rewards - cfg.reward_shift * batch.mask if cfg.reward_shift else batch.rewards
        g = returns.discounted_returns(rewards, batch.mask, cfg.gamma)
        # The value network (if any) as it stands before this batch: fitted on earlier ones only.
        v = learner.values(params, x, spec, limit=T) if spec.value else None
        adv = returns.advantages(rewards, batch.mask, cfg.gamma, cfg.baseline, x, cfg.gae_lambda, v, g)
        targets = returns.value_targets(g, batch.mask) if spec.value else None
        # the policy that drew the batch, for the ratios of --policy-epochs' extra steps
        logp_old = learner.log_prob(params, x, batch.u, spec) if cfg.policy_epochs > 1 else None
        params, opt, gnorm = learner.update(params, opt, x, batch.u, adv, batch.mask, lr,
                                            cfg.optimizer, spec, targets, limit=T)
        if cfg.policy_epochs > 1 and cfg.minibatch_steps:
            params, opt = learner.policy_minibatches(params, opt, x, batch.u, adv, batch.mask, logp_old, lr, cfg.clip,
                                                     cfg.policy_epochs - 1, cfg.minibatch_steps, shuffle, spec)
        elif cfg.policy_epochs > 1:
            params, opt = learner.policy_epochs(params, opt, x, batch.u, adv, batch.mask, logp_old, lr,
                                                cfg.clip, cfg.policy_epochs - 1, spec)
        if spec.value and cfg.value_epochs > 1:
            if cfg.value_minibatch_steps:
                params, opt = learner.value_minibatches(params, opt, x, targets, batch.mask, lr, cfg.value_epochs - 1,
                                                        cfg.value_minibatch_steps, value_shuffle, spec, limit=T)
            else:
                params, opt = learner.fit_value(params, opt, x, targets, batch.mask, lr, cfg.value_epochs - 1, spec,
                                                limit=T)
        norm = normalizer.update(norm, batch.obs[batch.mask > 0])
        steps += batch.steps
        ep_returns.extend(float(r) for r in batch.returns)
        gnorms.append(gnorm)
    new = agent.evolve(params=params, norm=norm, opt_m=opt.m, opt_v=opt.v, opt_t=opt.t)
    return TrainResult(new, steps, time.perf_counter() - t0, ep_returns, gnorms)


def evaluate(agent: Agent, envs, cfg: PoolConfig, iteration: int) -> EvalResult:
    """``cfg.eval_episodes`` episodes without updates on the iteration's shared seeds."""
    t0 = time.perf_counter()
    seeds, rng = eval_streams(cfg.seed, iteration, cfg.eval_episodes)
    batch = run_episodes(envs, agent.params, agent.spec, agent.norm, agent.low, agent.high, seeds,
                         agent.meta.max_episode_steps, rng,
                         deterministic=cfg.eval_mode == "mean", record=False)
    return EvalResult([float(r) for r in batch.returns], batch.steps, time.perf_counter() - t0,
                      [int(n) for n in batch.lengths], cfg.reward_shift)
