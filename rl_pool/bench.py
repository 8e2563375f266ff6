"""Benchmarks that print figures (not timed tests): ``python -m rl_pool.bench {throughput,scaling,evaluate}``.

All figures of one run come from the same machine at the same time; compare
them as ratios, since absolute times on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from . import fsutil
from .threads import cap_threads, capped_environ


def _plain_loop(env_id: str, steps: int, unwrapped: bool, constant: bool = False) -> float:
    import gymnasium as gym
    import numpy as np

    env = gym.make(env_id)
    if unwrapped:
        env = env.unwrapped
    env.reset(seed=0)
    env.action_space.seed(0)
    limit = gym.spec(env_id).max_episode_steps
    zero = np.zeros(env.action_space.shape)
    sample = (lambda: zero) if constant else env.action_space.sample
    t0 = time.perf_counter()
    k = 0
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(sample())
        k += 1
        if term or trunc or (unwrapped and k >= limit):
            env.reset()
            k = 0
    return steps / (time.perf_counter() - t0)


def throughput(args) -> None:
    """Plain gymnasium random-action loop vs one member's training (gradient included)."""
    from . import envs, learner, trainer
    from .config import PoolConfig
    from .member import make_initial

    learner.enable_compilation_cache()
    cfg, _ = PoolConfig(env=args.env).validate(), None
    agent, cfg = make_initial(cfg)
    env_list = [envs.make(cfg.env)[0] for _ in range(max(cfg.batch_episodes, cfg.eval_episodes))]
    t0 = time.perf_counter()
    first = trainer.train(agent, env_list, cfg, 0.1, 0, 1)
    cold = first.steps / (time.perf_counter() - t0)
    agent = first.agent
    plain, raw, bare, member = [], [], [], []
    for rep in range(args.repeats):
        plain.append(_plain_loop(cfg.env, args.steps, unwrapped=False))
        raw.append(_plain_loop(cfg.env, args.steps, unwrapped=True))
        bare.append(_plain_loop(cfg.env, args.steps, unwrapped=True, constant=True))
        steps = secs = 0.0
        while steps < args.steps:
            r = trainer.train(agent, env_list, cfg, 0.1, 0, 2 + rep)
            agent = r.agent
            steps += r.steps
            secs += r.seconds
        member.append(steps / secs)
    p, u, z, m = (statistics.median(x) for x in (plain, raw, bare, member))
    print(f"env {cfg.env}: {cfg.batch_episodes} envs in lockstep, {cfg.train_episodes} episodes per "
          f"iteration, median of {args.repeats} rounds of {args.steps} steps")
    print(f"  plain gymnasium env.step loop, random actions   {p:9.0f} steps/s")
    print(f"  same, on env.unwrapped (no wrappers)            {u:9.0f} steps/s")
    print(f"  env.unwrapped, constant action (env cost only)  {z:9.0f} steps/s")
    print(f"  one member's training (rollouts + gradients)    {m:9.0f} steps/s")
    print(f"  first iteration incl. JIT compile               {cold:9.0f} steps/s")
    print(f"  ratio member / plain loop                       {m / p:9.2f}   (target >= 0.9)")
    print(f"  ratio member / unwrapped loop                   {m / u:9.2f}")
    print(f"  ratio member / env cost only                    {m / z:9.2f}")


def _run_pool(root: str, n: int, iterations: int, extra: list[str]) -> dict:
    procs = []
    t0 = time.time()
    for m in range(n):
        cmd = [sys.executable, "-m", "rl_pool", "train", "--pool-dir", root, "--pool-size", str(n),
               "--member", str(m), "--iterations", str(iterations), "--learning-rate", "0.1",
               "--quiet", *extra]
        procs.append(subprocess.Popen(cmd, env=capped_environ(), stdout=subprocess.DEVNULL))
    for p in procs:
        if p.wait() != 0:
            raise SystemExit(f"member exited with {p.returncode}; see {root}/logs")
    wall = time.time() - t0
    from . import pool

    paths = pool.Paths(root)
    latencies, wait_share, first_sel, last_sel = [], [], None, None
    for i in range(1, iterations + 1):
        deps = [os.stat(paths.deposit_json(i, m)).st_mtime_ns / 1e9 for m in range(n)]
        waits = [fsutil.read_json(paths.wait_json(i, m)) for m in range(n)]
        docs = [fsutil.read_json(paths.deposit_json(i, m)) for m in range(n)]
        latencies.append(max(w["resumed_at"] for w in waits) - max(deps))
        for d, w in zip(docs, waits, strict=True):
            busy = d["train_seconds"] + d["eval_seconds"]
            wait_share.append(w["wait_seconds"] / (busy + w["wait_seconds"]))
        sel_t = fsutil.read_json(paths.selected(i))["time"]
        first_sel = sel_t if first_sel is None else first_sel
        last_sel = sel_t
    return {"wall": wall, "steady": (last_sel - first_sel) / max(iterations - 1, 1),
            "latency_ms": [x * 1000 for x in latencies], "wait_share": wait_share}


