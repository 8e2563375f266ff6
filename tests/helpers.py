"""Building blocks shared by the tests: agents and pool files made without running members, fake pools
for the readers, a reference pool run by real processes, and a reference evaluation episode."""

import json
import os
import time

import gymnasium as gym
import numpy as np

from rl_pool import fsutil
from rl_pool.config import PoolConfig
from rl_pool.maths.agent import Agent, AgentMeta
from rl_pool.protocol import claim, deposits, layout, pool
from rl_pool.protocol.heartbeat import HOST

from .conftest import SHORT, spawn

META = AgentMeta("Swimmer-v5", {}, 60, 8, 2, (-1.0, -1.0), (1.0, 1.0))


def agent(seed: int = 0) -> Agent:
    rng = np.random.default_rng(seed)
    a = Agent.initial(META)
    return a.evolve(params={"w": rng.normal(size=a.params["w"].shape)})


def fake_initial(cfg):
    return Agent.initial(META), cfg


def make_pool(root, pool_size=2, **kw) -> tuple[layout.Paths, PoolConfig]:
    paths = layout.Paths(root)
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


STEPS = {"train_steps": 1000, "eval_steps": 100, "parent_eval_steps": 100}  # 1200 env steps per member


T0 = 1_700_000_000.0  # pool creation time of the fake pools


ITERS = 6


def write_heartbeat(paths, m, state, iteration, target=20, last_return=None, **extra):
    fsutil.write_json(paths.heartbeat(m), sign(paths, {
        "member": m, "pid": os.getpid(), "host": HOST, "beat": 1, "state": state, "iteration": iteration,
        "target": target, "learning_rate": 0.01 * 10 ** m, "last_return": last_return, "time": time.time(),
        **extra}))


def fake_pool(root, returns_by_iteration, pool_size=2, **kw):
    paths, _ = make_pool(root, pool_size=pool_size, **kw)
    doc = json.loads(open(paths.pool_json).read())
    doc["created"] = T0
    fsutil.write_json(paths.pool_json, sign(paths, doc))  # test-only rewrite of the create-once file: a known clock
    for i, rets in enumerate(returns_by_iteration, start=1):
        if isinstance(rets, tuple):  # (returns, winner, parent_return)
            write_iteration(paths, i, rets[0], winner=rets[1], parent_return=rets[2])
        else:
            write_iteration(paths, i, rets)
    return paths


def write_iteration(paths, i, returns, winner="branch", t=None, lrs=None, parent_return=None):
    """Pool files of one decided iteration, as members write them: deposits, waits, selection.

    ``returns``: each member's eval return; the best branch wins unless ``winner`` says "parent"
    (then ``parent_return`` is the selected return and the agent is the previous selection's).
    """
    t = T0 + 2.0 * i if t is None else t
    os.makedirs(paths.iteration(i), exist_ok=True)
    lrs = lrs or [0.01 * 10 ** m for m in range(len(returns))]
    for m, ret in enumerate(returns):
        fsutil.write_json(paths.deposit_json(i, m), sign(paths, {
            "iteration": i, "member": m, "eval_return": ret, "learning_rate": lrs[m],
            "train_seconds": 0.5, "eval_seconds": 0.1, "train_return_mean": ret - 1.0, "time": t - 0.1,
            "agent_sha256": "0" * 64, **STEPS}))
        fsutil.write_json(paths.wait_json(i, m), {"iteration": i, "member": m, "wait_seconds": 0.01 * (m + 1)})
    best_m = max(range(len(returns)), key=lambda m: (returns[m], -m))
    prev = deposits.read_selected(paths, i - 1)
    if winner == "branch":
        sel = {"winner": "branch", "member": best_m, "eval_return": returns[best_m],
               "agent": paths.rel(paths.deposit_npz(i, best_m))}
    else:
        sel = {"winner": winner, "member": None, "eval_return": parent_return, "agent": prev["agent"]}
    considered = [{"member": m, "eval_return": r} for m, r in enumerate(returns)]
    claim.create_once(paths.selected(i), fsutil.dumps(sign(paths, {
        "iteration": i, "considered": considered, "skipped": [], "quorum_reason": "complete",
        "agent_sha256": "0" * 64, "time": t, **sel})))


def sign(paths, doc):
    """Sign as a key holder does (pools made by this rl-pool verify what decides anything)."""
    sign = getattr(paths, "sign", None)
    return sign(doc) if sign is not None else doc


def run_pool(d, lrs=(0.003, 0.03), extra=("--lr-adapt", 2, "--seed", 3, "--merge", "sum"), iters=ITERS):
    procs = [spawn("train", "--pool-dir", d, "--pool-size", 2, "--member", m, "--learning-rate", lr,
                   "--iterations", iters, *SHORT, "--quiet", *extra) for m, lr in enumerate(lrs)]
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    return history(d)


