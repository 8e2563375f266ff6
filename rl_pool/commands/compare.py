"""``rl-pool compare``: several runs (seeds, tasks, settings) side by side.

Each input is a pool directory or a ``history.csv`` (``rl-pool status POOL
--csv FILE``; the committed ones under ``results/``). Runs of the same *group*
(pools whose ``pool.json`` and learning rates agree except for the seed; CSV
files in one folder whose names differ only by a ``seedN`` part; or groups
named with ``--groups``) are summarised together: the plot shows each group's
median curve with the min-max range across its runs, against wall-clock time
and against env steps (all members, training and evaluation), and the printed
table gives per run and per group (median [min, max]) the best return at
given times (or env steps: runs from machines of different speeds compare at equal
samples) and the time and env steps to a threshold.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import statistics
from dataclasses import dataclass

import numpy as np

from rl_pool.commands import status
from rl_pool.errors import UsageError

#: Times (minutes) at which the table reports the best return so far, unless --at says otherwise.
DEFAULT_AT = (1.0, 2.0, 5.0, 10.0, 20.0)
_SEED = re.compile(r"[-_.]?seed[-_]?\d+", re.IGNORECASE)
_CSV_COLUMNS = ("elapsed_seconds", "env_steps", "eval_return")


@dataclass
class Run:
    """One run's curve: per selected iteration, elapsed wall seconds, env steps so far and returns."""

    name: str
    group: str
    seconds: np.ndarray
    steps: np.ndarray
    ret: np.ndarray      # selected agent's evaluation return (nan where none)
    best: np.ndarray     # best so far

    @property
    def duration(self) -> float:
        return float(self.seconds[-1]) if len(self.seconds) else 0.0

    def best_at(self, seconds: float) -> float | None:
        """Best return so far at ``seconds`` of wall clock; None if the run had stopped well before it."""
        if self.duration < seconds - min(30.0, 0.05 * seconds):
            return None
        return self._best_upto(self.seconds, seconds)

    def best_at_steps(self, steps: float) -> float | None:
        """Best return so far once ``steps`` env steps were taken (the last iteration at or before
        them); None if the run stopped more than 5% short of them."""
        if not len(self.steps) or not self.steps[-1] >= 0.95 * steps:
            return None
        return self._best_upto(self.steps, steps)

    def _best_upto(self, axis: np.ndarray, x: float) -> float | None:
        """Best so far at the last iteration whose ``axis`` value (seconds or env steps) is <= ``x``."""
        k = int(np.searchsorted(axis, x, side="right"))
        if k == 0 or not np.isfinite(self.best[k - 1]):
            return None
        return float(self.best[k - 1])

    def reach(self, threshold: float) -> tuple[float | None, float | None]:
        """(seconds, env steps) when the selected return first reached ``threshold``."""
        hit = np.nonzero(self.best >= threshold)[0]
        if not len(hit):
            return None, None
        return float(self.seconds[hit[0]]), float(self.steps[hit[0]])


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _running_best(ret: np.ndarray) -> np.ndarray:
    filled = np.where(np.isfinite(ret), ret, -np.inf)
    best = np.maximum.accumulate(filled) if len(filled) else filled
    return np.where(np.isfinite(best), best, np.nan)


def _from_rows(name: str, group: str, rows: list[dict]) -> Run:
    rows = [r for r in rows if math.isfinite(_float(r.get("elapsed_seconds")))]
    seconds = np.array([_float(r["elapsed_seconds"]) for r in rows], dtype=float)
    steps = np.array([_float(r.get("env_steps")) for r in rows], dtype=float)
    ret = np.array([_float(r.get("eval_return")) for r in rows], dtype=float)
    order = np.argsort(seconds, kind="stable")
    seconds, steps, ret = seconds[order], steps[order], ret[order]
    return Run(name, group, seconds, steps, ret, _running_best(ret))


def load_csv(path: str) -> Run:
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in _CSV_COLUMNS if c not in (reader.fieldnames or ())]
            if missing:
                raise UsageError(f"{path} is not a history.csv of rl-pool (no column {missing[0]!r})")
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UsageError(f"cannot read {path}: {exc}") from None
    stem = os.path.splitext(os.path.basename(path))[0]
    folder = os.path.dirname(os.path.abspath(path))
    rest = _SEED.sub("", stem)
    # history-seed0.csv ... history-seed2.csv in seeds/: one group "seeds"; a lone history.csv is its folder's run
    label = os.path.basename(folder) if rest in ("", "history") else rest
    name = os.path.basename(folder) if stem == "history" else stem
    run = _from_rows(name, "", rows)
    run.group = f"csv:{folder}:{label}\0{label}"
    return run


