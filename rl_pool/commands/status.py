"""Reading a pool for people: history, best, members (used by status, plot, progress, compare)."""

from __future__ import annotations

import os
import re
import time

from rl_pool.protocol import deposits, heartbeat, layout, pool, selection

_AGENT_RE = re.compile(r"^iterations/(\d{6,})/(?:member-(\d{3,})\.npz|initial\.npz)$")


def _num(x):
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def agent_from(sel: dict) -> dict | None:
    """Where a selection's agent was made: ``{"iteration", "member"}`` (member None: the initial agent).

    A branch win names its own deposit; a parent win or a revert names an older
    selection's file, so this says whose training the pool is running on.
    """
    mm = _AGENT_RE.match(str(sel.get("agent", "")))
    if mm is None:
        return None
    return {"iteration": int(mm.group(1)), "member": None if mm.group(2) is None else int(mm.group(2))}


def describe(row: dict, origin: bool = True) -> str:
    """Who won a history row (or ``best``): ``member 1``, ``the parent``, ``a revert to iteration 7``...

    With ``origin``, a parent or revert also says whose agent it is (member and iteration that trained it).
    """
    win = row.get("winner", "branch")
    member = row.get("selected_member", row.get("member"))
    if win == "branch":
        return f"member {member}"
    origin = row.get("agent_from") if origin else None
    made = ""
    if isinstance(origin, dict):
        made = (" (the initial agent)" if origin.get("member") is None else
                f" (member {origin['member']}'s agent of iteration {origin['iteration']})")
    if win == "revert":
        return f"a revert to iteration {row.get('reverted_to', '?')}{made}"
    if win == "carried":
        return "the parent, carried (no valid deposit)" + made
    if win == "merge":
        members = (row.get("merge") or {}).get("members") or []
        # best.json names no members: its record says only that a merge won
        return "a merge of members " + ", ".join(str(m) for m in members) if members else "a merge"
    if win == "fallback":
        return "the fallback (the merge scored lower)" + made
    return "the parent" + made


def short_winner(row: dict) -> str:
    """``m1``, ``parent``, ``revert``, ``carried``: for narrow columns."""
    win = row.get("winner", "branch")
    return f"m{row.get('selected_member', row.get('member'))}" if win == "branch" else str(win)


def _int(x):
    return int(x) if isinstance(x, int) and not isinstance(x, bool) and x >= 0 else None


def history(paths: layout.Paths, pool_size: int, first: int = 1) -> list[dict]:
    """One row per selected iteration (``first``, ``first + 1``, ...) with each member's deposit metrics."""
    rows = []
    for i in deposits.iterations_on_disk(paths):
        if i < max(1, first):
            continue
        sel = deposits.read_selected(paths, i)
        if sel is not None:
            rows.append(history_row(paths, sel, pool_size))
    return rows


def history_row(paths: layout.Paths, sel: dict, pool_size: int) -> dict:
    """The history row of one selection: the winner and every member's deposit metrics."""
    i = sel["iteration"]
    members = []
    for m in range(pool_size):
        doc = paths.read_object(paths.deposit_json(i, m))
        if doc is None:
            continue
        wait = paths.read_object(paths.wait_json(i, m)) or {}
        members.append({
            "member": m,
            "eval_return": _num(doc.get("eval_return")),
            "learning_rate": _num(doc.get("learning_rate")),
            "train_steps": _int(doc.get("train_steps")),
            "eval_steps": _int(doc.get("eval_steps")),
            "parent_eval_steps": _int(doc.get("parent_eval_steps")),
            "fallback_eval_steps": _int(doc.get("fallback_eval_steps")),
            "train_seconds": _num(doc.get("train_seconds")),
            "eval_seconds": _num(doc.get("eval_seconds")),
            "wait_seconds": _num(wait.get("wait_seconds")),
            "time": _num(doc.get("time")),
        })
    return {
        "iteration": i,
        "selected_member": sel.get("member"),
        "winner": sel.get("winner", "branch"),
        "agent_from": agent_from(sel),
        "reverted_to": sel.get("reverted_to"),
        "merge": sel.get("merge"),
        "rate_scale": selection.recorded_rate_scale(sel),
        "eval_return": _num(sel.get("eval_return")),
        "quorum_reason": sel.get("quorum_reason"),
        "skipped": sel.get("skipped", []),
        "time": _num(sel.get("time")),
        "members": members,
    }


