"""Benchmarks that print figures (not timed tests):
``python benchmarks/bench.py {throughput,scaling,evaluate,protocol,profile,signing,simd,train-cost}`` (outside the
installed package: it needs rl-pool installed, e.g. by ``shell/setup.sh``).

All figures of one run come from the same machine at the same time; compare
them as ratios, since absolute times on a shared machine are noisy.
"""

from __future__ import annotations

import argparse
import builtins
import collections
import itertools
import json
import os
import shutil
import stat
import statistics
import subprocess
import sys
import tempfile
import time

from rl_pool import fsutil
from rl_pool.threads import PORTABLE_SIMD, cap_threads, capped_environ, cpu_runs_v3


def _plain_loop(env_id: str, steps: int, unwrapped: bool, constant: bool = False) -> float:
    """Env steps per second of a bare loop: random actions drawn in the loop (gymnasium's sampler)
    or a ``constant`` zero action."""
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


def _member_setup(env_id: str, kind: str, hidden: str) -> dict:
    """A member ready to train (its first iteration done: JIT compiled, envs made)."""
    from rl_pool.commands.member import make_initial
    from rl_pool.config import PoolConfig
    from rl_pool.learning import envs, trainer
    from rl_pool.maths import learner

    learner.enable_compilation_cache()
    cfg = PoolConfig(env=env_id, policy=kind, hidden=hidden).validate()
    agent, cfg = make_initial(cfg)
    env_list = [envs.make(cfg.env)[0] for _ in range(max(cfg.batch_episodes, cfg.eval_episodes))]
    t0 = time.perf_counter()
    first = trainer.train(agent, env_list, cfg, 0.1, 0, 1)
    return {"cfg": cfg, "agent": first.agent, "envs": env_list, "rates": [],
            "cold": first.steps / (time.perf_counter() - t0)}


def _member_rate(su: dict, steps: int, iteration: int) -> float:
    """Training steps per second of the member in ``su`` over at least ``steps`` env steps."""
    from rl_pool.learning import trainer

    done = secs = 0.0
    while done < steps:
        r = trainer.train(su["agent"], su["envs"], su["cfg"], 0.1, 0, iteration)
        su["agent"] = r.agent
        done += r.steps
        secs += r.seconds
    return done / secs


def throughput(args) -> None:
    """One member's training throughput vs the environment's own cost, interleaved in one run;
    with ``--policy mlp`` the linear member is measured in the same rounds, for the ratio."""
    kinds = ["linear"] + (["mlp"] if args.policy == "mlp" else [])
    setups = {kind: _member_setup(args.env, kind, args.hidden) for kind in kinds}
    plain, raw, bare = [], [], []
    for rep in range(args.repeats):
        plain.append(_plain_loop(args.env, args.steps, unwrapped=False))
        raw.append(_plain_loop(args.env, args.steps, unwrapped=True))
        bare.append(_plain_loop(args.env, args.steps, unwrapped=True, constant=True))
        for su in setups.values():
            su["rates"].append(_member_rate(su, args.steps, 2 + rep))
    p, u, z = (statistics.median(x) for x in (plain, raw, bare))
    lin = setups["linear"]
    m = statistics.median(lin["rates"])
    print(f"env {args.env}: {lin['cfg'].batch_episodes} envs in lockstep, {lin['cfg'].train_episodes} episodes "
          f"per iteration, median of {args.repeats} rounds of {args.steps} steps")
    print(f"  plain gymnasium env.step loop, random actions   {p:9.0f} steps/s")
    print(f"  same, on env.unwrapped (no wrappers)            {u:9.0f} steps/s")
    print(f"  env.unwrapped, constant action (env cost only)  {z:9.0f} steps/s")
    print(f"  one linear member's training                    {m:9.0f} steps/s")
    print(f"  first iteration incl. JIT compile               {lin['cold']:9.0f} steps/s")
    print(f"  ratio linear member / plain loop                {m / p:9.2f}")
    print(f"  ratio linear member / unwrapped loop            {m / u:9.2f}")
    print(f"  ratio linear member / env cost only             {m / z:9.2f}   (target >= 0.9)")
    roll, replay = _replay_reference(lin, args.repeats)
    print(f"  the trained linear member's rollout alone         {roll:9.0f} steps/s   (10 envs in lockstep, sampling)")
    print(f"  its own actions replayed on env.unwrapped       {replay:9.0f} steps/s   (the same physics, no policy)")
    print(f"  ratio rollout / replay of its actions           {roll / replay:9.2f}")
    print(f"  ratio linear member's training / that replay    {m / replay:9.2f}   (gradient steps included)")
    if "mlp" in setups:
        mlp = setups["mlp"]
        mm = statistics.median(mlp["rates"])
        print(f"  one {mlp['cfg'].spec.describe()} member's training {mm:9.0f} steps/s")
        print(f"  first iteration incl. JIT compile               {mlp['cold']:9.0f} steps/s")
        print(f"  ratio mlp member / linear member                {mm / m:9.2f}   (target >= 0.8)")


