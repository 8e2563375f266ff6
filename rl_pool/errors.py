"""Errors that mean "bad input": the CLI prints them as one line and exits 2."""


class UsageError(Exception):
    """Bad arguments, a bad environment, or a pool directory that does not fit."""


class EnvError(UsageError):
    """The environment id is unknown or its spaces are not supported."""


class AgentFileError(UsageError):
    """An agent file that is unreadable, foreign, or inconsistent."""


class Stopped(BaseException):
    """SIGTERM/SIGINT/SIGHUP arrived; every file on disk is whole, so stopping anywhere is safe."""

    def __init__(self, signum: int):
        import signal

        super().__init__(signal.Signals(signum).name)
        self.signum = signum
