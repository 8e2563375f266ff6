"""Small filesystem primitives for the shared directory.

Everything written into a pool is written whole or not at all: a temp file in
the same directory, flushed and fsynced, then ``os.replace`` (atomic on POSIX
and on NFS). Create-once decisions live in :mod:`rl_pool.protocol.claim`. A write
that fails (full disk, read-only filesystem) removes its temp file and raises
with the real name as ``filename``; nothing half written ever has a real name.

Nothing read from a pool is trusted (docs/security.md). Every read here:

* opens ``O_NONBLOCK`` (a FIFO cannot make it wait) and ``O_NOFOLLOW``, after
  an ``lstat`` that refuses anything but a regular file (a device is never
  even opened), and checks the open file again with ``fstat`` (only a file
  the user names on the command line may be a link, to a regular file);
* with ``root`` (the pool directory) walks the path from ``root`` one
  directory at a time with ``O_NOFOLLOW | O_DIRECTORY`` relative to the
  previous one, so no symlinked directory (``iterations/000003 -> /dev``)
  leads out of the pool; the pool directory itself is the user's choice and
  may be a link;
* with a :class:`Root` holding a directory below it open (``with root.holding(d)``),
  walks from that descriptor instead: a member waiting at a barrier opens its
  iteration directory once, not once for every file it reads there;
* refuses a file larger than its cap before reading and reads at most cap + 1
  bytes, so a file that grows while it is read is refused, not read forever.

A refused file raises :class:`~rl_pool.errors.UnsafeFile` (an ``OSError``):
selection skips it with its reason, commands print one line and exit 2.
This relies on POSIX ``openat``/``O_NOFOLLOW`` semantics, which Linux gives on
local filesystems and on NFS clients alike.
"""

from __future__ import annotations

import errno
import json
import math
import os
import socket
import stat
import threading
import time
import uuid
from contextlib import contextmanager

from rl_pool.errors import UnsafeFile

TMP_MARK = ".tmp-"

#: Cap on a JSON file read from a pool: heartbeats, deposits' metrics and selections are a few KiB.
JSON_MAX_BYTES = 1 << 20
#: Cap on an agent file when the pool's shapes are not at hand (``best.npz``, ``evaluate FILE``);
#: with them, :func:`rl_pool.maths.agent.max_file_bytes` is the cap.
AGENT_MAX_BYTES = 64 << 20
_CHUNK = 1 << 20

#: Errors worth one more try on a network filesystem (stale handle, interrupted I/O).
TRANSIENT = {errno.ESTALE, errno.EIO, errno.EINTR, errno.EAGAIN, errno.ETIMEDOUT}


def writer_token(random_hex: int = 8) -> str:
    """``{host}-{pid}-{random}``: who writes (short host name and process id, so a leftover can be
    traced to a dead writer, :func:`tmp_owner`) and a random part that makes it unique."""
    return f"{socket.gethostname().split('.')[0]}-{os.getpid()}-{uuid.uuid4().hex[:random_hex]}"


def tmp_name(path: str) -> str:
    """``.{name}.tmp-{host}-{pid}-{random}``: unique, and names its writer (see :func:`tmp_owner`)."""
    d, base = os.path.split(os.fspath(path))
    return os.path.join(d, f".{base}{TMP_MARK}{writer_token()}")


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


def _named(exc: OSError, path: str) -> OSError:
    """``exc`` again, naming ``path`` (the file being written) rather than its temp file."""
    return OSError(exc.errno, exc.strerror or str(exc), path)  # the errno's own subclass (ENOSPC: OSError)


def _write_tmp(path: str, data: bytes, durable: bool = True) -> str:
    tmp = tmp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            if durable:
                os.fsync(fd)  # a network filesystem may report a full disk only here or at close
        finally:
            os.close(fd)
    except BaseException as exc:
        _unlink_quiet(tmp)
        if isinstance(exc, OSError):
            raise _named(exc, path) from None
        raise
    return tmp


