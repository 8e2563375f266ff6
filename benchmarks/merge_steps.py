"""How consistently a pool's merges step: the cosine between consecutive merge steps.

    python benchmarks/merge_steps.py POOL_DIR

For every run of iterations whose selections are merges, the step of each merge is its
parameters minus its parent's (all named arrays, flattened in name order); the script prints each
step's length and its cosine with the next step. Cosines near 1 mean the pool kept going the same
way one mean update at a time (what ``--merge momentum`` exploits; docs/scaling.md).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def flat(agent) -> np.ndarray:
    return np.concatenate([np.ravel(agent.params[k]) for k in sorted(agent.params)])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("pool_dir")
    args = p.parse_args(argv)
    from rl_pool.protocol import deposits, layout

    paths = layout.Paths(args.pool_dir)
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


if __name__ == "__main__":
    sys.exit(main())
