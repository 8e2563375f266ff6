"""Where a Reacher-v5 agent loses its return: each fresh episode's return beside where its target lies.

    .venv/bin/python results/reacher-v5/episodes_by_target.py AGENT.npz [AGENT.npz ...]

Runs each agent (deterministic Beta mean) on the 50 fresh episodes of every ``rescore.json`` (reset
seeds 1000000+k) one at a time and prints, per agent, the mean return and its two parts (distance
and control), then the mean return of the episodes whose target lies in front of the arm's start
(angle within 90 degrees of the +x axis the arm points along at reset) and behind it, and how many
of the behind ones end with the fingertip still more than 0.05 from the target.
"""

import sys

import gymnasium as gym
import numpy as np

from rl_pool.maths.agent import Agent

EPISODES, FIRST_SEED = 50, 1_000_000


def episodes(agent: Agent):
    env = gym.make("Reacher-v5")
    for k in range(EPISODES):
        obs, _ = env.reset(seed=FIRST_SEED + k)
        angle = float(np.arctan2(obs[5], obs[4]))  # the target's (x, y) are obs[4:6]
        total = dist = ctrl = 0.0
        done = False
        while not done:
            obs, reward, term, trunc, info = env.step(agent.act(obs))
            total, dist, ctrl = total + reward, dist + info["reward_dist"], ctrl + info["reward_ctrl"]
            done = term or trunc
        yield total, dist, ctrl, angle, float(np.linalg.norm(obs[8:10]))  # fingertip - target at the end
    env.close()


def main(paths):
    for path in paths:
        rows = np.array(list(episodes(Agent.load(path))))
        behind = np.abs(rows[:, 3]) > np.pi / 2
        missed = int((rows[behind, 4] > 0.05).sum())
        print(f"{path}: {rows[:, 0].mean():.2f} (distance {rows[:, 1].mean():.2f}, control {rows[:, 2].mean():.2f}); "
              f"in front {rows[~behind, 0].mean():.2f} ({int((~behind).sum())} episodes), "
              f"behind {rows[behind, 0].mean():.2f} ({int(behind.sum())}, {missed} of them end > 0.05 away)")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: episodes_by_target.py AGENT.npz [AGENT.npz ...]")
    main(sys.argv[1:])