def best_of(rows: list[dict]) -> dict | None:
    best = None
    for r in rows:
        if r["eval_return"] is not None and (best is None or r["eval_return"] > best["eval_return"]):
            best = {"iteration": r["iteration"], "member": r["selected_member"], "eval_return": r["eval_return"],
                    "winner": r.get("winner", "branch"), "agent_from": r.get("agent_from")}
    return best


def members(paths: layout.Paths, pool_size: int) -> list[dict]:
    """Heartbeats with their age as seen from here (file mtime on this host's clock)."""
    out = []
    for m in range(pool_size):
        hb = heartbeat.read_heartbeat(paths, m)
        if hb is None:
            out.append({"member": m, "state": "absent"})
            continue
        try:
            age = time.time() - os.path.getmtime(paths.heartbeat(m))
        except OSError:
            age = None
        state = hb.get("state")
        if (state not in heartbeat.TERMINAL_STATES and hb.get("host") == heartbeat.HOST
                and isinstance(hb.get("pid"), int) and not heartbeat.pid_alive(hb["pid"])):
            state = "dead"
        out.append({"member": m, "state": state, "iteration": hb.get("iteration"),
                    "pid": hb.get("pid"), "host": hb.get("host"), "heartbeat_age": age,
                    "learning_rate": hb.get("learning_rate"), "last_return": hb.get("last_return"),
                    "target": hb.get("target"), "error": hb.get("error")})
    return out


def status(pool_dir: str) -> dict:
    paths = layout.Paths(pool_dir)
    cfg = pool.read_config(paths, readonly=True)
    # With the key (the default path, --key-file's env var) only key holders' files count, as for
    # members; a reader without it sees the files unverified, and says so.
    verified = pool.attach_key(paths, required=False)
    rows = history(paths, cfg.pool_size)
    doc = paths.read_object(paths.pool_json) or {}
    created = _num(doc.get("created"))
    for r in rows:
        r["elapsed_seconds"] = (r["time"] - created) if (r["time"] and created) else None
    return {
        "pool_dir": paths.root,
        "pool_size": cfg.pool_size,
        "env": cfg.env,
        "config": cfg.to_json(),
        "verified": verified,
        "created": created,
        "versions": recorded_versions(doc),
        "iterations_completed": rows[-1]["iteration"] if rows else 0,
        "best": best_of(rows),
        "members": members(paths, cfg.pool_size),
        "history": rows,
    }


def recorded_versions(doc: dict) -> dict | None:
    """``pool.json``'s ``versions`` (python, numpy, jax, ... at creation), or None if it has none."""
    v = doc.get("versions")
    if not isinstance(v, dict):
        return None
    return {str(k): (x if isinstance(x, str) or x is None else str(x)) for k, x in list(v.items())[:32]}


def curve(st: dict) -> list[dict]:
    """Per iteration: selected return, best so far, elapsed wall seconds and env steps of all members so far.

    Env steps count training, evaluation and the parent's re-scoring: every
    step any member simulated.
    """
    out, steps, best = [], 0, None
    for r in st["history"]:
        steps += sum((x.get("train_steps") or 0) + (x.get("eval_steps") or 0) + (x.get("parent_eval_steps") or 0)
                     + (x.get("fallback_eval_steps") or 0)
                     for x in r["members"])
        if r["eval_return"] is not None:
            best = r["eval_return"] if best is None else max(best, r["eval_return"])
        out.append({"iteration": r["iteration"], "selected_member": r["selected_member"], "winner": r["winner"],
                    "eval_return": r["eval_return"], "best_so_far": best,
                    "elapsed_seconds": r["elapsed_seconds"], "env_steps": steps})
    return out


