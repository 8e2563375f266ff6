"""Errors that mean "bad input": the CLI prints them as one line and exits 2."""


class UsageError(Exception):
    """Bad arguments, a bad environment, or a pool directory that does not fit."""


class EnvError(UsageError):
    """The environment id is unknown or its spaces are not supported."""


class AgentFileError(UsageError):
    """An agent file that is unreadable, foreign, or inconsistent."""
