"""Learning scaling: iterations, env steps and minutes to a return threshold for pools of N members.

    python benchmarks/learning.py --env Swimmer-v5 --threshold 350 --sizes 2,8 --seeds 0,1,2
    python benchmarks/learning.py --preset halfcheetah --threshold 3000 --sizes 2,8 --seeds 0

Each pool is the default launch (``rl-pool launch``, with ``--preset`` when given, and any
further options after ``--``), stopped as soon as its best evaluated return reaches the
threshold, or at ``--max-iterations``. Pools run one after another, each on every core, so
minutes compare only within one run on one machine; iterations and env steps do not depend on
the machine (the runs are deterministic in their seed). The last table gives each size's median
iterations, env steps and minutes, and how many times fewer iterations than 2 members (or the
smallest size, without 2) needed. ``--summary`` prints that table again from the JSON lines of
earlier runs (``--out``), one table per set of launch options, e.g. several files' seeds together:

    python benchmarks/learning.py --summary results/scaling/device-16core-preset.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

from rl_pool.errors import SignalLatch

#: Ctrl-C as KeyboardInterrupt, kept: one that lands in a finaliser is only printed and lost, so
#: the poll loop of :func:`run_pool` raises it again (``check``).
_interrupt = SignalLatch(lambda signum: KeyboardInterrupt())


def _progress(pool_dir: str) -> list[dict]:
    from rl_pool.commands import status

    try:
        return status.curve(status.status(pool_dir))
    except Exception:  # the pool is still being made
        return []


def run_pool(pool_dir: str, size: int, seed: int, threshold: float, max_iterations: int,
             options: list[str], poll: float = 2.0) -> dict:
    """Run one pool until its best evaluated return reaches ``threshold``; what it took."""
    cmd = [sys.executable, "-m", "rl_pool", "launch", "--pool-dir", pool_dir, "--pool-size", str(size),
           "--seed", str(seed), "--iterations", str(max_iterations), "--quiet",
           "--no-pick", *options]  # the time to the threshold is the measure: no pick after a capped run
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    hit = None
    try:
        while hit is None:
            _interrupt.check()
            done = proc.poll() is not None
            rows = _progress(pool_dir)
            hit = next((r for r in rows if r["best_so_far"] is not None and r["best_so_far"] >= threshold), None)
            if done:
                break
            time.sleep(poll)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    rows = _progress(pool_dir)
    last = rows[-1] if rows else {}
    out = {"size": size, "seed": seed, "reached": hit is not None,
           "iterations": hit["iteration"] if hit else None,
           "env_steps": hit["env_steps"] if hit else None,
           "minutes": round(hit["elapsed_seconds"] / 60, 2) if hit else None,
           "ran_iterations": last.get("iteration"), "best": last.get("best_so_far"),
           "ran_minutes": round(last["elapsed_seconds"] / 60, 2) if last else None,
           "wall_minutes": round((time.monotonic() - t0) / 60, 2)}
    if proc.returncode not in (0, -signal.SIGINT, 130) and hit is None:
        out["error"] = proc.stderr.read().decode(errors="replace")[-400:] if proc.stderr else ""
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default=None, help="task (default: the preset's, else Swimmer-v5)")
    p.add_argument("--preset", default=None)
    p.add_argument("--threshold", type=float, default=None, help="the return to reach (required unless --summary)")
    p.add_argument("--sizes", default="2,8", help="pool sizes, comma-separated")
    p.add_argument("--seeds", default=None, help="comma-separated (default 0,1,2; with --summary: every seed)")
    p.add_argument("--max-iterations", type=int, default=150)
    p.add_argument("--workdir", default=None, help="where the pools go (default: a temporary directory)")
    p.add_argument("--out", default=None, help="also write the results as JSON lines here")
    p.add_argument("--summary", nargs="+", metavar="JSONL", default=None,
                   help="run nothing: print the summary tables of result lines written earlier by --out "
                        "(with --seeds given, only those seeds)")
    p.add_argument("options", nargs=argparse.REMAINDER, help="-- then further rl-pool launch options")
    args = p.parse_args(argv)
    seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else None
    if args.summary:
        return summarize_files(args.summary, seeds)
    seeds = seeds or [0, 1, 2]
    if args.threshold is None:
        p.error("--threshold is required (unless --summary)")
    options = [o for o in args.options if o != "--"]
    if args.preset:
        options = ["--preset", args.preset, *options]
    if args.env:
        options = ["--env", args.env, *options]
    sizes = [int(x) for x in args.sizes.split(",")]
    work = args.workdir or tempfile.mkdtemp(prefix="rl-pool-learning-")
    print(f"# {' '.join(options) or 'defaults'}; threshold {args.threshold}; pools in {work}", flush=True)
    print(f"{'N':>3} {'seed':>4} {'iterations':>10} {'env steps':>12} {'minutes':>8}  best", flush=True)
    results = []
    for size in sizes:
        for seed in seeds:
            d = os.path.join(work, f"n{size}-s{seed}")
            r = run_pool(d, size, seed, args.threshold, args.max_iterations, options)
            results.append(r)
            it = r["iterations"] if r["reached"] else f">{r['ran_iterations']}"
            print(f"{size:>3} {seed:>4} {it!s:>10} {r['env_steps'] or '-'!s:>12} {r['minutes'] or '-'!s:>8}  "
                  f"{r['best']}" + (f"  ERROR {r['error']}" if r.get("error") else ""), flush=True)
            if args.out:
                with open(args.out, "a") as fh:
                    fh.write(json.dumps(r | {"options": options, "threshold": args.threshold}) + "\n")
    print_summary(results, sizes)
    return 0


def _median(rs: list[dict], key: str, bound: str | None = None) -> tuple[float, bool]:
    """``(median, exact)`` of ``key`` over pools ``rs``. A pool that did not get there needed more
    than its ``bound`` (the iterations it ran); counting it as just that gives a lower bound of the
    median (``exact`` False) whenever such a pool is one of the middle values. Without ``bound``
    such a median is unknown (inf)."""
    inf = float("inf")
    exact = statistics.median([r[key] if r["reached"] else inf for r in rs])
    if exact != inf or bound is None:
        return exact, exact != inf
    return statistics.median([r[key] if r["reached"] else r[bound] or 0 for r in rs]), False


def summary(results: list[dict], sizes: list[int], base_size: int | None = None) -> list[tuple[int, str, str, str, str]]:
    """Per pool size: the median iterations, env steps and minutes to the threshold over its seeds,
    and how many times fewer iterations than ``base_size`` needed (default: 2 members where the
    sizes have it, else the first size). Pools that failed with an error are left out. A median of
    pools that did not all get there reads as a lower bound (``>X``); a ratio against one as a
    bound (``>`` or ``<``), or ``-`` when nothing can be said."""
    if base_size is None:
        base_size = _base_size(sizes)
    stats = {}
    for size in sizes:
        rs = [r for r in results if r["size"] == size and not r.get("error")]
        if rs:
            if any(r["reached"] and r.get("minutes") is None for r in rs):
                minutes = (float("inf"), False)  # not recorded
            elif all(r.get("ran_minutes") is not None for r in rs):
                minutes = _median(rs, "minutes", bound="ran_minutes")
            else:
                minutes = _median(rs, "minutes")
            stats[size] = (_median(rs, "iterations", bound="ran_iterations"), _median(rs, "env_steps"), minutes)
    base = stats[base_size][0] if base_size in stats else (0.0, False)
    rows = []
    for size in sizes:
        if size not in stats:
            rows.append((size, "-", "-", "-", "-"))
            continue
        (med, exact), (steps, steps_exact), (minutes, minutes_exact) = stats[size]
        if size == base_size:
            ratio = "1.00x"
        elif med <= 0 or base[0] <= 0 or (not exact and not base[1]):
            ratio = "-"
        else:
            ratio = f"{'' if exact and base[1] else '>' if exact else '<'}{base[0] / med:.2f}x"
        if minutes == float("inf"):
            mins = "-"
        else:
            mins = f"{minutes:g}" if minutes_exact else f">{minutes:g}"
        rows.append((size, f"{med:g}" if exact else f">{med:g}", ratio, f"{steps:.0f}" if steps_exact else "-", mins))
    return rows


def _base_size(sizes: list[int]) -> int:
    """The size the ratios compare against: 2 members where the sizes have it, else the first."""
    return 2 if 2 in sizes else sizes[0]


def print_summary(results: list[dict], sizes: list[int]) -> None:
    base = _base_size(sizes)
    print(f"\n{'N':>3} {'median iterations':>18} {'fewer than N=' + str(base):>16} {'median env steps':>17} "
          f"{'median minutes':>15}")
    for row in summary(results, sizes, base):
        print(f"{row[0]:>3} {row[1]:>18} {row[2]:>16} {row[3]:>17} {row[4]:>15}")


def summarize_files(paths: list[str], seeds: list[int] | None = None) -> int:
    """The summary tables of JSON lines that ``--out`` wrote earlier (or rows in the same form),
    one table per launch option set and threshold, in the order they first appear."""
    groups: dict[tuple, list[dict]] = {}
    for path in paths:
        try:
            with open(path) as fh:
                lines = [line for line in fh if line.strip()]
        except OSError as e:
            print(f"learning.py: cannot read {path}: {e.strerror}", file=sys.stderr)
            return 2
        for n, line in enumerate(lines, 1):
            try:
                r = json.loads(line)
                key = (" ".join(r.get("options", [])) or "defaults", r["threshold"], r.get("experiment"))
                if not {"size", "seed", "reached", "iterations", "ran_iterations"} <= r.keys():
                    raise KeyError("a field the summary needs")
            except (ValueError, KeyError, TypeError):
                print(f"learning.py: {path}:{n}: not a result line", file=sys.stderr)
                return 2
            if seeds is None or r["seed"] in seeds:
                groups.setdefault(key, []).append(r)
    for (options, threshold, experiment), rs in groups.items():
        sizes = sorted({r["size"] for r in rs})
        seeds_seen = sorted({r["seed"] for r in rs})
        print(f"# {options}; threshold {threshold}" + (f"; experiment {experiment}" if experiment else "")
              + f"; seeds {','.join(map(str, seeds_seen))}")
        print_summary(rs, sizes)
        print()
    return 0


if __name__ == "__main__":
    _interrupt.install((signal.SIGINT,))  # the script's own process only, never a caller's
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # run_pool has stopped the pool it was running
        print("learning.py: interrupted; the running pool was stopped, the lines written so far stay",
              file=sys.stderr)
        sys.exit(130)