def write_csv(st: dict, out: str) -> str:
    """``history.csv``: one row per iteration, each member's return and learning rate, wall time, env steps."""
    import csv

    n = st["pool_size"]
    cols = ["iteration", "selected_member", "winner", "eval_return", "best_so_far", "elapsed_seconds",
            "env_steps"]
    for m in range(n):
        cols += [f"member{m}_eval_return", f"member{m}_learning_rate"]
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r, c in zip(st["history"], curve(st), strict=True):
            by = {x["member"]: x for x in r["members"]}
            row = [r["iteration"], r["selected_member"], r["winner"], r["eval_return"], c["best_so_far"],
                   None if r["elapsed_seconds"] is None else round(r["elapsed_seconds"], 3), c["env_steps"]]
            for m in range(n):
                x = by.get(m, {})
                row += [x.get("eval_return"), x.get("learning_rate")]
            w.writerow(["" if v is None else v for v in row])
    return out


def format_table(st: dict, last: int = 10) -> str:
    """A status page a person reads at a glance."""
    lines = [f"pool {st['pool_dir']}  env {st['env']}  members {st['pool_size']}  "
             f"iterations completed {st['iterations_completed']}"]
    if st.get("verified") is False:
        lines.append("unverified: the pool's key was not found (--key-file's RL_POOL_KEY_FILE), "
                     "so signatures were not checked")
    b = st["best"]
    lines.append("best: none yet" if b is None else
                 f"best: {b['eval_return']:.2f} (iteration {b['iteration']}, {describe(b)})")
    v = st.get("versions")
    if v:
        from rl_pool.versions import differences, format_versions

        lines.append(f"versions: {format_versions(v)}")
        diff = differences(v)
        if diff:
            lines.append("  installed here: " + format_versions({k: now for k, (_, now) in diff.items()}))
    lines.append("")
    lines.append(f"{'member':>6}  {'state':<10} {'iter':>5}  {'lr':>9}  {'last return':>11}  {'heartbeat':>9}")
    for m in st["members"]:
        age = m.get("heartbeat_age")
        lines.append(f"{m['member']:>6}  {m['state'] or '-':<10} {cell(m.get('iteration')):>5}  "
                     f"{general(m.get('learning_rate')):>9}  {fixed(m.get('last_return')):>11}  "
                     f"{('-' if age is None else f'{age:.0f}s ago'):>9}")
        if m.get("error") and m["state"] in ("failed", "stopped"):
            lines.append(f"{'':>8}error: {m['error']}")
    rows = st["history"][-last:]
    if rows:
        lines.append("")
        lines.append(f"{'iter':>5}  {'selected':>8}  {'return':>9}  members (return)")
        for r in rows:
            ms = "  ".join(f"m{x['member']}:{fixed(x['eval_return'])}" for x in r["members"])
            who = cell(r["selected_member"]) if r["winner"] == "branch" else r["winner"]
            lines.append(f"{r['iteration']:>5}  {who:>8}  {fixed(r['eval_return']):>9}  {ms}")
    return "\n".join(lines)


def cell(x) -> str:
    """A value for a table cell: ``-`` when there is none (status, progress and compare share these)."""
    return "-" if x is None else str(x)


def fixed(x, nd: int = 2) -> str:
    """A number with ``nd`` decimals, or ``-``."""
    return "-" if not isinstance(x, (int, float)) or isinstance(x, bool) else f"{x:.{nd}f}"


def general(x) -> str:
    """A number with 3 significant digits, or ``-``."""
    return "-" if not isinstance(x, (int, float)) or isinstance(x, bool) else f"{x:.3g}"

