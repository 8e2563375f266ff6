"""Names of the files in a pool directory (pure: no file is touched here).

The directory itself, and what each file means, is described in ``docs/protocol.md``.
"""

from __future__ import annotations

import re

DEPOSIT_RE = re.compile(r"^member-(\d{3,})\.json$")
ITER_RE = re.compile(r"^\d{6,}$")
MERGED_PREFIX = "merged-"


def member_name(m: int) -> str:
    return f"member-{m:03d}"


def iteration_rel(i: int) -> str:
    return f"iterations/{i:06d}"


def deposit_rel(i: int, m: int) -> str:
    """A member's agent deposit, relative to the pool root."""
    return f"{iteration_rel(i)}/{member_name(m)}.npz"


def merged_name(sha256: str) -> str:
    """The file of a merged agent, named by the SHA-256 of its bytes: two merges computed from
    different sets of deposits (a member that went on with a quorum while a late deposit landed)
    never overwrite each other, and the selection names the one it decided."""
    return f"{MERGED_PREFIX}{sha256[:16]}.npz"
