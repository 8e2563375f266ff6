"""Summarise learning runs of several seeds: a table and curves vs wall clock and env steps.

    python results/summarize.py OUT.png history-seed0.csv history-seed1.csv ...

Each CSV is ``rl-pool status POOL --csv FILE`` of one run. Prints, per run and
as median [min, max] over runs, the best selected evaluation return at 5, 10
and 20 minutes and the time to reach 350.
"""

import csv
import statistics
import sys

MARKS = (5, 10, 20)
TARGET = 350.0


def load(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    t = [float(r["elapsed_seconds"]) for r in rows]
    steps = [int(r["env_steps"]) for r in rows]
    ret = [float(r["eval_return"]) for r in rows]
    best = [float(r["best_so_far"]) for r in rows]
    return t, steps, ret, best


def best_at(t, best, seconds):
    if t[-1] < seconds - 30:  # the run ended before this mark
        return None
    out = None
    for ti, b in zip(t, best):
        if ti <= seconds:
            out = b
    return out


def time_to(t, best, target):
    return next((ti for ti, b in zip(t, best) if b >= target), None)


def fmt(x, nd=1):
    return "-" if x is None else f"{x:.{nd}f}"


def fmt_spread(v, nd=1):
    return "-" if v is None else f"{fmt(v[0], nd)} [{fmt(v[1], nd)}, {fmt(v[2], nd)}]"


def main(out, paths):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), dpi=110, sharey=True)
    table = []
    for p in paths:
        t, steps, ret, best = load(p)
        name = p.split("/")[-1].removesuffix(".csv")
        a1.plot([x / 60 for x in t], ret, lw=0.8, label=name)
        a2.plot([s / 1e6 for s in steps], ret, lw=0.8, label=name)
        table.append([best_at(t, best, 60 * m) for m in MARKS] + [time_to(t, best, TARGET)])
        print(f"{name:>24}: " + "  ".join(f"{m} min {fmt(v)}" for m, v in zip(MARKS, table[-1]))
              + f"  time to {TARGET:.0f}: {fmt(table[-1][-1], 0)} s")
    cols = list(zip(*table))
    med = []
    for c in cols:
        vals = [v for v in c if v is not None]
        med.append((statistics.median(vals), min(vals), max(vals)) if vals else None)
    print(f"{'median [min, max]':>24}: " + "  ".join(f"{m} min {fmt_spread(v)}" for m, v in zip(MARKS, med[:-1]))
          + f"  time to {TARGET:.0f}: {fmt_spread(med[-1], 0)} s")
    for a in (a1, a2):
        a.axhline(TARGET, color="grey", ls=":", lw=1)
        a.grid(alpha=0.3)
    a1.set_xlabel("wall clock (minutes)")
    a2.set_xlabel("env steps, all members (millions)")
    a1.set_ylabel("selected agent's evaluation return")
    a1.legend(loc="lower right")
    fig.suptitle("Swimmer-v5, default 2-member pool, one curve per root seed")
    fig.tight_layout()
    fig.savefig(out)
    print(out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
