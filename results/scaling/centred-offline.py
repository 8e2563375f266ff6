"""Offline: at a locked parent, does a centred-rank (evolution strategies) combination of its branches beat it?

    python centred-offline.py POOL I [EPISODES]

The parent is the agent selected before iteration I of the pool in POOL; the branches are the
iteration's deposits (still on disk: the pool keeps its last five iterations' agents). Every
candidate is scored with mean actions on EPISODES fresh episodes (the seeds of iteration 10000 + I).
"""
import dataclasses
import json
import os
import sys

import numpy as np

from rl_pool.config import PoolConfig
from rl_pool.learning import envs, trainer
from rl_pool.maths.agent import Agent


def read_json(path):
    with open(path) as fh:
        return json.load(fh)


def load(root, rel):
    with open(os.path.join(root, rel), "rb") as fh:
        return Agent.from_bytes(fh.read())


def length(arrays):
    return float(np.sqrt(sum(np.sum(v * v) for v in arrays.values())))


def main(root, i, n_eval):
    cfg = dataclasses.replace(PoolConfig.from_json(read_json(f"{root}/pool.json")), eval_episodes=n_eval)
    parent = load(root, read_json(f"{root}/iterations/{i - 1:06d}/selected.json")["agent"])
    branches, scores = [], []
    for m in range(cfg.pool_size):
        scores.append(read_json(f"{root}/iterations/{i:06d}/member-{m:03d}.json")["eval_return"])
        branches.append(load(root, f"iterations/{i:06d}/member-{m:03d}.npz"))
    kw = dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps)
    env_list = [envs.make(cfg.env, kw)[0] for _ in range(n_eval)]

    def score(agent):  # fresh episodes: iteration 10000 + i's evaluation seeds
        return trainer.evaluate(agent, env_list, cfg, 10_000 + i).mean

    order = np.argsort(-np.array(scores))
    n = len(scores)
    ranks = np.empty(n)
    ranks[order] = np.arange(n)
    w = (n - 1) / 2 - ranks  # centred: the best +3.5 ... the worst -3.5 (8 branches)
    w = w / np.abs(w).sum()
    names = parent.params.keys()
    mean_step = {k: np.mean([b.params[k] - parent.params[k] for b in branches], axis=0) for k in names}
    d = {k: sum(wm * (b.params[k] - parent.params[k]) for wm, b in zip(w, branches, strict=True)) for k in names}
    blen = np.mean([length({k: b.params[k] - parent.params[k] for k in names}) for b in branches])
    print(f"iteration {i}: branch scores {sorted([round(s) for s in scores], reverse=True)}; "
          f"branch step {blen:.3f}, mean step {length(mean_step):.3f}, centred {length(d):.3f}")
    print("parent", round(score(parent)))
    for c in (0.25, 0.5, 1.0, 2.0):
        s = c * blen / length(d)
        print(f"centred, length {c} x branch",
              round(score(parent.evolve(params={k: parent.params[k] + s * d[k] for k in names}))))
    for c in (0.25, 0.5, 1.0):
        print(f"mean step x {c}", round(score(parent.evolve(params={k: parent.params[k] + c * mean_step[k]
                                                                     for k in names}))))
    best = branches[order[0]]
    print("best branch", round(scores[order[0]]), "fresh", round(score(best)))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 5)
