"""Evaluation across worker processes, and the base class for custom evaluation workers.

Workers are started with ``spawn`` (a fresh interpreter, never a fork of a
process that may hold JAX or BLAS threads) and inherit one-thread caps through
their environment, so W workers on W cores do not oversubscribe. Each worker
process builds its environment once and reuses it for every episode it runs.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import multiprocessing as mp
import os
import time

from rl_pool.threads import VARIABLES, cap_threads


class EvalWorker:
    """A picklable evaluation callable: ``worker(seed) -> float``.

    Subclass it and override :meth:`evaluate` (and :meth:`make_env` if the
    episode needs a differently made environment). The instance carries only
    the agent's bytes and plain settings, so it pickles cleanly under spawn;
    the env and the loaded agent are built lazily, once per process, after the
    math-thread caps are in place. Subclasses must live in an importable module
    (not ``__main__``), since spawned processes import them by name.
    """

    def __init__(self, agent_bytes: bytes, mode: str = "mean"):
        self.agent_bytes = agent_bytes
        self.mode = mode
        self._env = None
        self._agent = None

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_env"] = state["_agent"] = None
        return state

    # ----- hooks for subclasses -------------------------------------------
    def make_env(self, agent):
        """The environment episodes run in (default: the agent's own, unwrapped)."""
        from rl_pool.learning import envs

        kwargs = dict(agent.meta.env_kwargs, max_episode_steps=agent.meta.max_episode_steps)
        return envs.make(agent.meta.env, kwargs)[0]

    def evaluate(self, env, agent, seed: int) -> float:
        """Score one episode; the default is its undiscounted return."""
        total = 0.0
        for _, _, reward, _ in self.episode(env, agent, seed):
            total += reward
        return total

    # ----- helpers ----------------------------------------------------------
    def actor(self, agent, seed: int):
        """``obs -> action`` for one episode: the Beta mean, or samples seeded by ``seed``."""
        import numpy as np

        if self.mode != "sample":
            return agent.act
        rng = np.random.default_rng(seed)
        return lambda obs: agent.act(obs, rng=rng, deterministic=False)

    def episode(self, env, agent, seed: int):
        """Yield ``(obs, action, reward, info)`` for each step of one episode."""
        act = self.actor(agent, seed)
        obs, _ = env.reset(seed=int(seed))
        for _ in range(agent.meta.max_episode_steps):
            action = act(obs)
            nxt, reward, terminated, _, info = env.step(action)
            yield obs, action, float(reward), info
            obs = nxt
            if terminated:
                break

    def setup(self) -> None:
        cap_threads()
        from rl_pool.maths.agent import Agent

        self._agent = Agent.from_bytes(self.agent_bytes)
        self._env = self.make_env(self._agent)

    def __call__(self, seed: int) -> float:
        if self._env is None:
            self.setup()
        return float(self.evaluate(self._env, self._agent, seed))


@contextlib.contextmanager
def capped_children():
    """While open, processes spawned from here inherit the one-thread caps and the portable SIMD
    level (:mod:`rl_pool.threads`) through their environment, before they import numpy; this
    process's environment is restored afterwards (a library caller's settings stay theirs)."""
    saved = {k: os.environ.get(k) for k in VARIABLES}
    cap_threads()
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


_WORKER: EvalWorker | None = None


def _init(worker: EvalWorker) -> None:
    global _WORKER
    _WORKER = worker
    _WORKER.setup()


def _run(seed: int) -> float:
    return _WORKER(seed)


def load_worker_class(spec: str | None):
    if not spec:
        return EvalWorker
    from rl_pool.errors import UsageError

    module, _, name = spec.partition(":")
    if not module or not name:
        raise UsageError(f"--worker must be MODULE:CLASS, got {spec!r}")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise UsageError(f"cannot import worker {spec!r}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, EvalWorker)):
        raise UsageError(f"worker {spec!r} is not a subclass of rl_pool.commands.evaluate.EvalWorker")
    return cls


def evaluate_bytes(agent_bytes: bytes, episodes: int, workers: int = 1, seed: int = 1_000_000,
                   worker_cls=EvalWorker, mode: str = "mean") -> dict:
    """Run ``episodes`` episodes (reset seeds ``seed + k``) over ``workers`` processes; results in episode order."""
    worker = worker_cls(agent_bytes, mode=mode)
    seeds = [seed + k for k in range(episodes)]
    t0 = time.perf_counter()
    if workers <= 1:
        scores = [worker(s) for s in seeds]
    else:
        with capped_children(), mp.get_context("spawn").Pool(workers, initializer=_init, initargs=(worker,)) as p:
            scores = p.map(_run, seeds, chunksize=1)
    secs = time.perf_counter() - t0
    mean = sum(scores) / len(scores)
    std = math.sqrt(sum((s - mean) ** 2 for s in scores) / len(scores))
    return {"episodes": episodes, "mean_return": mean, "std_return": std, "returns": scores, "seeds": seeds,
            "workers": max(1, workers), "seconds": secs, "mode": mode,
            "worker": f"{worker_cls.__module__}:{worker_cls.__qualname__}"}


def resolve_agent(target: str) -> tuple[str, bytes]:
    """A pool directory (its agent: the pick when there is a current one, else ``best.npz``) or an
    agent file -> ``(path, bytes)``, checked.

    A pool's pick (``POOL/picked.npz``, from ``rl-pool pick`` or ``launch --pick``) counts while
    it covers the pool's last selection (:func:`rl_pool.commands.pick.current_pick`); once the
    pool trains on, ``best.npz`` does again. Read bounded and without blocking
    (:mod:`rl_pool.fsutil`): a pool's files are never read through a symbolic link; an agent
    file the user names may be one, but must lead to a regular file. Reads only: works on a
    read-only pool.
    """
    from rl_pool import fsutil
    from rl_pool.commands.pick import current_pick
    from rl_pool.errors import AgentFileError, UsageError
    from rl_pool.maths.agent import Agent
    from rl_pool.protocol import layout, pool

    path, root, follow, pick = target, None, True, None
    if os.path.isdir(target):
        paths = layout.Paths(target)
        pool.read_config(paths, readonly=True)  # a foreign directory is refused here
        pool.attach_key(paths, required=False)  # with the key, only signed selections vouch for a pick
        pick = current_pick(paths)
        path, root, follow = os.path.join(target, "best.npz"), target, False
        if pick is None and not os.path.lexists(path):
            raise UsageError(f"pool {target} has no best agent yet (no iteration completed)")
    elif not os.path.lexists(target):
        raise UsageError(f"no agent file or pool directory at {target}")
    if pick is not None:
        path, data = pick
    else:
        try:
            data = fsutil.read_bytes(path, fsutil.AGENT_MAX_BYTES, root=root, follow=follow)
        except OSError as exc:
            raise AgentFileError(f"cannot read agent {path}: {exc.strerror or exc}") from None
    Agent.from_bytes(data, source=path)  # AgentFileError (a UsageError) if it is not an agent
    return path, data


#: More episodes than this is a typo, not a job (a million Hopper episodes are a billion steps):
#: refused rather than listing the seeds in memory.
MAX_EPISODES = 1_000_000


def evaluate_path(target: str, episodes: int = 10, workers: int = 1, seed: int = 1_000_000,
                  worker: str | None = None, mode: str = "mean") -> dict:
    from rl_pool.errors import UsageError

    if episodes < 1 or workers < 1:
        raise UsageError("--episodes and --workers must be positive")
    if episodes > MAX_EPISODES:
        raise UsageError(f"--episodes must be at most {MAX_EPISODES}")
    cls = load_worker_class(worker)
    path, data = resolve_agent(target)
    return evaluate_bytes(data, episodes, workers, seed, cls, mode) | {"agent": path}