def scaling(args) -> None:
    """1 member vs N members on N cores, same iterations per member; barrier latency."""
    extra = ["--env", args.env, "--train-episodes", str(args.train_episodes), "--batch-episodes",
             str(args.batch_episodes), "--eval-episodes", str(args.eval_episodes)]
    if args.max_episode_steps:
        extra += ["--max-episode-steps", str(args.max_episode_steps)]
    base = tempfile.mkdtemp(prefix="rl-pool-bench-")
    try:
        one = _run_pool(os.path.join(base, "one"), 1, args.iterations, extra)
        many = _run_pool(os.path.join(base, "many"), args.members, args.iterations, extra)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    lat = many["latency_ms"]
    print(f"env {args.env}: {args.iterations} iterations per member, {args.train_episodes} training + "
          f"{args.eval_episodes} evaluation episodes each")
    print(f"  wall, 1 member (incl. start-up)           {one['wall']:8.2f} s")
    print(f"  wall, {args.members} members (incl. start-up)          {many['wall']:8.2f} s")
    print(f"  seconds per iteration, 1 member           {one['steady']:8.3f}")
    print(f"  seconds per iteration, {args.members} members          {many['steady']:8.3f}")
    print(f"  efficiency wall(1)/wall({args.members})                {one['wall'] / many['wall']:8.2f}   (target >= 0.9)")
    print(f"  efficiency per iteration (steady state)   {one['steady'] / many['steady']:8.2f}")
    print(f"  episodes/s: 1 member {(args.train_episodes + args.eval_episodes) / one['steady']:.1f}, "
          f"{args.members} members {args.members * (args.train_episodes + args.eval_episodes) / many['steady']:.1f}")
    print(f"  barrier latency, last deposit -> all resumed: median {statistics.median(lat):.1f} ms, "
          f"p90 {sorted(lat)[int(0.9 * (len(lat) - 1))]:.1f} ms, max {max(lat):.1f} ms   (target median <= 20)")
    print(f"  share of member time spent waiting: median {100 * statistics.median(many['wait_share']):.1f}%")


def evaluation(args) -> None:
    """``rl-pool evaluate`` on 1 worker vs W spawned workers, start-up included."""
    from .evaluate import evaluate_bytes, resolve_agent

    path, data = resolve_agent(args.agent)
    one = evaluate_bytes(data, args.episodes, workers=1)
    many = evaluate_bytes(data, args.episodes, workers=args.workers)
    assert one["returns"] == many["returns"], "results must not depend on the number of workers"
    print(f"{args.episodes} episodes of {path}: mean return {one['mean_return']:.2f}")
    print(f"  1 worker (in process)            {one['seconds']:7.2f} s")
    print(f"  {args.workers} spawned workers (incl. start-up) {many['seconds']:7.2f} s")
    print(f"  speed-up                         {one['seconds'] / many['seconds']:7.2f}x   (target >= 1.7 for 2 workers)")


def main(argv=None) -> None:
    cap_threads()
    p = argparse.ArgumentParser(prog="python -m rl_pool.bench")
    sub = p.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--env", default="Swimmer-v5")
    t.add_argument("--steps", type=int, default=40000)
    t.add_argument("--repeats", type=int, default=3)
    t.set_defaults(func=throughput)
    s = sub.add_parser("scaling")
    s.add_argument("--env", default="Swimmer-v5")
    s.add_argument("--members", type=int, default=2)
    s.add_argument("--iterations", type=int, default=30)
    s.add_argument("--train-episodes", type=int, default=20)
    s.add_argument("--batch-episodes", type=int, default=10)
    s.add_argument("--eval-episodes", type=int, default=3)
    s.add_argument("--max-episode-steps", type=int, default=0)
    s.set_defaults(func=scaling)
    e = sub.add_parser("evaluate")
    e.add_argument("agent", help="agent .npz or pool directory")
    e.add_argument("--episodes", type=int, default=160)
    e.add_argument("--workers", type=int, default=2)
    e.set_defaults(func=evaluation)
    args = p.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
