"""How far apart an agent's mean actions and its sampled actions score, and how much it explores.

    python benchmarks/action_noise.py AGENT.npz [AGENT.npz ...] [--episodes 10] [--sharpen 1,3,10]

REINFORCE climbs the return of the actions a policy samples; selection and the re-scores compare
the return of its mean actions. For each agent (optionally sharpened: every Beta shape's excess
over 1 times F, as ``--sharpen`` and ``--revert-sharpen`` do) the script plays the same episodes
(reset seeds 1000000+k) both ways and prints the two mean returns, and the median Beta
concentration alpha + beta over the states and action dimensions of the first mean-action episode, with the standard
deviation of an action in (0, 1) that a symmetric Beta of that concentration has. Episodes run one
after another in this process.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from rl_pool.errors import UsageError


def _floats(text: str) -> list[float]:
    try:
        out = [float(x) for x in text.split(",")]
    except ValueError:
        raise UsageError(f"--sharpen: comma-separated factors >= 1, got {text!r}") from None
    if not out or any(not (np.isfinite(f) and f >= 1.0) for f in out):
        raise UsageError(f"--sharpen: comma-separated factors >= 1, got {text!r}")
    return out


def play(agent, env, seed: int, rng: np.random.Generator | None, shapes: bool = False) -> tuple[float, list[float]]:
    """One episode of at most the agent's episode length (the env is unwrapped: no time limit of
    its own): its return and, with ``shapes``, the concentration alpha + beta of every action
    dimension at each state."""
    obs, _ = env.reset(seed=seed)
    total, conc = 0.0, []
    for _ in range(agent.meta.max_episode_steps):
        if shapes:
            alpha, beta = agent.beta_params(obs)
            conc.extend(np.ravel(alpha + beta).tolist())
        action = agent.act(obs, rng=rng, deterministic=rng is None)
        obs, reward, term, trunc, _ = env.step(action)
        total += float(reward)
        if term or trunc:
            break
    return total, conc


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("agents", nargs="+")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--sharpen", default="1", help="comma-separated factors F >= 1 (default 1: the agent as it is)")
    args = p.parse_args(argv)
    try:
        if args.episodes < 1:
            raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
        factors = _floats(args.sharpen)
        from rl_pool.learning import envs
        from rl_pool.maths import policy
        from rl_pool.maths.agent import Agent

        print("agent | sharpen | mean actions | sampled actions | median alpha+beta | action std in (0, 1)")
        for path in args.agents:
            base = Agent.load(path)
            env = envs.make(base.meta.env, dict(base.meta.env_kwargs, max_episode_steps=base.meta.max_episode_steps))[0]
            for f in factors:
                agent = base if f == 1.0 else base.evolve(params=policy.sharpened(base.params, base.spec, f))
                rng = np.random.default_rng(0)
                means, samples, conc = [], [], []
                for k in range(args.episodes):
                    ret, c = play(agent, env, 1_000_000 + k, None, shapes=k == 0)
                    means.append(ret)
                    conc += c
                    samples.append(play(agent, env, 1_000_000 + k, rng)[0])
                med = float(np.median(conc))
                print(f"{path} | {f:g} | {np.mean(means):.1f} ± {np.std(means):.1f} | "
                      f"{np.mean(samples):.1f} ± {np.std(samples):.1f} | {med:.1f} | {np.sqrt(0.25 / (med + 1)):.3f}")
            env.close()
    except (UsageError, ValueError) as exc:
        print(f"action_noise: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
