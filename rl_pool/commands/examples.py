"""Example custom evaluation worker: ``rl-pool evaluate POOL --worker rl_pool.commands.examples:XDistance``."""

from __future__ import annotations

from rl_pool.commands.evaluate import EvalWorker


class XDistance(EvalWorker):
    """Distance the body travels along x in one episode (MuJoCo ``qpos[0]``, metres).

    The swimming worm's headline metric. Swimmer's reward is forward velocity
    minus a small control cost, so the distance tracks the return times the
    control step ``dt``.
    """

    def evaluate(self, env, agent, seed: int) -> float:
        act = self.actor(agent, seed)
        obs, _ = env.reset(seed=int(seed))
        x0 = float(env.data.qpos[0])
        for _ in range(agent.meta.max_episode_steps):
            obs, _, terminated, _, _ = env.step(act(obs))
            if terminated:
                break
        return float(env.data.qpos[0]) - x0
