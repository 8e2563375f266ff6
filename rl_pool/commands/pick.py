"""``rl-pool pick``: choose a pool's agent on held-out episodes.

``best.npz`` is the selected agent with the highest mean evaluation return on
its own iteration's episodes. Those episodes change every iteration, so over
hundreds of iterations the highest mean is partly the luck of an easy draw (on
Reacher the return depends mostly on where the target lands; docs/results.md
shows by how much). ``pick`` runs candidate agents on one shared
set of held-out episodes and keeps the one with the highest mean return, so
every candidate meets the same episodes and an easy draw favours none of them.

Candidates are the distinct agents the pool selected (by hash), ranked by the
best evaluation return each reached in the pool: the first ``top`` of them (0:
all), and the last selected agent. Held-out episodes use reset seeds ``seed +
k`` (default from 2,000,000: not the pool's seeds, which are drawn from the
whole 32-bit range, nor ``evaluate``'s default 1,000,000 on), so a later
``rl-pool evaluate`` of the pick scores it on episodes the pick never saw.
Episodes run as in ``evaluate`` (the same worker code): a candidate's mean here
equals ``rl-pool evaluate AGENT --episodes E --seed SEED``.

With ``finalists`` K, the K candidates with the best means go on to ``final_episodes`` more
held-out episodes (the seeds after the first round's), and the pick is the finalist with the
highest mean over all its episodes: a first round of 20 episodes cannot tell an agent that fails
once in 20 starts from one that never does.

The pool is only read, apart from the pick itself: ``POOL/picked.npz`` and
``POOL/picked.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import time

from rl_pool import fsutil
from rl_pool.commands.evaluate import MAX_EPISODES, EvalWorker, capped_children
from rl_pool.errors import AgentFileError, UsageError
from rl_pool.protocol import deposits, layout, pool

DEFAULT_SEED = 2_000_000
#: Candidates (besides the last selected agent) and held-out episodes of a pick by default.
DEFAULT_TOP = 20
DEFAULT_EPISODES = 20
#: Held-out episodes of a final round (``--finalists``), after the first round's.
DEFAULT_FINAL_EPISODES = 100


def candidates(paths: layout.Paths, top: int) -> tuple[list[dict], int]:
    """``(candidates, distinct agents selected)``: the ``top`` distinct selected agents by the best
    evaluation return each reached (0: all; ties: the earlier iteration), then the last selected
    agent if it is not among them. Each: ``agent`` (path in the pool), ``agent_sha256``,
    ``iteration`` (where it reached that return), ``eval_return``, ``last`` (the last selected)."""
    seen: dict[str, dict] = {}
    last = None
    for i in deposits.iterations_on_disk(paths):
        sel = deposits.read_selected(paths, i)
        if sel is None or not isinstance(sel.get("agent"), str) or not isinstance(sel.get("agent_sha256"), str):
            continue
        ret = sel.get("eval_return")
        ret = float(ret) if isinstance(ret, (int, float)) and not isinstance(ret, bool) else None
        c = seen.get(sel["agent_sha256"])
        if c is None:
            c = seen[sel["agent_sha256"]] = {"agent": sel["agent"], "agent_sha256": sel["agent_sha256"],
                                             "iteration": i, "eval_return": ret}
        elif ret is not None and (c["eval_return"] is None or ret > c["eval_return"]):
            c.update(iteration=i, eval_return=ret)
        last = c
    ranked = sorted(seen.values(), key=lambda c: (c["eval_return"] is None, -(c["eval_return"] or 0.0),
                                                   c["iteration"]))
    chosen = ranked if top == 0 else ranked[:top]
    if last is not None and last not in chosen:
        chosen.append(last)
    return [c | {"last": c is last} for c in chosen], len(seen)


def _pool_agent_meta(paths: layout.Paths):
    """The description every agent of the pool shares (its initial agent's, a decided file), or None."""
    try:
        return deposits.load_selected_agent(paths, 0).meta
    except (OSError, ValueError, AgentFileError):
        return None


def episode_steps(paths: layout.Paths, episodes: int = DEFAULT_EPISODES) -> int:
    """The env steps of ``episodes`` held-out episodes at most (one candidate's in a default pick):
    each as long as the pool's episodes (1000 where the pool has no initial agent to say)."""
    meta = _pool_agent_meta(paths)
    return episodes * max(1, meta.max_episode_steps if meta is not None else 1000)


def current_pick(paths: layout.Paths) -> tuple[str, bytes] | None:
    """``(POOL/picked.npz, its bytes)`` when that file is the pick of the pool as it stands, else
    None: its ``picked.json`` saw the pool's last selection (a pool trained on after its pick has
    agents the pick never ran), and the file holds the agent that JSON names, which a selection of
    the pool chose. Read bounded, never through a link, as ``best.npz`` is."""
    npz = os.path.join(paths.root, "picked.npz")
    try:
        doc = fsutil.read_json(os.path.join(paths.root, "picked.json"), root=paths.root)
        picked = doc["picked"]
        if doc["pool_iteration"] != deposits.last_selected(paths):
            return None
        sel = deposits.read_selected(paths, picked["iteration"])
        if sel is None or sel.get("agent_sha256") != picked["agent_sha256"]:
            return None
        data = fsutil.read_bytes(npz, fsutil.AGENT_MAX_BYTES, root=paths.root)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (npz, data) if layout.sha256(data) == picked["agent_sha256"] else None


# Worker processes keep one environment per (task, kwargs, episode length) for every candidate they run.
_ENVS: dict[str, object] = {}


class _SharedEnvWorker(EvalWorker):
    def make_env(self, agent):
        key = json.dumps([agent.meta.env, agent.meta.env_kwargs, agent.meta.max_episode_steps], sort_keys=True)
        if key not in _ENVS:
            _ENVS[key] = super().make_env(agent)
        return _ENVS[key]


def _returns(task: tuple[bytes, list[int], str]) -> list[float]:
    agent_bytes, seeds, mode = task
    worker = _SharedEnvWorker(agent_bytes, mode=mode)
    return [worker(s) for s in seeds]


def _run_all(agents: list[bytes], seeds: list[int], mode: str, workers: int) -> list[list[float]]:
    """Every agent's returns on ``seeds``, over ``workers`` spawned processes (one math thread each)."""
    if workers <= 1:
        return [_returns((a, seeds, mode)) for a in agents]
    # Few candidates: split their episodes too, so every worker has work.
    parts = max(1, min(len(seeds), math.ceil(2 * workers / len(agents))))
    size = math.ceil(len(seeds) / parts)
    tasks = [(a, seeds[k:k + size], mode) for a in agents for k in range(0, len(seeds), size)]
    with capped_children(), mp.get_context("spawn").Pool(workers) as p:
        out = p.map(_returns, tasks, chunksize=1)
    per = len(range(0, len(seeds), size))
    return [[r for part in out[j * per:(j + 1) * per] for r in part] for j in range(len(agents))]


def _why_not_playable(data: bytes, digest: str, source: str, cfg, like=None) -> str | None:
    """None if ``data`` is an agent for the pool's task, else why not (checked here, so a bad
    candidate is skipped rather than failing a worker process). ``like``: the initial agent's
    description, which every agent of the pool shares (as :func:`rl_pool.protocol.deposits.read_agent` checks);
    without it, the pool's env."""
    try:
        meta = deposits.parse_agent(data, digest, source).meta
    except (AgentFileError, ValueError) as exc:
        return str(exc).removeprefix(f"{source}: ")
    if meta != like if like is not None else (meta.env, meta.env_kwargs) != (cfg.env, cfg.env_kwargs):
        return (f"an agent for {meta.env} {json.dumps(meta.env_kwargs)} ({meta.max_episode_steps} steps), "
                f"not this pool's task or policy shape")
    return None


def pick(pool_dir: str, top: int = DEFAULT_TOP, episodes: int = DEFAULT_EPISODES, seed: int = DEFAULT_SEED,
         workers: int = 1, mode: str = "mean", out: str | None = None, finalists: int = 0,
         final_episodes: int = DEFAULT_FINAL_EPISODES) -> dict:
    """Run the candidates on ``episodes`` held-out episodes; with ``finalists`` K, the K best of them
    on ``final_episodes`` more, and pick the finalist with the highest mean over all its episodes."""
    if top < 0 or episodes < 1 or workers < 1 or finalists < 0 or final_episodes < 1:
        raise UsageError("--top and --finalists must be >= 0, --episodes, --final-episodes and --workers positive")
    if episodes + (final_episodes if finalists else 0) > MAX_EPISODES:
        raise UsageError(f"--episodes (plus --final-episodes) must be at most {MAX_EPISODES}")
    paths = layout.Paths(pool_dir)
    cfg = pool.read_config(paths, readonly=True)  # a foreign directory is refused here
    verified = pool.attach_key(paths, required=False)
    # read before the candidates: an iteration that lands meanwhile leaves the pick stale, not wrong
    last_iteration = deposits.last_selected(paths)
    found, distinct = candidates(paths, top)
    like = _pool_agent_meta(paths)
    t0 = time.perf_counter()
    ok, skipped = [], []
    for c in found:
        try:
            data = paths.read_bytes(paths.resolve(c["agent"]))
        except (OSError, ValueError) as exc:
            skipped.append(c | {"reason": str(getattr(exc, "strerror", None) or exc)})
            continue
        if layout.sha256(data) != c["agent_sha256"]:
            skipped.append(c | {"reason": "does not match the hash its selection recorded"})
            continue
        why = _why_not_playable(data, c["agent_sha256"], c["agent"], cfg, like)
        if why:  # only an unverified read (no key) lets such a selection through
            skipped.append(c | {"reason": why})
            continue
        ok.append((c, data))
    if not ok:
        raise UsageError(f"pool {pool_dir} has no selected agent to pick from"
                         + (f" ({len(skipped)} unreadable)" if skipped else ""))
    seeds = [seed + k for k in range(episodes)]
    results = _run_all([data for _, data in ok], seeds, mode, workers)
    rows = [c | _stats(rets) for (c, _), rets in zip(ok, results, strict=True)]
    # the highest held-out mean; ties go to the higher-ranked candidate (listed first)
    ranked = sorted(range(len(rows)), key=lambda j: (-rows[j]["mean_return"], j))
    if finalists:
        # The round's maximum is partly luck too: the leaders play on, on the episodes that follow.
        more = [seed + episodes + k for k in range(final_episodes)]
        leaders = ranked[:finalists]
        finalists = len(leaders)  # as many as there were candidates
        extra = _run_all([ok[j][1] for j in leaders], more, mode, workers)
        for j, rets in zip(leaders, extra, strict=True):
            rows[j] |= {"first_mean_return": rows[j]["mean_return"], "finalist": True}
            rows[j] |= _stats(rows[j]["returns"] + rets)
        ranked = sorted(leaders, key=lambda j: (-rows[j]["mean_return"], j))
    best = ranked[0]
    chosen = rows[best]
    data = ok[best][1]
    npz = out or os.path.join(paths.root, "picked.npz")
    meta = os.path.splitext(npz)[0] + ".json"
    summary = {"pool_dir": str(paths.root), "verified": verified, "episodes": episodes, "seed": seed,
               "mode": mode, "top": top, "finalists": finalists, "final_episodes": final_episodes if finalists else 0,
               "distinct_agents": distinct, "pool_iteration": last_iteration, "seconds": time.perf_counter() - t0,
               "picked": {k: chosen[k] for k in ("iteration", "agent", "agent_sha256", "eval_return",
                                                 "mean_return", "std_return", "episodes")},
               "out": npz}
    if out is None:
        pool.make_room(paths, npz, meta)
    fsutil.atomic_write(npz, data)
    keys = ("iteration", "agent_sha256", "eval_return", "mean_return", "std_return", "episodes", "finalist",
            "first_mean_return")
    fsutil.write_json(meta, summary | {"candidates": [{k: r[k] for k in keys if k in r} for r in rows]})
    return summary | {"candidates": rows, "skipped": skipped}


def _stats(rets: list[float]) -> dict:
    mean = math.fsum(rets) / len(rets)
    std = math.sqrt(math.fsum((r - mean) ** 2 for r in rets) / len(rets))
    return {"mean_return": mean, "std_return": std, "returns": rets, "episodes": len(rets)}


def format_text(res: dict) -> str:
    n = len(res["candidates"])
    which = "all" if res["top"] == 0 else f"the top {res['top']} by evaluation return, and the last selected"
    first, last = res["seed"], res["seed"] + res["episodes"] - 1
    lines = [f"{n} of {res['distinct_agents']} selected agents ({which}) on {res['episodes']} held-out episodes "
             f"(reset seeds {first}..{last}, {res['mode']} actions) "
             f"in {res['seconds']:.1f}s" + ("" if res["verified"] else "; pool files unverified (no key)")]
    if res["finalists"]:
        lines.append(f"the {res['finalists']} best of them on {res['final_episodes']} more (reset seeds "
                     f"{last + 1}..{last + res['final_episodes']}); the pick is the finalist with the highest "
                     f"mean over all its episodes")
    lines.append(f"{'iteration':>9} {'eval return':>12} {'held-out mean':>14} {'std':>8} {'episodes':>8}")
    for r in res["candidates"]:
        ev = "—" if r["eval_return"] is None else f"{r['eval_return']:.2f}"
        mark = " <- picked" if r["agent_sha256"] == res["picked"]["agent_sha256"] else ""
        mark += " (finalist)" if r.get("finalist") and not mark else ""
        mark += " (last selected)" if r.get("last") else ""
        lines.append(f"{r['iteration']:>9} {ev:>12} {r['mean_return']:>14.2f} {r['std_return']:>8.2f} "
                     f"{r['episodes']:>8}{mark}")
    for s in res["skipped"]:
        lines.append(f"skipped iteration {s['iteration']}'s agent {s['agent']}: {s['reason']}")
    p = res["picked"]
    lines.append(f"picked: the agent of iteration {p['iteration']} (held-out mean {p['mean_return']:.2f}), "
                 f"written to {res['out']}")
    return "\n".join(lines)
