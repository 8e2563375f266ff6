"""Offline: at a locked parent, does a centred-rank (ES-style) combination of the branches beat it?"""
import json, sys, os
import numpy as np
from rl_pool.config import PoolConfig
from rl_pool.maths.agent import Agent
from rl_pool.learning import envs, trainer

root, i = sys.argv[1], int(sys.argv[2])
n_eval = int(sys.argv[3]) if len(sys.argv) > 3 else 5
cfg = PoolConfig.from_json(json.load(open(f"{root}/pool.json")))
import dataclasses
cfg = dataclasses.replace(cfg, eval_episodes=n_eval)
sel_prev = json.load(open(f"{root}/iterations/{i-1:06d}/selected.json"))
load = lambda p: Agent.from_bytes(open(os.path.join(root, p), "rb").read())
P = load(sel_prev["agent"])
B, S = [], []
for m in range(cfg.pool_size):
    d = json.load(open(f"{root}/iterations/{i:06d}/member-{m:03d}.json"))
    B.append(load(f"iterations/{i:06d}/member-{m:03d}.npz")); S.append(d["eval_return"])
kw = dict(cfg.env_kwargs, max_episode_steps=cfg.max_episode_steps)
E = [envs.make(cfg.env, kw)[0] for _ in range(n_eval)]
ev = lambda a: trainer.evaluate(a, E, cfg, 10_000 + i).mean  # fresh episodes
order = np.argsort(-np.array(S))
n = len(S)
ranks = np.empty(n); ranks[order] = np.arange(n)
w = (n - 1) / 2 - ranks  # centred: best +3.5 ... worst -3.5
w = w / np.abs(w).sum()
names = P.params.keys()
mean_step = {k: np.mean([b.params[k] - P.params[k] for b in B], axis=0) for k in names}
d = {k: sum(wm * (b.params[k] - P.params[k]) for wm, b in zip(w, B)) for k in names}
norm = lambda x: float(np.sqrt(sum(np.sum(v * v) for v in x.values())))
blen = np.mean([norm({k: b.params[k] - P.params[k] for k in names}) for b in B])
print(f"iteration {i}: branch scores {sorted([round(s) for s in S], reverse=True)}; branch step {blen:.3f}, mean step {norm(mean_step):.3f}, centred {norm(d):.3f}")
print("parent", round(ev(P)))
for c in (0.25, 0.5, 1.0, 2.0):
    s = c * blen / norm(d)
    a = P.evolve(params={k: P.params[k] + s * d[k] for k in names})
    print(f"centred, length {c} x branch", round(ev(a)))
for c in (0.25, 0.5, 1.0):
    a = P.evolve(params={k: P.params[k] + c * mean_step[k] for k in names})
    print(f"mean step x {c}", round(ev(a)))
best = B[order[0]]
print("best branch", round(S[order[0]]), "fresh", round(ev(best)))
