"""Errors that mean "bad input": the CLI prints them as one line and exits 2."""

import os


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


class SignalLatch:
    """Turns the first of a process's stop signals into an exception in its main thread, and keeps it.

    Python runs a signal handler between two bytecodes of the main thread, and those may belong
    to a finaliser: an abandoned generator being closed, a ``__del__``. An exception raised there
    is only printed ("Exception ignored in ...") and lost, so a process that acted on its first
    signal alone would run on. ``handler`` raises ``make(signum)`` for the first signal and
    ignores later ones (a second Ctrl-C must not cut a clean shutdown short); the process's
    loops call :meth:`check`, which raises it again (once the process acts on it, it leaves
    those loops and nothing calls ``check`` any more).
    """

    def __init__(self, make):
        self.make = make
        self.signum: int | None = None

    def handler(self, signum, frame) -> None:
        if self.signum is None:
            self.signum = signum
            raise self.make(signum)

    def check(self) -> None:
        if self.signum is not None:
            raise self.make(self.signum)

    def install(self, signums) -> dict:
        """Handle ``signums`` (from a clean slate); returns the old handlers for ``restore``."""
        import signal

        self.signum = None
        return {s: signal.signal(s, self.handler) for s in signums}

    @staticmethod
    def restore(old: dict) -> None:
        import signal

        for s, h in old.items():
            signal.signal(s, h)


def drop_output(stream) -> None:
    """Point ``stream`` (stdout or stderr) at /dev/null once its reader has gone (a closed pipe),
    so that nothing written later, nor the interpreter's last flush, fails again (Python would
    print "Exception ignored ... BrokenPipeError" and exit 120)."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return
    try:
        os.dup2(fd, stream.fileno())
    except (OSError, ValueError, AttributeError):
        pass  # a stream without a descriptor of its own
    finally:
        os.close(fd)
