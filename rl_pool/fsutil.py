"""Small filesystem primitives for the shared directory.

Everything written into a pool is written whole or not at all: a temp file in
the same directory, flushed and fsynced, then ``os.replace`` (atomic on POSIX
and on NFS). ``create_exclusive`` uses ``os.link`` of a complete temp file,
which fails if the target exists: an atomic create-once that, unlike
``O_EXCL`` on old NFS or ``flock``, needs no server-side lock support.
"""

from __future__ import annotations

import errno
import json
import math
import os
import socket
import time
import uuid

TMP_MARK = ".tmp-"

#: Errors worth one more try on a network filesystem (stale handle, interrupted I/O).
TRANSIENT = {errno.ESTALE, errno.EIO, errno.EINTR, errno.EAGAIN, errno.ETIMEDOUT}


def tmp_name(path: str) -> str:
    """``.{name}.tmp-{host}-{pid}-{random}``: unique, and names its writer (see :func:`tmp_owner`)."""
    d, base = os.path.split(os.fspath(path))
    host = socket.gethostname().split(".")[0]
    return os.path.join(d, f".{base}{TMP_MARK}{host}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _fsync_dir(d: str) -> None:
    try:
        fd = os.open(d or ".", os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_tmp(path: str, data: bytes) -> str:
    tmp = tmp_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        _unlink_quiet(tmp)
        raise
    os.close(fd)
    return tmp


def _unlink_quiet(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def atomic_write(path, data: bytes, sync_dir: bool = True) -> None:
    """Replace ``path`` with ``data`` atomically."""
    path = os.fspath(path)
    tmp = _write_tmp(path, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        _unlink_quiet(tmp)
        raise
    if sync_dir:
        _fsync_dir(os.path.dirname(path))


def create_exclusive(path, data: bytes) -> bool:
    """Create ``path`` with ``data`` unless it exists. True if this call created it."""
    path = os.fspath(path)
    tmp = _write_tmp(path, data)
    try:
        os.link(tmp, path)
        created = True
    except FileExistsError:
        # On NFS a retransmitted LINK whose first reply was lost answers EEXIST even though
        # this call made the link: then the temp file has two names.
        created = os.stat(tmp).st_nlink == 2
    finally:
        _unlink_quiet(tmp)
    if created:
        _fsync_dir(os.path.dirname(path))
    return created


def finite_or_null(obj):
    """``obj`` with every non-finite float (nested in dicts and lists) replaced by None."""
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_or_null(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj) -> bytes:
    return (json.dumps(obj, indent=1, sort_keys=True, allow_nan=False) + "\n").encode()


def write_json(path, obj, sync_dir: bool = True) -> None:
    atomic_write(path, dumps(obj), sync_dir=sync_dir)


def read_bytes(path, retries: int = 3, missing_retries: int = 0) -> bytes:
    """Read a whole file, retrying transient network-filesystem errors with backoff.

    ``missing_retries``: also retry "no such file" that many times, for files
    another host's listing says exist (an NFS client may cache a stale
    negative lookup for a moment).
    """
    delay = 0.01
    for attempt in range(max(retries, missing_retries) + 1):
        try:
            with open(path, "rb") as fh:
                return fh.read()
        except FileNotFoundError:
            if attempt >= missing_retries:
                raise
        except OSError as exc:
            if exc.errno not in TRANSIENT or attempt >= retries:
                raise
        time.sleep(delay)  # 10, 20, 40, ... ms
        delay *= 2
    raise AssertionError("unreachable")


def read_json(path, missing_retries: int = 0):
    """Parse a JSON file; raises OSError or ValueError (incl. JSONDecodeError)."""
    return json.loads(read_bytes(path, missing_retries=missing_retries).decode("utf-8"))


def listdir(path) -> list[str]:
    delay = 0.01
    for attempt in range(4):
        try:
            return os.listdir(path)
        except FileNotFoundError:
            return []
        except OSError as exc:
            if exc.errno not in TRANSIENT or attempt == 3:
                raise
            time.sleep(delay)
            delay *= 4
    return []


def is_tmp(name: str) -> bool:
    return TMP_MARK in name and name.startswith(".")


def tmp_owner(name: str) -> tuple[str, int] | None:
    """``(host, pid)`` of the process that made a temp file, from its name."""
    if not is_tmp(name):
        return None
    tail = name.rsplit(TMP_MARK, 1)[1]  # "{host}-{pid}-{rand}"; host may contain '-'
    try:
        host, pid, _ = tail.rsplit("-", 2)
        return host, int(pid)
    except ValueError:
        return None
