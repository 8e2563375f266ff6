"""Where each file of a pool lives: its names (pure functions) and :class:`Paths`, which joins
them to a pool's root and reads its files bounded, never through a link, checking signatures.

The directory itself, and what each file means, is described in ``docs/protocol.md``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re

from rl_pool import fsutil
from rl_pool.protocol import claim

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


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class Paths:
    """Where each file of a pool lives."""

    def __init__(self, root):
        self.root = fsutil.Root(root)
        self.pool_json = os.path.join(self.root, "pool.json")
        self.lock = os.path.join(self.root, ".init.lock")
        self.iterations = os.path.join(self.root, "iterations")
        self.members = os.path.join(self.root, "members")
        self.logs = os.path.join(self.root, "logs")
        self.best_npz = os.path.join(self.root, "best.npz")
        self.best_json = os.path.join(self.root, "best.json")
        self._legacy: bool | None = None

    def iteration(self, i: int) -> str:
        return os.path.join(self.iterations, f"{i:06d}")

    def initial(self) -> str:
        return os.path.join(self.iteration(0), "initial.npz")

    def deposit_npz(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".npz")

    def deposit_json(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".json")

    def wait_json(self, i: int, m: int) -> str:
        return os.path.join(self.iteration(i), member_name(m) + ".wait.json")

    def selected(self, i: int) -> str:
        return os.path.join(self.iteration(i), "selected.json")

    def heartbeat(self, m: int) -> str:
        return os.path.join(self.members, member_name(m) + ".json")

    def log(self, m: int) -> str:
        return os.path.join(self.logs, member_name(m) + ".log")

    def holding(self, d: str):
        """Reads below directory ``d`` start from one descriptor while the block runs (fsutil.Root)."""
        return self.root.holding(d)

    def rel(self, path: str) -> str:
        return os.path.relpath(path, self.root)

    #: The pool's key (:mod:`rl_pool.protocol.keys`) once :func:`open_pool` or :func:`attach_key` found it.
    #: With a key every decision file is signed when written and checked when read; without one
    #: (a reader such as ``status`` that cannot find the key) files are read unverified.
    key = None

    def sign(self, doc: dict) -> dict:
        return self.key.sign(doc) if self.key is not None else doc

    def why_unsigned(self, doc) -> str | None:
        """None if ``doc`` may decide something here, else why not (unsigned, bad signature)."""
        return None if self.key is None else self.key.why_invalid(doc)

    def signed(self, payload: bytes) -> str | None:
        """``accept`` for :mod:`rl_pool.protocol.claim`: why a decided JSON document may not decide here."""
        try:
            doc = json.loads(payload.decode("utf-8"))
        except ValueError:
            return "not JSON"
        return self.why_unsigned(doc)

    def decision(self, path: str, cap: int = fsutil.JSON_MAX_BYTES, signed: bool = True) -> bytes | None:
        """The decided bytes of ``path`` (``pool.json``, ``initial.npz``, ``selected.json``), or None.
        In a pool made before decisions (protocol 2: ``pool.json`` without ``.pool.json.once``),
        the plain file, for readers such as ``status`` (members refuse such pools)."""
        data = claim.read_once(path, root=self.root, cap=cap, accept=self.signed if signed else None)
        if data is None and self.legacy():
            try:
                data = self.read_bytes(path, cap)
            except FileNotFoundError:
                return None
        return data

    def legacy(self) -> bool:
        if self._legacy is None:
            self._legacy = os.path.exists(self.pool_json) and not os.path.isdir(claim.decision_dir(self.pool_json))
        return self._legacy

    def read_json(self, path: str, missing_retries: int = 0):
        """A JSON file of this pool, read bounded and never through a link (:mod:`rl_pool.fsutil`)."""
        return fsutil.read_json(path, missing_retries=missing_retries, root=self.root)

    def read_object(self, path: str, signed: bool = False) -> dict | None:
        """A JSON object of this pool, or None if it is missing, unreadable or not an object; with
        ``signed``, also None unless a key holder wrote it (for readers: status, TensorBoard, best)."""
        try:
            doc = self.read_json(path)
        except (OSError, ValueError):
            return None
        if not isinstance(doc, dict) or (signed and self.why_unsigned(doc)):
            return None
        return doc

    def read_bytes(self, path: str, cap: int = fsutil.AGENT_MAX_BYTES, missing_retries: int = 0) -> bytes:
        """A file of this pool (an agent), read bounded and never through a link."""
        return fsutil.read_bytes(path, cap, missing_retries=missing_retries, root=self.root)

    def resolve(self, rel: str) -> str:
        """A path named inside a pool file, refused if it points outside the pool."""
        full = os.path.normpath(os.path.join(self.root, rel))
        if os.path.isabs(rel) or not full.startswith(self.root + os.sep):
            raise ValueError(f"path {rel!r} points outside the pool")
        return full
