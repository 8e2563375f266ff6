"""Reading a pool for people: history, best, members (used by status, plot, results export)."""

from __future__ import annotations

import os
import time

from . import fsutil, pool


def _read(path):
    try:
        doc = fsutil.read_json(path)
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _num(x):
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def history(paths: pool.Paths, pool_size: int) -> list[dict]:
    """One row per selected iteration (1, 2, ...) with each member's deposit metrics."""
    rows = []
    for i in pool.iterations_on_disk(paths):
        if i == 0:
            continue
        sel = pool.read_selected(paths, i)
        if sel is None:
            continue
        members = []
        for m in range(pool_size):
            doc = _read(paths.deposit_json(i, m))
            if doc is None:
                continue
            wait = _read(paths.wait_json(i, m)) or {}
            members.append({
                "member": m,
                "eval_return": _num(doc.get("eval_return")),
                "learning_rate": _num(doc.get("learning_rate")),
                "train_steps": doc.get("train_steps"),
                "eval_steps": doc.get("eval_steps"),
                "parent_eval_steps": doc.get("parent_eval_steps"),
                "train_seconds": _num(doc.get("train_seconds")),
                "eval_seconds": _num(doc.get("eval_seconds")),
                "wait_seconds": _num(wait.get("wait_seconds")),
                "time": _num(doc.get("time")),
            })
        rows.append({
            "iteration": i,
            "selected_member": sel.get("member"),
            "winner": sel.get("winner", "branch"),
            "eval_return": _num(sel.get("eval_return")),
            "quorum_reason": sel.get("quorum_reason"),
            "skipped": sel.get("skipped", []),
            "time": _num(sel.get("time")),
            "members": members,
        })
    return rows


def best_of(rows: list[dict]) -> dict | None:
    best = None
    for r in rows:
        if r["eval_return"] is not None and (best is None or r["eval_return"] > best["eval_return"]):
            best = {"iteration": r["iteration"], "member": r["selected_member"], "eval_return": r["eval_return"]}
    return best


def members(paths: pool.Paths, pool_size: int) -> list[dict]:
    """Heartbeats with their age as seen from here (file mtime on this host's clock)."""
    out = []
    for m in range(pool_size):
        hb = pool.read_heartbeat(paths, m)
        if hb is None:
            out.append({"member": m, "state": "absent"})
            continue
        try:
            age = time.time() - os.path.getmtime(paths.heartbeat(m))
        except OSError:
            age = None
        state = hb.get("state")
        if (state not in pool.TERMINAL_STATES and hb.get("host") == pool.HOST
                and isinstance(hb.get("pid"), int) and not pool.pid_alive(hb["pid"])):
            state = "dead"
        out.append({"member": m, "state": state, "iteration": hb.get("iteration"),
                    "pid": hb.get("pid"), "host": hb.get("host"), "heartbeat_age": age,
                    "learning_rate": hb.get("learning_rate"), "last_return": hb.get("last_return"),
                    "error": hb.get("error")})
    return out


def status(pool_dir: str) -> dict:
    paths = pool.Paths(pool_dir)
    cfg = pool.read_config(paths)
    rows = history(paths, cfg.pool_size)
    created = _read(paths.pool_json).get("created")
    for r in rows:
        r["elapsed_seconds"] = (r["time"] - created) if (r["time"] and created) else None
    return {
        "pool_dir": paths.root,
        "pool_size": cfg.pool_size,
        "env": cfg.env,
        "config": cfg.to_json(),
        "iterations_completed": rows[-1]["iteration"] if rows else 0,
        "best": best_of(rows),
        "members": members(paths, cfg.pool_size),
        "history": rows,
    }


def write_csv(st: dict, out: str) -> str:
    """``history.csv``: one row per iteration, each member's return and learning rate, wall time, env steps."""
    import csv

    n = st["pool_size"]
    cols = ["iteration", "selected_member", "winner", "eval_return", "best_so_far", "elapsed_seconds",
            "env_steps"]
    for m in range(n):
        cols += [f"member{m}_eval_return", f"member{m}_learning_rate"]
    steps, best = 0, None
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in st["history"]:
            by = {x["member"]: x for x in r["members"]}
            steps += sum((x.get("train_steps") or 0) + (x.get("eval_steps") or 0) + (x.get("parent_eval_steps") or 0)
                         for x in r["members"])
            if r["eval_return"] is not None:
                best = r["eval_return"] if best is None else max(best, r["eval_return"])
            row = [r["iteration"], r["selected_member"], r["winner"], r["eval_return"], best,
                   None if r["elapsed_seconds"] is None else round(r["elapsed_seconds"], 3), steps]
            for m in range(n):
                x = by.get(m, {})
                row += [x.get("eval_return"), x.get("learning_rate")]
            w.writerow(["" if v is None else v for v in row])
    return out


def format_table(st: dict, last: int = 10) -> str:
    """A status page a person reads at a glance."""
    lines = [f"pool {st['pool_dir']}  env {st['env']}  members {st['pool_size']}  "
             f"iterations completed {st['iterations_completed']}"]
    b = st["best"]
    lines.append("best: none yet" if b is None else
                 f"best: {b['eval_return']:.2f} (iteration {b['iteration']}, member {b['member']})")
    lines.append("")
    lines.append(f"{'member':>6}  {'state':<10} {'iter':>5}  {'lr':>9}  {'last return':>11}  {'heartbeat':>9}")
    for m in st["members"]:
        age = m.get("heartbeat_age")
        lines.append(f"{m['member']:>6}  {m['state'] or '-':<10} {_s(m.get('iteration')):>5}  "
                     f"{_g(m.get('learning_rate')):>9}  {_f(m.get('last_return')):>11}  "
                     f"{('-' if age is None else f'{age:.0f}s ago'):>9}")
        if m.get("error") and m["state"] in ("failed", "stopped"):
            lines.append(f"{'':>8}error: {m['error']}")
    rows = st["history"][-last:]
    if rows:
        lines.append("")
        lines.append(f"{'iter':>5}  {'selected':>8}  {'return':>9}  members (return)")
        for r in rows:
            ms = "  ".join(f"m{x['member']}:{_f(x['eval_return'])}" for x in r["members"])
            who = _s(r["selected_member"]) if r["winner"] == "branch" else r["winner"]
            lines.append(f"{r['iteration']:>5}  {who:>8}  {_f(r['eval_return']):>9}  {ms}")
    return "\n".join(lines)


def _s(x):
    return "-" if x is None else str(x)


def _f(x):
    return "-" if x is None else f"{x:.2f}"


def _g(x):
    return "-" if x is None else f"{x:.3g}"

