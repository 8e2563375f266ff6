"""rl-pool: branch-and-merge process pools for REINFORCE with Beta policies on MuJoCo tasks.

``from rl_pool import Agent`` is the stable API. The package imports nothing
heavy at import time, so entry points can cap math-library threads before
numpy or jax load (see :mod:`rl_pool.threads`).
"""

__version__ = "0.1.0"
__all__ = ["Agent", "__version__"]


def __getattr__(name):
    if name == "Agent":
        from rl_pool.maths.agent import Agent

        return Agent
    raise AttributeError(f"module 'rl_pool' has no attribute {name!r}")
