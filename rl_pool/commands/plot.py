"""``rl-pool plot``: per-iteration evaluation return of a pool, to a PNG."""

from __future__ import annotations

import os

from rl_pool.commands.status import status


def plot_pool(pool_dir: str, out: str | None = None) -> str:
    st = status(pool_dir)  # raises UsageError for a missing or foreign directory
    out = out or os.path.join(st["pool_dir"], "progress.png")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    rows = [r for r in st["history"] if r["eval_return"] is not None]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    xs, ys, cs = [], [], []
    for r in st["history"]:
        for m in r["members"]:
            if m["eval_return"] is not None and m["learning_rate"]:
                xs.append(r["iteration"])
                ys.append(m["eval_return"])
                cs.append(m["learning_rate"])
    if xs:
        lo, hi = min(cs), max(cs)
        norm = LogNorm(vmin=lo, vmax=hi if hi > lo else lo * 1.0001)
        sc = ax.scatter(xs, ys, c=cs, cmap="viridis", norm=norm, s=6, alpha=0.6, linewidths=0,
                        label="each member's evaluation", zorder=1)
        fig.colorbar(sc, ax=ax, label="member learning rate")
    if rows:
        it = [r["iteration"] for r in rows]
        ret = [r["eval_return"] for r in rows]
        ax.plot(it, ret, color="tab:red", lw=1.0, label="selected agent", zorder=2)
        best, run = [], float("-inf")
        for v in ret:
            run = max(run, v)
            best.append(run)
        ax.plot(it, best, color="black", lw=1.5, ls="--", label="best so far", zorder=3)
    ax.set_xlabel("iteration")
    ax.set_ylabel("evaluation return (mean over episodes)")
    b = st["best"]
    title = f"{st['env']}, pool of {st['pool_size']}"
    if b is not None:
        title += f" — best {b['eval_return']:.1f} at iteration {b['iteration']}"
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if rows or xs:
        ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