def simd(args) -> None:
    """One member's training throughput with rl-pool's portable SIMD level (x86-64-v3, the default)
    and with all of the CPU (``RL_POOL_NATIVE_SIMD=1``): each measured in a fresh process (the
    level is fixed when numpy loads), the two alternating, per env and policy."""
    if not cpu_runs_v3():
        sys.exit("bench simd: this CPU does not run x86-64-v3 code (or is not x86-64): nothing to compare")
    base = {k: v for k, v in os.environ.items() if k not in PORTABLE_SIMD and k != "RL_POOL_NATIVE_SIMD"}
    base["XLA_FLAGS"] = " ".join(f for f in base.get("XLA_FLAGS", "").split() if "xla_cpu_max_isa" not in f)
    modes = {"x86-64-v3": cap_threads(dict(base)), "native": cap_threads(base | {"RL_POOL_NATIVE_SIMD": "1"})}
    print(f"one member's training steps/s, median of {args.repeats} fresh processes each, alternating; "
          f"{args.steps} steps each after a warm-up iteration")
    print(f"  {'env':16} {'policy':10} {'x86-64-v3':>10} {'native':>10} {'v3 / native':>12}")
    for case in args.cases.split(","):
        env_id, _, kind = case.partition(":")
        rates = {m: [] for m in modes}
        for _ in range(args.repeats):
            for mode, environ in modes.items():
                proc = subprocess.run([sys.executable, os.path.abspath(__file__), "_rate", env_id, kind or "linear",
                                       args.hidden, str(args.steps)], env=environ, capture_output=True, text=True)
                if proc.returncode:
                    sys.exit(f"bench simd: the {mode} child failed:\n{proc.stderr[-2000:]}")
                got = json.loads(proc.stdout.strip().splitlines()[-1])
                if got["simd"] != mode:
                    raise RuntimeError(f"the {mode} child ran with {got['simd']}")
                rates[mode].append(got["rate"])
        v3, nat = (statistics.median(rates[m]) for m in modes)
        print(f"  {env_id:16} {kind or 'linear':10} {v3:10.0f} {nat:10.0f} {v3 / nat:12.2f}", flush=True)


def _rate(args) -> None:
    from rl_pool.versions import simd as simd_level

    su = _member_setup(args.env, args.kind, args.hidden)
    print(json.dumps({"rate": _member_rate(su, args.steps, 2), "simd": simd_level(os.environ)}))


def _replay_reference(su: dict, repeats: int) -> tuple[float, float]:
    """Steps/s of the trained member's rollout (``trainer``'s episodes: lockstep envs, Beta draws,
    recording) and of replaying the very actions it took on ``env.unwrapped`` from the same resets.
    MuJoCo is deterministic, so the replay retraces the same trajectories: it is the env's own cost
    for exactly this workload (a policy that drives a body into its joint limits costs MuJoCo more
    than a still or randomly twitching one)."""
    import numpy as np

    from rl_pool.learning.rollout import run_episodes
    from rl_pool.maths.policy import to_action

    agent, cfg, env_list = su["agent"], su["cfg"], su["envs"]
    seeds = list(range(1_000_000, 1_000_000 + cfg.batch_episodes))
    T = agent.meta.max_episode_steps
    rolls, replays = [], []
    for rep in range(repeats):
        t0 = time.perf_counter()
        b = run_episodes(env_list, agent.params, agent.spec, agent.norm, agent.low, agent.high, seeds, T,
                         np.random.default_rng(rep), deterministic=False)
        rolls.append(b.steps / (time.perf_counter() - t0))
        actions = [list(to_action(b.u[k, :b.lengths[k]], agent.low, agent.high)) for k in range(len(seeds))]
        env = env_list[0]
        t0 = time.perf_counter()
        for k, seed in enumerate(seeds):
            env.reset(seed=seed)
            for a in actions[k]:
                env.step(a)
        replays.append(b.steps / (time.perf_counter() - t0))
    return statistics.median(rolls), statistics.median(replays)


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
    from rl_pool.protocol import layout

    paths = layout.Paths(root)
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
    from rl_pool.commands.evaluate import evaluate_bytes, resolve_agent

    path, data = resolve_agent(args.agent)
    one = evaluate_bytes(data, args.episodes, workers=1)
    many = evaluate_bytes(data, args.episodes, workers=args.workers)
    assert one["returns"] == many["returns"], "results must not depend on the number of workers"
    print(f"{args.episodes} episodes of {path}: mean return {one['mean_return']:.2f}")
    print(f"  1 worker (in process)            {one['seconds']:7.2f} s")
    print(f"  {args.workers} spawned workers (incl. start-up) {many['seconds']:7.2f} s")
    print(f"  speed-up                         {one['seconds'] / many['seconds']:7.2f}x   (target >= 1.7 for 2 workers)")


