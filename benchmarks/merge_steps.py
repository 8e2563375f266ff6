"""How consistently a pool's merges step: the cosine between consecutive merge steps.

    python benchmarks/merge_steps.py POOL_DIR
    python benchmarks/merge_steps.py POOL_DIR --branches

For every run of iterations whose selections are merges, the step of each merge is its
parameters minus its parent's (all named arrays, flattened in name order); the script prints each
step's length and its cosine with the next step. Cosines near 1 mean the pool kept going the same
way one mean update at a time (what ``--merge momentum`` exploits; docs/scaling.md).

``--branches`` looks inside each iteration instead, for the iterations whose deposits all still
have their agents on disk (a pool deletes most of them as it goes): the branches' mean step
length, the length of their plain mean step, the ratio of the two and the mean cosine between two
branches' steps. If every step were a shared part ``g`` plus independent noise, that cosine
would estimate ``|g|^2 / |step|^2`` and the mean of k branches would keep about
``sqrt(cos + (1 - cos) / k)`` of a branch's length: how much of each step the branches agree on.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from rl_pool.errors import UsageError


def flat(agent) -> np.ndarray:
    return np.concatenate([np.ravel(agent.params[k]) for k in sorted(agent.params)])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("pool_dir")
    p.add_argument("--branches", action="store_true",
                   help="per iteration: how far the branches step, alone and on average, and how alike")
    args = p.parse_args(argv)
    from rl_pool.protocol import layout

    paths = layout.Paths(args.pool_dir)
    try:
        return branches(paths) if args.branches else merges(paths)
    except UsageError as exc:  # not a pool
        print(f"merge_steps.py: {exc}", file=sys.stderr)
        return 2


def merges(paths) -> int:
    """Print each merge's step length and its cosine with the next merge's step."""
    from rl_pool.protocol import deposits, pool

    pool.read_config(paths, readonly=True)  # a pool, or UsageError
    last = deposits.last_selected(paths)
    steps = []  # (iteration, step) of consecutive merges
    for i in range(1, last + 1):
        sel = deposits.read_selected(paths, i)
        if sel is None or sel.get("winner") != "merge":
            steps.append(None)
            continue
        here = flat(deposits.load_selected_agent(paths, i, sel))
        parent = flat(deposits.load_selected_agent(paths, i - 1))
        steps.append((i, here - parent))
    print(f"{'iteration':>9} {'step length':>11} {'cosine with the next':>20}")
    for a, b in zip(steps, [*steps[1:], None], strict=True):
        if a is None:
            continue
        cos = "" if b is None else f"{float(a[1] @ b[1] / np.linalg.norm(a[1]) / np.linalg.norm(b[1])):.3f}"
        print(f"{a[0]:>9} {float(np.linalg.norm(a[1])):>11.4f} {cos:>20}")
    return 0


def branches(paths) -> int:
    """Print, per iteration with every deposit's agent on disk, how far and how alike its branches stepped."""
    from rl_pool.protocol import deposits, pool

    cfg = pool.read_config(paths, readonly=True)
    print(f"{'iteration':>9} {'branches':>8} {'branch step':>11} {'mean step':>9} {'ratio':>5} {'pair cosine':>11}")
    for i in range(1, deposits.last_selected(paths) + 1):
        agents = []
        for m in range(cfg.pool_size):
            if not os.path.exists(paths.deposit_npz(i, m)):  # deleted as the pool went on: not whole
                break
            try:
                agents.append(flat(deposits.read_deposit(paths, i, m)[1]))
            except ValueError:  # unreadable, or not what its metrics say
                break
        if len(agents) < max(2, cfg.pool_size):
            continue
        try:
            parent = flat(deposits.load_selected_agent(paths, i - 1))
        except (OSError, RuntimeError, UsageError):  # the parent's file is gone or unreadable
            continue
        steps = [a - parent for a in agents]
        lengths = [float(np.linalg.norm(s)) for s in steps]
        if min(lengths) == 0.0:  # a branch that did not move has no direction
            continue
        mean = float(np.linalg.norm(np.mean(steps, axis=0)))
        cos = [float(a @ b) / (la * lb) for j, (a, la) in enumerate(zip(steps, lengths, strict=True))
               for b, lb in zip(steps[j + 1:], lengths[j + 1:], strict=True)]
        branch = float(np.mean(lengths))
        print(f"{i:>9} {len(steps):>8} {branch:>11.4f} {mean:>9.4f} {mean / branch:>5.3f} {np.mean(cos):>11.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