def history(d):
    """What must be identical between two runs: selections, every score and every agent's hash."""
    out = []
    i = 1
    while os.path.exists(d / f"iterations/{i:06d}/selected.json"):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        deps = {}
        for m in range(2):
            p = d / f"iterations/{i:06d}/member-{m:03d}.json"
            if p.exists():
                doc = json.loads(p.read_text())
                deps[m] = (doc["eval_return"], doc["eval_returns"], doc["agent_sha256"], doc["learning_rate"],
                           doc["parent_eval_return"])
        out.append((sel["member"], sel["eval_return"], sel["agent_sha256"], deps, sel["winner"]))
        i += 1
    best = json.loads((d / "best.json").read_text())
    out.append(("best", best["iteration"], best["member"], best["eval_return"],
                (d / "best.npz").read_bytes() == (d / best["agent"]).read_bytes()))
    return out


def reference_episode(agent, seed):
    """An independent episode loop on the fully wrapped gymnasium env."""
    env = gym.make(agent.meta.env, max_episode_steps=agent.meta.max_episode_steps)
    obs, _ = env.reset(seed=seed)
    x0 = float(env.unwrapped.data.qpos[0])
    total, done = 0.0, False
    while not done:
        obs, r, term, trunc, _ = env.step(agent.act(obs))
        total += r
        done = term or trunc
    return total, float(env.unwrapped.data.qpos[0]) - x0


def racer(root: str, names: int, me: int, barrier, out) -> None:
    import random
    import time

    jitter = random.Random(me)
    results = []
    for k in range(names):
        barrier.wait()
        # Up to 2 ms apart, so that no racer wins every race by always leaving the barrier first
        # (seen on SeaweedFS: the mount that made the directory won 30 of 30); claims still overlap.
        time.sleep(jitter.uniform(0, 0.002))
        data = json.dumps({"racer": me, "name": k}).encode()
        results.append(claim.create_once(os.path.join(root, f"d{k:03d}.json"), data))
    out.put((me, results))


def tree_remover(trees: list[str], barrier, out) -> None:
    """Remove each of ``trees`` (``claim.remove_tree``) at the same moment as the other removers;
    puts the first exception's ``repr``, or None."""
    try:
        for t in trees:
            barrier.wait(timeout=60)  # a remover that failed breaks it for the others
            claim.remove_tree(t)
    except Exception as exc:
        out.put(repr(exc))
        return
    out.put(None)


def like_agent(paths):
    return deposits.load_selected_agent(paths, 0)


def deposit(paths, i, m, ret, seed=None, parent=None, parent_sha=None):
    extra = {}
    if parent is not None:
        prev = deposits.read_selected(paths, i - 1)
        extra = {"parent_eval_return": parent, "parent_sha256": parent_sha or prev["agent_sha256"]}
    return deposits.deposit(paths, i, m, agent(m if seed is None else seed), {"eval_return": ret, **extra})


def finite_differences(J, params: dict, h: float = 1e-6) -> dict:
    """Central differences of the scalar function ``J`` of named arrays, element by element."""
    out = {}
    for name, w in params.items():
        fd = np.zeros_like(w)
        for idx in np.ndindex(w.shape):
            e = np.zeros_like(w)
            e[idx] = h
            fd[idx] = (J(params | {name: w + e}) - J(params | {name: w - e})) / (2 * h)
        out[name] = fd
    return out


def adam_ascent_by_hand(p: dict, m: dict, v: dict, g: dict, t: float, lr: float, skip: str = "v_") -> None:
    """One Adam step up ``g``, written out array by array in place (bias-corrected for step ``t``);
    arrays named ``skip*`` (the value network's) are left as they are."""
    from rl_pool.maths.learner import ADAM_EPS

    for k in p:
        if k.startswith(skip):
            continue
        gk = np.asarray(g[k])
        m[k] = 0.9 * m[k] + 0.1 * gk
        v[k] = 0.999 * v[k] + 0.001 * gk * gk
        p[k] = p[k] + lr * (m[k] / (1 - 0.9**t)) / (np.sqrt(v[k] / (1 - 0.999**t)) + ADAM_EPS)


def random_opt_state(params: dict, seed: int, t: float):
    """Adam moments well away from zero (and a step count ``t``), so that steps written out test them."""
    from rl_pool.maths.learner import OptState

    rng = np.random.default_rng(seed)
    return OptState({k: rng.normal(size=a.shape) * 0.01 for k, a in params.items()},
                    {k: rng.uniform(0, 0.01, size=a.shape) for k, a in params.items()}, t)