# ---------------------------------------------------------------- protocol cost
def _deposit_marker(me: int):
    """``is_deposit(path)``: whether a rename to ``path`` is member ``me``'s deposit marker (its
    metrics file in an iteration directory), which ends one iteration of that member."""
    marker = f"{os.sep}member-{me:03d}.json"
    return lambda path: path.endswith(marker) and f"{os.sep}iterations{os.sep}" in path


def _member_argv(args) -> list[str]:
    """The ``train`` command line an internal member subcommand was given (after ``--``)."""
    return args.rest[1:] if args.rest[:1] == ["--"] else args.rest


def _trivial_work(env: str) -> list[str]:
    """Pool options for trivial work: 10-step episodes, one training and one evaluation episode."""
    return ["--env", env, "--max-episode-steps", "10", "--train-episodes", "1", "--batch-episodes", "1",
            "--eval-episodes", "1", "--heartbeat-timeout", "600", "--barrier-timeout", "600"]


class _FsCounter:
    """Counts one member's filesystem calls on the pool directory (nothing else), without strace.

    Installed in the member's process before the CLI runs (``_member`` below): it wraps the
    ``os`` functions and ``open`` the protocol uses and classifies each call on a path inside
    the pool. Paths relative to a directory descriptor (``openat``-style walks in
    :mod:`rl_pool.fsutil`) are resolved through the descriptors it saw opened. A snapshot is
    taken each time this member's deposit marker is renamed into place, so the difference of
    two snapshots is one whole iteration: barrier, selection, training, deposit.
    """

    def __init__(self, root: str, me: int):
        self.roots = {os.path.abspath(root) + os.sep, os.path.realpath(root) + os.sep}
        self.is_deposit = _deposit_marker(me)
        self.count: collections.Counter = collections.Counter()
        self.marks: list = []
        self.fds: dict[int, str] = {}

    def where(self, path, dir_fd=None) -> str | None:
        if isinstance(path, int):
            return self.fds.get(path)
        try:
            path = os.fsdecode(path)
        except TypeError:
            return None
        if dir_fd is not None and not os.path.isabs(path):
            base = self.fds.get(dir_fd)
            return None if base is None else os.path.join(base, path)
        full = os.path.abspath(path)
        return full if any((full + os.sep).startswith(r) for r in self.roots) else None

    def install(self) -> None:
        real = {n: getattr(os, n) for n in ("open", "close", "stat", "lstat", "listdir", "scandir", "rename",
                                             "replace", "unlink", "mkdir", "rmdir", "link", "fsync")}
        real_open, fstat, c = builtins.open, os.fstat, self

        def os_open(path, flags, mode=0o777, *, dir_fd=None):
            where = c.where(path, dir_fd)
            try:
                fd = real["open"](path, flags, mode, dir_fd=dir_fd)
            except OSError as exc:
                if where:
                    c.count["open_failed" if exc.errno != 2 else "open_missing"] += 1
                raise
            if where:
                if stat.S_ISDIR(fstat(fd).st_mode):
                    c.count["open_dir"] += 1
                else:
                    c.count["open_write" if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) else "open_read"] += 1
                c.fds[fd] = where
            return fd

        def os_close(fd):
            c.fds.pop(fd, None)
            return real["close"](fd)

        def py_open(file, mode="r", *a, **kw):
            where = c.where(file) if not isinstance(file, int) else None
            try:
                fh = real_open(file, mode, *a, **kw)
            except OSError as exc:
                if where:
                    c.count["open_failed" if exc.errno != 2 else "open_missing"] += 1
                raise
            if where:
                c.count["open_write" if any(x in mode for x in "wax+") else "open_read"] += 1
            return fh

        def counted(name, key, paths=1):
            fn = real[name]

            def wrapper(*a, **kw):
                if any(c.where(a[k] if k < len(a) else ".", kw.get("dir_fd", kw.get("src_dir_fd")))
                       for k in range(paths)):
                    c.count[key] += 1
                    if name == "replace" and len(a) > 1 and c.is_deposit(os.fsdecode(a[1])):
                        out = fn(*a, **kw)
                        c.marks.append((time.monotonic(), dict(c.count), time.process_time()))
                        return out
                return fn(*a, **kw)
            return wrapper

        def fsync(fd):
            if fd in c.fds:
                c.count["fsync"] += 1
            return real["fsync"](fd)

        os.open, os.close, builtins.open, os.fsync = os_open, os_close, py_open, fsync
        os.stat, os.lstat = counted("stat", "stat"), counted("lstat", "stat")
        os.listdir, os.scandir = counted("listdir", "listing"), counted("scandir", "listing")
        os.rename, os.replace = counted("rename", "rename"), counted("replace", "rename")
        os.unlink, os.rmdir, os.mkdir = counted("unlink", "unlink"), counted("rmdir", "rmdir"), counted("mkdir", "mkdir")
        os.link = counted("link", "link")