def _unlink_quiet(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def atomic_write(path, data: bytes, sync_dir: bool = True, durable: bool = True) -> None:
    """Replace ``path`` with ``data`` atomically.

    ``durable``: fsync the data before the rename (and the directory after it, with
    ``sync_dir``), so a machine that crashes keeps the file whole or the old one. Files
    that only say how things are going (heartbeats, wait times) skip both: after a
    crash they are rewritten or ignored, and each fsync is a disk flush (on NFS a
    COMMIT to the server) that a pool of N members would make N times an iteration.
    Atomicity against readers and killed writers is the rename's, either way."""
    path = os.fspath(path)
    tmp = _write_tmp(path, data, durable)
    try:
        os.replace(tmp, path)
    except BaseException as exc:
        _unlink_quiet(tmp)
        if isinstance(exc, OSError):
            raise _named(exc, path) from None
        raise
    if sync_dir and durable:
        _fsync_dir(os.path.dirname(path))


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


def write_json(path, obj, sync_dir: bool = True, durable: bool = True) -> None:
    atomic_write(path, dumps(obj), sync_dir=sync_dir, durable=durable)


_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"),
          (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"))


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def _not_regular(st: os.stat_result, path: str) -> UnsafeFile:
    err = errno.ELOOP if stat.S_ISLNK(st.st_mode) else errno.EISDIR if stat.S_ISDIR(st.st_mode) \
        else errno.EINVAL
    return UnsafeFile(err, f"{_kind(st.st_mode)}, not a regular file", path, (st.st_dev, st.st_ino))


def _parts(path: str, root: str) -> list[str]:
    """``path``'s components below ``root``; UnsafeFile if it is not below it."""
    if isinstance(root, Root) and path.startswith(root + os.sep):  # a Root is absolute, so is path
        # The common case, cheaply (a member walks a dozen paths an iteration): an absolute, already
        # normal path below the pool's (normal) root; anything else is normalised below.
        parts = path[len(root) + 1:].split(os.sep)
        if all(p not in ("", ".", "..") for p in parts):
            return parts
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
    parts = [p for p in rel.split(os.sep) if p not in ("", ".")]
    if ".." in parts:
        raise UnsafeFile(errno.EXDEV, "outside the pool directory", path)
    return parts


class Root(str):
    """A pool directory's path (a ``str``) that can hold directories below it open.

    ``with root.holding(d):`` opens ``d`` once (walked from the root as every
    read is) and, in that thread, reads and listings below ``d`` start from
    that descriptor (``openat(held, ".")``, then the file): on a network
    filesystem a lookup of each path component is a round trip to the server,
    made once instead of once per file. The held descriptor keeps naming the
    directory it opened even if a stranger renames another in its place, which
    is what a walk from the root would have found when the hold began.
    """

    def __new__(cls, path):
        obj = super().__new__(cls, os.path.abspath(os.fspath(path)))
        obj._local = threading.local()
        return obj

    def __reduce__(self):  # held descriptors belong to this process: a copy starts with none
        return Root, (str(self),)

    def held(self) -> dict:
        if not hasattr(self._local, "fds"):
            self._local.fds = {}
        return self._local.fds

    @contextmanager
    def holding(self, d):
        d = os.path.abspath(os.fspath(d))
        held = self.held()
        if d in held:
            yield
            return
        try:
            fd = _open_dir(d, self)
        except OSError:  # not there (yet) or refused: reads walk from the root and say why
            yield
            return
        held[d] = fd
        try:
            yield
        finally:
            del held[d]
            os.close(fd)


def _open_dir(path: str, root: str | None, target: str | None = None) -> int:
    """A descriptor of directory ``path``. With ``root``: reached from ``root`` one component at a
    time, never through a symbolic link (``root`` itself is opened as given), or from the nearest
    directory a :class:`Root` holds. ``target``: the file wanted in it, named in errors (default:
    ``path``)."""
    target = path if target is None else target
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC
    if root is None:
        return os.open(path or ".", flags)
    parts = _parts(path, root)
    base, fd = root, None
    if isinstance(root, Root):
        held = root.held()
        for k in range(len(parts), 0, -1):
            start = os.path.join(root, *parts[:k])
            if start in held:
                # Open "." afresh rather than dup the held descriptor: on NFS an open of a
                # directory revalidates its cached attributes (close-to-open), so listings and
                # lookups below it see other hosts' new files as a walk from the root would.
                base, fd, parts = start, os.open(".", flags, dir_fd=held[start]), parts[k:]
                break
    if fd is None:
        fd = os.open(root, flags)
    try:
        for k, part in enumerate(parts):
            try:
                nfd = os.open(part, flags | os.O_NOFOLLOW, dir_fd=fd)
            except OSError as exc:
                if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                    where = os.path.join(base, *parts[:k + 1])
                    try:
                        st = os.stat(part, dir_fd=fd, follow_symlinks=False)
                        what = _kind(st.st_mode)
                    except OSError:
                        what = "not a directory"
                    why = (f"{what}, not a directory of the pool"
                           if os.path.abspath(where) == os.path.abspath(target)
                           else f"reached through {where}, which is {what}, not a directory of the pool")
                    raise UnsafeFile(exc.errno, why, target) from None
                raise OSError(exc.errno, exc.strerror, target) from None  # FileNotFoundError & co.
            os.close(fd)
            fd = nfd
    except BaseException:
        os.close(fd)
        raise
    return fd


def open_regular(path, root=None, follow: bool = False) -> tuple[int, os.stat_result]:
    """``(fd, fstat)`` of the regular file ``path``, opened read-only without blocking.

    ``root``: the pool directory ``path`` lies in (see the module docstring).
    ``follow``: follow a symbolic link in the last component (only for a file the
    user named, never for a pool file). Anything else raises :class:`UnsafeFile`.
    """
    path = os.fspath(path)
    d, name = os.path.split(os.path.abspath(path))
    dfd = _open_dir(d, root, path)
    try:
        # Look before opening, so a device is never even opened (opening one can have effects).
        st = os.stat(name, dir_fd=dfd, follow_symlinks=follow)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(st, path)
        flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow else os.O_NOFOLLOW)
        try:
            fd = os.open(name, flags, dir_fd=dfd)
        except OSError as exc:
            if exc.errno in (errno.ELOOP, errno.ENXIO):  # replaced by a link or a socket since the lstat
                raise UnsafeFile(exc.errno, "not a regular file", path) from None
            raise OSError(exc.errno, exc.strerror, path) from None
    except FileNotFoundError as exc:
        raise FileNotFoundError(errno.ENOENT, exc.strerror or "No such file or directory", path) from None
    finally:
        os.close(dfd)
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise _not_regular(st, path)
    return fd, st


def _read_capped(path, cap: int, root, follow: bool) -> bytes:
    fd, st = open_regular(path, root, follow)
    try:
        if st.st_size > cap:
            raise UnsafeFile(errno.EFBIG, f"larger than the {cap}-byte cap ({st.st_size} bytes)", path,
                             (st.st_dev, st.st_ino))
        chunks, left = [], cap + 1
        while left > 0:
            chunk = os.read(fd, min(left, _CHUNK))
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
            left -= len(chunk)
        raise UnsafeFile(errno.EFBIG, f"grew past the {cap}-byte cap while being read", path,
                         (st.st_dev, st.st_ino))
    finally:
        os.close(fd)


def read_bytes(path, cap: int = AGENT_MAX_BYTES, retries: int = 3, missing_retries: int = 0,
               root=None, follow: bool = False) -> bytes:
    """Read a whole regular file of at most ``cap`` bytes, never blocking and never following a
    link (see the module docstring); :class:`UnsafeFile` if it is anything else.

    Transient network-filesystem errors are retried with backoff. ``missing_retries``:
    also retry "no such file" that many times, for files another host's listing says
    exist (an NFS client may cache a stale negative lookup for a moment). A refused
    file is never retried.
    """
    delay = 0.01
    for attempt in range(max(retries, missing_retries) + 1):
        try:
            return _read_capped(path, cap, root, follow)
        except UnsafeFile:
            raise
        except FileNotFoundError:
            if attempt >= missing_retries:
                raise
        except OSError as exc:
            if exc.errno not in TRANSIENT or attempt >= retries:
                raise
        time.sleep(delay)  # 10, 20, 40, ... ms
        delay *= 2
    raise AssertionError("unreachable")


def read_json(path, missing_retries: int = 0, root=None, cap: int = JSON_MAX_BYTES):
    """Parse a JSON file read as :func:`read_bytes` does; raises OSError (UnsafeFile included)
    or ValueError (incl. JSONDecodeError, UnicodeDecodeError, and nesting too deep to parse)."""
    data = read_bytes(path, cap, missing_retries=missing_retries, root=root).decode("utf-8")
    try:
        return json.loads(data)
    except RecursionError:  # a megabyte of "[" parses past the interpreter's stack
        raise ValueError(f"{path}: JSON nested too deeply") from None


def lstat(path, root=None) -> os.stat_result:
    """``os.lstat(path)``, reaching the parent as reads do: with ``root``, no symbolic link on the
    way (UnsafeFile), and the parent directory opened afresh (on NFS that revalidates its cached
    entries, so a name another host just created is not hidden by a cached "no such file")."""
    path = os.fspath(path)
    if root is None:
        return os.lstat(path)
    d, name = os.path.split(os.path.abspath(path))
    dfd = _open_dir(d, root, path)
    try:
        return os.stat(name, dir_fd=dfd, follow_symlinks=False)
    except FileNotFoundError as exc:
        raise FileNotFoundError(errno.ENOENT, exc.strerror or "No such file or directory", path) from None
    finally:
        os.close(dfd)


def listdir(path, root=None) -> list[str]:
    """Names in directory ``path`` ([] if it does not exist). With ``root``, ``path`` is reached
    as in :func:`read_bytes` (a symlinked or non-directory component raises UnsafeFile)."""
    return [e.name for e in _scan(path, root)]


def subdirs(path, root=None) -> list[str]:
    """Names of the real directories in ``path`` (no symbolic links, no files)."""
    return [e.name for e in _scan(path, root) if e.is_dir(follow_symlinks=False)]


def _scan(path, root) -> list[os.DirEntry]:
    path = os.fspath(path)
    delay = 0.01
    for attempt in range(4):
        try:
            if root is None:
                with os.scandir(path) as it:
                    return list(it)
            fd = _open_dir(path, root)
            try:
                with os.scandir(fd) as it:
                    return list(it)
            finally:
                os.close(fd)
        except FileNotFoundError:
            return []
        except UnsafeFile:
            raise
        except OSError as exc:
            if exc.errno not in TRANSIENT or attempt == 3:
                raise
            time.sleep(delay)
            delay *= 4
    return []


def set_aside(path, ident: tuple[int, int], root=None) -> bool:
    """Remove the refused thing at ``path`` (``ident``: its ``UnsafeFile.ident``) from the name.

    For create-once names (``selected.json``) and replaced ones (``best.json``) that a
    stranger has occupied with something the protocol never writes there (a FIFO, a
    directory, a link, a huge file). What is at the name is renamed aside first
    (atomic), then looked at: a regular file other than ``ident`` is a writer's whole
    file that took the name in between, and is put back (``link``, never over another);
    anything else is removed. True if the name is free of the refused thing. A directory
    that is not empty stays under a hidden name, which no reader looks at.
    """
    path = os.fspath(path)
    d, name = os.path.split(os.path.abspath(path))
    aside = f".{name}.refused-{uuid.uuid4().hex[:8]}"
    dfd = _open_dir(d, root)
    try:
        try:
            os.rename(name, aside, src_dir_fd=dfd, dst_dir_fd=dfd)
        except FileNotFoundError:
            return True
        st = os.stat(aside, dir_fd=dfd, follow_symlinks=False)
        if stat.S_ISREG(st.st_mode) and (st.st_dev, st.st_ino) != tuple(ident):
            # A writer's whole file took the name since it was refused: put it back.
            try:
                os.link(aside, name, src_dir_fd=dfd, dst_dir_fd=dfd, follow_symlinks=False)
            except FileExistsError:
                pass  # yet another file has the name now; that one stands
            os.unlink(aside, dir_fd=dfd)
            return False
        try:
            if stat.S_ISDIR(st.st_mode):
                os.rmdir(aside, dir_fd=dfd)
            else:
                os.unlink(aside, dir_fd=dfd)
        except OSError:
            pass
        return True
    finally:
        os.close(dfd)


def open_append(path, root=None):
    """A log file of the pool opened for appending (binary), never blocking and never through a link:
    a FIFO, device, directory or link a stranger put at the name is set aside first."""
    path = os.fspath(path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
    for _ in range(3):
        try:
            fd = os.open(path, flags, 0o644)
        except OSError as exc:
            if exc.errno not in (errno.ELOOP, errno.ENXIO, errno.EISDIR):
                raise
            st = os.lstat(path)  # a link (ELOOP), a FIFO without reader (ENXIO) or a directory
            set_aside(path, (st.st_dev, st.st_ino), root=root)
            continue
        st = os.fstat(fd)
        if stat.S_ISREG(st.st_mode):
            os.set_blocking(fd, True)
            return os.fdopen(fd, "ab")
        os.close(fd)
        set_aside(path, (st.st_dev, st.st_ino), root=root)
    raise UnsafeFile(errno.EEXIST, "keeps being replaced by something that is not a file", path)


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


def why(exc: Exception) -> str:
    """A refused or unreadable file's reason, for logs and ``skipped`` entries."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