def load_pool(path: str) -> Run:
    st = status.status(path)  # UsageError for a missing or foreign directory
    cfg = {k: v for k, v in st["config"].items() if k != "seed"}
    first = st["history"][0]["members"] if st["history"] else []
    lrs = [m.get("learning_rate") for m in sorted(first, key=lambda m: m["member"])]
    key = json.dumps({"config": cfg, "learning_rates": lrs}, sort_keys=True)
    label = f"{st['env']} lr " + "/".join(f"{x:g}" for x in lrs if isinstance(x, (int, float)))
    run = _from_rows(os.path.basename(os.path.normpath(path)) or path, "", status.curve(st))
    run.group = f"pool:{key}\0{label}"
    return run


def load(path: str) -> Run:
    """A pool directory or a ``history.csv``."""
    if os.path.isdir(path):
        return load_pool(path)
    if os.path.isfile(path):
        return load_csv(path)
    raise UsageError(f"no pool directory or history.csv at {path}")


def group_runs(runs: list[Run], names: list[str] | None = None) -> dict[str, list[Run]]:
    """``{label: runs}`` in input order; ``names`` (one per run) overrides the automatic groups."""
    if names is not None:
        if len(names) != len(runs):
            raise UsageError(f"--groups has {len(names)} names for {len(runs)} inputs")
        keys = [(n, n) for n in names]
    else:
        keys = [tuple(r.group.split("\0", 1)) for r in runs]
    # the same label for different keys (e.g. two folders of seeds): tell them apart
    labels: dict[str, str] = {}
    used: dict[str, int] = {}
    for key, label in keys:
        if key not in labels:
            n = used.get(label, 0)
            used[label] = n + 1
            labels[key] = label if n == 0 else f"{label} ({n + 1})"
    out: dict[str, list[Run]] = {}
    for run, (key, _) in zip(runs, keys, strict=True):
        run.group = labels[key]
        out.setdefault(labels[key], []).append(run)
    return out


# ---------------------------------------------------------------- table
def _spread(values: list[float | None]) -> tuple[float, float, float, int] | None:
    vals = [v for v in values if v is not None]
    if not vals:
        return None
    return statistics.median(vals), min(vals), max(vals), len(vals)


def _fmt(x: float | None, nd: int = 1, scale: float = 1.0) -> str:
    return status.fixed(None if x is None else x / scale, nd)


def _fmt_spread(s, nd: int = 1, scale: float = 1.0, of: int = 0) -> str:
    if s is None:
        return "-"
    med, lo, hi, n = s
    text = f"{med / scale:.{nd}f} [{lo / scale:.{nd}f}, {hi / scale:.{nd}f}]"
    return text + (f" ({n}/{of})" if n < of else "")


def table(groups: dict[str, list[Run]], threshold: float | None, at_minutes, at_steps=()) -> str:
    """Per run and per group: iterations, duration, best at each time (``at_minutes``) and at each
    count of env steps (``at_steps``, millions), time and env steps to ``threshold``."""
    longest = max((r.duration for rs in groups.values() for r in rs), default=0.0)
    marks = [m for m in at_minutes if m * 60 <= longest + min(30.0, 3.0 * m)]
    if not marks and not at_steps:
        marks = list(at_minutes[:1])
    # (header, best so far of a run at that mark): wall-clock marks, then env-step marks
    cols = [(f"best at {m:g} min", lambda r, m=m: r.best_at(60 * m)) for m in marks]
    cols += [(f"best at {s:g} M steps", lambda r, s=s: r.best_at_steps(1e6 * s)) for s in at_steps]
    head = ["run", "iterations", "minutes", "best"] + [h for h, _ in cols]
    if threshold is not None:
        head += [f"time to {threshold:g} (s)", f"env steps to {threshold:g} (M)"]
    rows = []
    for label, runs in groups.items():
        for r in runs:
            cells = [r.name if r.name == label or len(runs) == 1 else f"{label}/{r.name}",
                     str(len(r.seconds)), _fmt(r.duration, 1, 60.0),
                     _fmt(float(np.nanmax(r.best)) if np.isfinite(r.best).any() else None, 1)]
            cells += [_fmt(at(r)) for _, at in cols]
            if threshold is not None:
                t, s = r.reach(threshold)
                cells += [_fmt(t, 0), _fmt(s, 2, 1e6)]
            rows.append(cells)
        if len(runs) > 1:
            n = len(runs)
            cells = [f"{label}: median [min, max]", "", "",
                     _fmt_spread(_spread([float(np.nanmax(r.best)) if np.isfinite(r.best).any() else None
                                          for r in runs]), of=n)]
            cells += [_fmt_spread(_spread([at(r) for r in runs]), of=n) for _, at in cols]
            if threshold is not None:
                reach = [r.reach(threshold) for r in runs]
                cells += [_fmt_spread(_spread([t for t, _ in reach]), 0, of=n),
                          _fmt_spread(_spread([s for _, s in reach]), 2, 1e6, of=n)]
            rows.append(cells)
    widths = [max(len(h), *(len(r[k]) for r in rows)) for k, h in enumerate(head)]
    lines = ["  ".join(h.ljust(w) if k < 1 else h.rjust(w) for k, (h, w) in enumerate(zip(head, widths, strict=True)))]
    for r in rows:
        lines.append("  ".join(c.ljust(w) if k < 1 else c.rjust(w)
                               for k, (c, w) in enumerate(zip(r, widths, strict=True))))
    note = ("(n/m: only n of the group's m runs reached the threshold or lasted that long)"
            if any("/" in c and c.endswith(")") for r in rows for c in r[1:]) else "")
    return "\n".join(lines + ([note] if note else []))