def _member(args) -> None:
    """One member under :class:`_FsCounter` (``python benchmarks/bench.py _member OUT -- train ...``)."""
    import atexit

    rest = _member_argv(args)
    root = rest[rest.index("--pool-dir") + 1]
    me = int(rest[rest.index("--member") + 1])
    counter = _FsCounter(root, me)
    counter.install()

    def dump():
        with open(args.out + ".tmp", "w") as fh:
            json.dump({"marks": counter.marks, "total": dict(counter.count)}, fh)
        os.replace(args.out + ".tmp", args.out)

    atexit.register(dump)
    from rl_pool.commands.cli import main as cli_main

    sys.exit(cli_main(rest))


def _profiled_member(args) -> None:
    """One member under cProfile, CPU time only (``bench.py _profiled OUT WARMUP -- train ...``):
    the profiler runs from the member's deposit of iteration WARMUP to its last deposit (the
    marker renamed into place), so start-up, JIT and shutdown are left out, and whole
    iterations, deposit to deposit, are counted; its stats go to OUT at exit."""
    import atexit
    import cProfile

    rest = _member_argv(args)
    is_deposit = _deposit_marker(int(rest[rest.index("--member") + 1]))
    last = int(rest[rest.index("--iterations") + 1])
    prof = cProfile.Profile(time.process_time)
    deposits = [0]
    real_replace = os.replace

    def replace(src, dst, *a, **kw):
        real_replace(src, dst, *a, **kw)
        if isinstance(dst, str) and is_deposit(dst):
            deposits[0] += 1
            if deposits[0] == args.warmup:
                prof.enable()
            elif deposits[0] == last:
                prof.disable()

    os.replace = replace

    def dump():
        prof.disable()
        prof.dump_stats(args.out)
        with open(args.out + ".json", "w") as fh:  # the iterations profiled, deposit to deposit
            json.dump({"iterations": max(0, min(deposits[0], last) - args.warmup)}, fh)

    atexit.register(dump)
    from rl_pool.commands.cli import main as cli_main

    sys.exit(cli_main(rest))


