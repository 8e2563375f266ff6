"""Building blocks for tests that need agents and pool files without running members."""

import numpy as np

from rl_pool import pool
from rl_pool.agent import Agent, AgentMeta
from rl_pool.config import PoolConfig

META = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0))


def agent(seed: int = 0) -> Agent:
    rng = np.random.default_rng(seed)
    a = Agent.initial(META)
    return a.evolve(params={"w": rng.normal(size=a.params["w"].shape)})


def fake_initial(cfg):
    return Agent.initial(META), cfg


def make_pool(root, pool_size=2, **kw) -> tuple[pool.Paths, PoolConfig]:
    paths = pool.Paths(root)
    # the rule of picking one branch (merges have tests of their own)
    cfg = pool.open_pool(paths, {"pool_size": pool_size, "max_episode_steps": 60, "merge": "none", **kw},
                         fake_initial)
    return paths, cfg


class Evil:
    """Unpickling this creates ``marker``: proof that code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))