# ---------------------------------------------------------------- plot
def _step_values(x: np.ndarray, y: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The value of step function (x, y) at each grid point: the last y at or before it; nan before x[0] and
    after the run ended."""
    k = np.searchsorted(x, grid, side="right") - 1
    out = np.where(k >= 0, y[np.clip(k, 0, None)], np.nan)
    return np.where(grid <= x[-1], out, np.nan)


def _band(runs: list[Run], axis: str, metric: str, points: int = 400):
    xs = [getattr(r, axis) for r in runs]
    hi = max(float(x[-1]) for x in xs)
    grid = np.linspace(0.0, hi, points)
    vals = np.vstack([_step_values(x, getattr(r, metric), grid) for x, r in zip(xs, runs, strict=True)])
    ok = np.isfinite(vals).sum(axis=0) >= 1
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.where(ok, vals, 0.0), axis=0)
            lo = np.nanmin(np.where(ok, vals, 0.0), axis=0)
            hi_ = np.nanmax(np.where(ok, vals, 0.0), axis=0)
    return grid[ok], med[ok], lo[ok], hi_[ok]


def plot(groups: dict[str, list[Run]], out: str, threshold: float | None = None, metric: str = "ret",
         title: str | None = None) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), dpi=110, sharey=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (label, runs) in enumerate(groups.items()):
        runs = [r for r in runs if len(r.seconds)]
        if not runs:
            continue
        c = colors[k % len(colors)]
        n = len(runs)
        name = label if n == 1 else f"{label} (median of {n}, range shaded)"
        for ax, axis, scale in ((a1, "seconds", 60.0), (a2, "steps", 1e6)):
            if n == 1:
                r = runs[0]
                ax.step(getattr(r, axis) / scale, getattr(r, metric), where="post", color=c, lw=1.0, label=name)
                continue
            x, med, lo, hi = _band(runs, axis, metric)
            ax.fill_between(x / scale, lo, hi, color=c, alpha=0.2, lw=0)
            ax.plot(x / scale, med, color=c, lw=1.3, label=name)
    for ax in (a1, a2):
        if threshold is not None:
            ax.axhline(threshold, color="grey", ls=":", lw=1)
        ax.grid(alpha=0.3)
    a1.set_xlabel("wall clock (minutes)")
    a2.set_xlabel("env steps, all members (millions)")
    a1.set_ylabel("best return so far" if metric == "best" else "selected agent's evaluation return")
    a1.legend(loc="lower right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def compare(paths: list[str], out: str | None = None, threshold: float | None = None,
            at_minutes=DEFAULT_AT, groups: list[str] | None = None, metric: str = "selected",
            title: str | None = None, at_steps=()) -> str:
    """Load, group, plot (if ``out``) and return the table as text. ``at_steps``: millions of env
    steps at which the table also reports the best return so far."""
    if not paths:
        raise UsageError("give at least one pool directory or history.csv")
    if threshold is not None and not math.isfinite(threshold):
        raise UsageError(f"--threshold must be a finite number, got {threshold}")
    if (not at_minutes and not at_steps) or any(not (math.isfinite(m) and m > 0) for m in at_minutes):
        raise UsageError("--at takes positive minutes, e.g. 1,5,20")
    if any(not (math.isfinite(s) and s > 0) for s in at_steps):
        raise UsageError("--at-steps takes positive millions of env steps, e.g. 1,2.5,5")
    runs = [load(p) for p in paths]
    grouped = group_runs(runs, groups)
    text = table(grouped, threshold, sorted(at_minutes), sorted(at_steps))
    if out:
        plot(grouped, out, threshold, "best" if metric == "best" else "ret", title)
    return text