def profile(args) -> None:
    """Where a member's CPU goes in a pool with trivial work: every member under cProfile (CPU
    time), the functions with the most CPU per member and iteration over all members."""
    import pstats

    if not 1 <= args.warmup <= args.iterations - 1:
        raise SystemExit("bench profile: need 1 <= --warmup <= --iterations - 1")
    base = tempfile.mkdtemp(prefix="rl-pool-profile-")
    extra = [*_trivial_work(args.env), "--merge", args.merge]
    n = args.members
    try:
        root = os.path.join(base, "pool")
        _run_members(n, [root], args.iterations, extra,
                     lambda m: [sys.executable, os.path.abspath(__file__), "_profiled",
                                os.path.join(base, f"{m}.prof"), str(args.warmup), "--"], args.learning_rate)
        from rl_pool.protocol import deposits, layout

        paths = layout.Paths(root)
        sels = [deposits.read_selected(paths, i) for i in range(args.warmup + 1, args.iterations + 1)]
        merged = sum((s or {}).get("winner") == "merge" for s in sels)
        covered = 0
        for m in range(n):
            with open(os.path.join(base, f"{m}.prof.json")) as fh:
                covered += json.load(fh)["iterations"]
        stats = pstats.Stats(*(os.path.join(base, f"{m}.prof") for m in range(n)))
        total = sum(v[2] for v in stats.stats.values())  # tottime: each function's own CPU
        per = 1000 / max(covered, 1)
        print(f"{n} members, --merge {args.merge}, learning rate {args.learning_rate}, {args.env} with 10-step "
              f"episodes; iterations {args.warmup + 1}..{args.iterations} profiled ({covered} member-iterations, "
              f"{merged} of {len(sels)} selections merged)")
        print(f"CPU per member and iteration, all profiled functions: {total * per:.2f} ms")
        for key, title in (("tottime", "own CPU"), ("cumulative", "CPU including callees")):
            print(f"\ntop {args.top} by {title}, ms per member and iteration:")
            rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2 if key == "tottime" else 3], reverse=True)
            for (file, line, func), (_cc, calls, tt, ct, _callers) in rows[:args.top]:
                where = f"{os.path.relpath(file) if file.startswith(os.sep) else file}:{line}({func})"
                print(f"{(tt if key == 'tottime' else ct) * per:8.3f}  {calls / max(covered, 1):7.1f} calls  {where}")
    finally:
        shutil.rmtree(base, ignore_errors=True)


KINDS = ("open_read", "open_write", "open_missing", "open_dir", "listing", "stat", "rename", "fsync",
         "mkdir", "unlink")


def _run_members(n: int, roots: list[str], iterations: int, extra: list[str], head, lr: float = 0.1) -> None:
    """Run an N-member pool of ``rl-pool train`` processes to its end; ``head(m)`` is the command
    line before ``train`` for member ``m``. A member exiting non-zero stops the bench in one line."""
    procs = []
    try:
        for m in range(n):
            cmd = [*head(m), "train", "--pool-dir", roots[m % len(roots)], "--pool-size", str(n), "--member",
                   str(m), "--iterations", str(iterations), "--learning-rate", str(lr), "--quiet", *extra]
            procs.append(subprocess.Popen(cmd, env=capped_environ(), stdout=subprocess.DEVNULL,
                                          stderr=subprocess.PIPE, text=True))
        for p in procs:
            _, err = p.communicate()
            if p.returncode != 0:
                raise SystemExit(f"member exited with {p.returncode}: {err.strip()[-500:]}")
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()


def _protocol_pool(n: int, dirs: list[str], iterations: int, warmup: int, extra: list[str], lr: float) -> dict:
    name = f"bench-protocol-{n}-{os.getpid()}-{time.time_ns() % 10**6}"
    roots = [os.path.join(d, name) for d in dirs]
    counts = tempfile.mkdtemp(prefix="rl-pool-counts-")
    try:
        _run_members(n, roots, iterations, extra, lambda m: [sys.executable, os.path.abspath(__file__), "_member",
                                                             os.path.join(counts, f"{m}.json"), "--"], lr)
        per_kind = {k: [] for k in KINDS}
        secs, cpu = [], []
        for m in range(n):
            with open(os.path.join(counts, f"{m}.json")) as fh:
                marks = json.load(fh)["marks"][warmup:]
            for (t0, c0, p0), (t1, c1, p1) in itertools.pairwise(marks):
                secs.append(t1 - t0)
                cpu.append(p1 - p0)
                for k in KINDS:
                    per_kind[k].append(c1.get(k, 0) - c0.get(k, 0))
        return {"ms": 1000 * statistics.median(secs), "cpu_ms": 1000 * statistics.median(cpu),
                **{k: statistics.mean(v) for k, v in per_kind.items()},
                "cycles": len(secs)}
    finally:
        shutil.rmtree(counts, ignore_errors=True)
        shutil.rmtree(roots[0], ignore_errors=True)


