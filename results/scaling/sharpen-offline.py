"""Offline: from a locked parent, do branches beat it more often if its Beta shapes are sharpened first?

    python sharpen-offline.py POOL I F1,F2,...

For the agent selected before iteration I of the pool in POOL, sharpened F times (every Beta shape's
excess over 1 times F: log F added to the MLP's output bias), 8 branches train one iteration as
the pool trains them (member 0 at rate 0.001, the others at 0.003, the pool's seeds of iteration I);
the parent and each branch are scored with mean actions on 5 fresh episodes (iteration 10000 + I's
seeds). Two processes.
"""
import dataclasses
import json
import os
import sys
from multiprocessing import get_context

import numpy as np


def read_json(path):
    with open(path) as fh:
        return json.load(fh)


def work(args):
    root, i, f, m = args
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    from rl_pool.config import PoolConfig
    from rl_pool.learning import envs, trainer
    from rl_pool.maths.agent import Agent

    cfg = dataclasses.replace(PoolConfig.from_json(read_json(f"{root}/pool.json")), eval_episodes=5, batch_episodes=5)
    sel = read_json(f"{root}/iterations/{i - 1:06d}/selected.json")
    with open(os.path.join(root, sel["agent"]), "rb") as fh:
        parent = Agent.from_bytes(fh.read())
    last = max(int(k[1:]) for k in parent.params if k.startswith("b"))
    if f != 1:
        bias = parent.params[f"b{last}"].copy()
        bias += np.log(f)
        parent = parent.evolve(params=dict(parent.params, **{f"b{last}": bias}))
    kw = dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps)
    env_list = [envs.make(cfg.env, kw)[0] for _ in range(5)]
    if m < 0:
        return f, m, trainer.evaluate(parent, env_list, cfg, 10_000 + i).mean, None
    tr = trainer.train(parent, env_list, cfg, 0.001 if m == 0 else 0.003, m, i)
    return f, m, trainer.evaluate(tr.agent, env_list, cfg, 10_000 + i).mean, float(np.mean(tr.episode_returns))


def main(root, i, factors):
    jobs = [(root, i, f, m) for f in factors for m in range(-1, 8)]
    with get_context("spawn").Pool(2) as pool:
        res = pool.map(work, jobs)
    for f in factors:
        rows = [r for r in res if r[0] == f]
        par = next(r[2] for r in rows if r[1] < 0)
        br = [r for r in rows if r[1] >= 0]
        print(f"f={f}: parent {par:.0f}; branches " + " ".join(f"{r[2]:.0f}" for r in br)
              + f"; above parent {sum(r[2] > par for r in br)}/8; train mean {np.mean([r[3] for r in br]):.0f}")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), [float(x) for x in sys.argv[3].split(",")])
