"""Errors that mean "bad input": the CLI prints them as one line and exits 2."""


class UsageError(Exception):
    """Bad arguments, a bad environment, or a pool directory that does not fit."""


class EnvError(UsageError):
    """The environment id is unknown or its spaces are not supported."""


class AgentFileError(UsageError):
    """An agent file that is unreadable, foreign, or inconsistent."""


class UnsafeFile(OSError):
    """A pool file that is never read: not a regular file (FIFO, socket, device, directory,
    symbolic link), reached through a symbolic link, outside the pool, or larger than its cap.

    An ``OSError`` (``strerror`` says why, ``filename`` names the file), so callers that skip an
    unreadable file skip this one too, and the CLI prints it as one line and exits 2. ``ident``
    is ``(st_dev, st_ino)`` of the refused thing when known, so it can be removed without
    touching a file that took its name since (see :func:`rl_pool.fsutil.set_aside`).
    """

    def __init__(self, err: int, reason: str, filename=None, ident: tuple[int, int] | None = None):
        super().__init__(err, reason, filename)
        self.ident = ident


class Stopped(BaseException):
    """SIGTERM/SIGINT/SIGHUP arrived; every file on disk is whole, so stopping anywhere is safe."""

    def __init__(self, signum: int):
        import signal

        super().__init__(signal.Signals(signum).name)
        self.signum = signum