def _plain_pool(n: int, dirs: list[str], iterations: int, warmup: int, extra: list[str],
                lr: float) -> tuple[float, int, int]:
    """ms per iteration of the same pool with nothing counted: members run as ``rl-pool train``;
    the mean gap between the decisions of iterations ``warmup`` and ``iterations``; and how many of
    the counted iterations merged, and of those how many with momentum."""
    from rl_pool.protocol import deposits, layout

    name = f"bench-plain-{n}-{os.getpid()}-{time.time_ns() % 10**6}"
    roots = [os.path.join(d, name) for d in dirs]
    try:
        _run_members(n, roots, iterations, extra, lambda m: [sys.executable, "-m", "rl_pool"], lr)
        paths = layout.Paths(roots[0])
        t0, t1 = (deposits.read_selected(paths, i)["time"] for i in (warmup, iterations))
        sels = [deposits.read_selected(paths, i) for i in range(warmup + 1, iterations + 1)]
        merges = [s for s in sels if s.get("winner") == "merge"]
        momentum = [s for s in merges if "beta" in s["merge"].get("momentum", {})]
        return 1000 * (t1 - t0) / (iterations - warmup), len(merges), len(momentum)
    finally:
        shutil.rmtree(roots[0], ignore_errors=True)


def protocol(args) -> None:
    """Protocol cost per member and iteration with trivial work: time, opens, listings, stats."""
    if not 1 <= args.warmup <= args.iterations - 2:
        # iteration 0's decision (the initial agent) has no time; a median needs two counted gaps
        raise SystemExit("bench protocol: need 1 <= --warmup <= --iterations - 2")
    base = None if args.dir else tempfile.mkdtemp(prefix="rl-pool-bench-")
    dirs = args.dir or [base]
    extra = [*_trivial_work(args.env), "--selection", args.selection]
    parent = " + the parent's re-score (3 members, all in pools of up to 3)" if args.selection == "parent" else ""
    print(f"env {args.env}, 10-step episodes, 1 training + 1 evaluation episode{parent} per member and iteration, "
          f"{args.iterations} iterations (first {args.warmup} not counted); pool on {', '.join(dirs)}")
    print("per member and iteration (mean over members and iterations; ms/iter and cpu ms: median; plain: mean):")
    print(f"{'N':>4} {'merge':>8} {'ms/iter':>8} {'plain':>6} {'cpu ms':>6} {'floor':>6} {'reads':>6} {'writes':>6} "
          f"{'missing':>7} {'dir opens':>9} {'listings':>8} {'stats':>6} {'renames':>7} {'fsyncs':>6} "
          f"{'reads <= N+3':>12} {'merged':>8}")
    rows = []
    try:
        for n in args.members:
            for kind in args.merge:
                r = _protocol_pool(n, dirs, args.iterations, args.warmup, [*extra, "--merge", kind],
                                   args.learning_rate)
                r["plain_ms"], r["merged"], r["with_momentum"] = _plain_pool(n, dirs, args.iterations, args.warmup,
                                                                             [*extra, "--merge", kind],
                                                                             args.learning_rate)
                rows.append({"members": n, "merge": kind, **r})
                floor = n * r["cpu_ms"] / min(n, os.cpu_count() or 1)
                print(f"{n:>4} {kind:>8} {r['ms']:>8.1f} {r['plain_ms']:>6.1f} {r['cpu_ms']:>6.1f} {floor:>6.0f} "
                      f"{r['open_read']:>6.1f} {r['open_write']:>6.1f} "
                      f"{r['open_missing']:>7.1f} {r['open_dir']:>9.1f} {r['listing']:>8.1f} {r['stat']:>6.1f} "
                      f"{r['rename']:>7.1f} {r['fsync']:>6.1f} {'yes' if r['open_read'] <= n + 3 else 'no':>12} "
                      f"{r['merged']:>3}/{args.iterations - args.warmup}"
                      + (f" ({r['with_momentum']} with momentum)" if kind == "momentum" else ""), flush=True)
    finally:
        if base:
            shutil.rmtree(base, ignore_errors=True)
    print("ms/iter: with every file call counted (a Python wrapper around each); plain: the same pool again with "
          "nothing counted (mean gap between decisions)")
    print(f"cpu ms: a member's own CPU time per iteration (all its threads); floor: N x cpu ms / cores used "
          f"(min(N, {os.cpu_count()})), the shortest iteration these CPUs allow whatever the protocol does;")
    print("reads/writes: files opened to read/write; missing: opens of names not there (yet): polls;")
    print("dir opens: directories opened (fsync of a directory, the no-symlink walk of rl_pool.fsutil)")
    print("merged: counted iterations of the plain pool whose selection was a merge (and, with momentum, "
          "how many of those added the momentum term)")
    if args.json:
        print(json.dumps(rows))


def signing(args) -> None:
    """What the pool key costs per member and iteration: HMAC-SHA256 over the JSON files a member
    signs (its deposit, heartbeats, maybe the selection) and checks (N deposits, the selection)."""
    import json as _json
    import secrets

    from rl_pool.protocol.keys import Key

    key = Key(secrets.token_bytes(32))
    deposit = {"iteration": 123, "member": 1, "agent_sha256": "ab" * 32, "eval_return": 357.25,
               "eval_returns": [355.1, 358.0, 358.6], "eval_score": 357.25, "learning_rate": 0.1,
               "train_steps": 20000, "train_seconds": 2.31, "eval_seconds": 0.3, "parent_eval_return": 350.0,
               "parent_sha256": "cd" * 32, "host": "node17", "pid": 4242, "time": 1.7e9}
    doc = key.sign(deposit)
    selection = key.sign({"iteration": 123, "member": 1, "winner": "branch", "agent_sha256": "ab" * 32,
                          "considered": [{"member": m, "eval_return": 350.0 + m, "score": 350.0 + m}
                                         for m in range(args.members)],
                          "skipped": [], "parent": {"iteration": 122, "eval_return": 350.0}})
    reps = args.repeats
    t0 = time.perf_counter()
    for _ in range(reps):
        key.sign(deposit)
    sign_us = (time.perf_counter() - t0) / reps * 1e6
    t0 = time.perf_counter()
    for _ in range(reps):
        key.verify(_json.loads(_json.dumps(doc)))
    verify_us = (time.perf_counter() - t0) / reps * 1e6
    t0 = time.perf_counter()
    for _ in range(reps):
        key.verify(selection)
    sel_us = (time.perf_counter() - t0) / reps * 1e6
    n = args.members
    # per iteration a member signs its deposit, one selection (at most) and ~2 heartbeats, and
    # checks N deposits, the selection (a few times while waiting) and N heartbeats
    per_iter = 4 * sign_us + n * verify_us + 3 * sel_us + n * verify_us
    print(f"HMAC-SHA256 over canonical JSON, {reps} repetitions each")
    print(f"  sign a deposit's metrics                  {sign_us:8.1f} us")
    print(f"  parse + verify a deposit's metrics        {verify_us:8.1f} us")
    print(f"  verify a selection of {n} members          {sel_us:8.1f} us")
    print(f"  per member and iteration, pool of {n}      {per_iter:8.1f} us  "
          f"({100 * per_iter / 1e6 / 2.5:.4f}% of a 2.5 s Swimmer iteration)")


def _option_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def train_cost(args) -> None:
    """Seconds per training iteration of one member with a preset's settings and with some of them
    changed, alternating in one process on the same agent and the same episodes (every round
    trains the given agent afresh at the same iteration, so both sides sample alike at first)."""
    from dataclasses import fields, replace

    from rl_pool.commands import presets
    from rl_pool.config import PoolConfig
    from rl_pool.learning import envs, trainer
    from rl_pool.maths import learner
    from rl_pool.maths.agent import Agent

    learner.enable_compilation_cache()
    names = {f.name for f in fields(PoolConfig)}
    preset = presets.get(args.preset)
    base = PoolConfig(**{k: v for k, v in preset.items() if k in names}).validate()
    changed = {}
    for item in args.set:
        key, _, text = item.partition("=")
        if key.replace("-", "_") not in names:
            sys.exit(f"bench: unknown option {key!r}")
        changed[key.replace("-", "_")] = _option_value(text)
    sides = {"the preset": base, "changed": replace(base, **changed).validate()}
    agent = Agent.load(args.agent)
    env_list = [envs.make(base.env, base.train_env_kwargs or None)[0] for _ in range(base.batch_episodes)]
    lr = float(preset["learning_rates"][0])
    secs = {k: [] for k in sides}
    steps = {k: [] for k in sides}
    for rep in range(args.repeats + 1):
        for name, cfg in sides.items():
            r = trainer.train(agent, env_list, cfg, lr, 0, 1 + rep)
            if rep:  # the first round compiles
                secs[name].append(r.seconds)
                steps[name].append(r.steps)
    med = {k: statistics.median(secs[k]) for k in sides}
    print(f"{args.preset}: one member's training iteration from {args.agent}, rate {lr}, "
          f"median of {args.repeats} rounds, alternating")
    for name in sides:
        print(f"  {name:<12} {med[name]:7.2f} s per iteration, {statistics.median(steps[name]):8.0f} env steps")
    print(f"  changed ({', '.join(args.set)}) / the preset: {med['changed'] / med['the preset']:.2f}")


def main(argv=None) -> None:
    cap_threads()
    p = argparse.ArgumentParser(prog="python benchmarks/bench.py")
    sub = p.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--env", default="Swimmer-v5")
    t.add_argument("--steps", type=int, default=40000)
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--policy", default="linear", choices=("linear", "mlp"))
    t.add_argument("--hidden", default="64,64", help="MLP hidden sizes (with --policy mlp)")
    t.set_defaults(func=throughput)
    g = sub.add_parser("signing")
    g.add_argument("--members", type=int, default=16)
    g.add_argument("--repeats", type=int, default=20000)
    g.set_defaults(func=signing)
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
    pr = sub.add_parser("protocol", help="files opened, listings and time per member and iteration, N = 2..32")
    pr.add_argument("--members", type=lambda t: [int(x) for x in t.split(",")], default=[2, 4, 8, 16, 32],
                    help="pool sizes (default 2,4,8,16,32)")
    pr.add_argument("--iterations", type=int, default=10)
    pr.add_argument("--warmup", type=int, default=2, help="first iterations not counted (start-up, JIT)")
    pr.add_argument("--env", default="Swimmer-v5")
    pr.add_argument("--dir", action="append", default=None,
                    help="where the pool lives (default: a temp dir); repeat for mounts of one shared "
                         "directory (members alternate between them)")
    pr.add_argument("--selection", default="parent", choices=("parent", "branches"),
                    help="the pool's --selection: parent (the default) also re-scores the parent each "
                         "iteration, one more evaluation episode for three members (all in pools of up to 3)")
    pr.add_argument("--merge", type=lambda t: t.split(","), default=["none"],
                    help="the pools' --merge, comma-separated: each pool size runs once per rule, side by side "
                         "(e.g. none,adaptive: a merge reads every valid branch's agent and writes one more)")
    pr.add_argument("--learning-rate", type=float, default=0.1,
                    help="every member's rate (0.01 makes Swimmer's branches beat the parent often enough that "
                         "the rules that merge do merge; see the merged column)")
    pr.add_argument("--json", action="store_true", help="also print the rows as one JSON list")
    pr.set_defaults(func=protocol)
    pf = sub.add_parser("profile", help="where a member's CPU goes in a pool with trivial work (cProfile)")
    pf.add_argument("--members", type=int, default=16)
    pf.add_argument("--iterations", type=int, default=40)
    pf.add_argument("--warmup", type=int, default=5, help="first iterations not profiled (start-up, JIT)")
    pf.add_argument("--env", default="Swimmer-v5")
    pf.add_argument("--merge", default="momentum", help="the pool's --merge (default momentum)")
    pf.add_argument("--learning-rate", type=float, default=0.01,
                    help="every member's rate (default 0.01: Swimmer's pools then merge in most iterations)")
    pf.add_argument("--top", type=int, default=25, help="functions listed per table")
    pf.set_defaults(func=profile)
    tc = sub.add_parser("train-cost", help="a member's training iteration with a preset and with options changed")
    tc.add_argument("--preset", default="humanoid")
    tc.add_argument("--agent", default="results/humanoid-v5/best.npz", help="the agent every round trains from")
    tc.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="an option to change, e.g. value_minibatch_steps=0 (repeatable)")
    tc.add_argument("--repeats", type=int, default=5)
    tc.set_defaults(func=train_cost)
    sm = sub.add_parser("simd", help="member throughput with the portable SIMD level vs all of the CPU")
    sm.add_argument("--cases", default="Swimmer-v5:linear,HalfCheetah-v5:linear,HalfCheetah-v5:mlp",
                    help="ENV:POLICY,... (default Swimmer linear, HalfCheetah linear and mlp)")
    sm.add_argument("--hidden", default="64,64")
    sm.add_argument("--steps", type=int, default=40000)
    sm.add_argument("--repeats", type=int, default=3)
    sm.set_defaults(func=simd)
    r = sub.add_parser("_rate")  # internal: one member's training rate in this process
    r.add_argument("env")
    r.add_argument("kind")
    r.add_argument("hidden")
    r.add_argument("steps", type=int)
    r.set_defaults(func=_rate)
    pm = sub.add_parser("_profiled")  # internal: one member under cProfile
    pm.add_argument("out")
    pm.add_argument("warmup", type=int)
    pm.add_argument("rest", nargs=argparse.REMAINDER)
    pm.set_defaults(func=_profiled_member)
    m = sub.add_parser("_member")  # internal: one member under the filesystem-call counter
    m.add_argument("out")
    m.add_argument("rest", nargs=argparse.REMAINDER)
    m.set_defaults(func=_member)
    args = p.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
