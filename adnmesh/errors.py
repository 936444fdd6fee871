"""Exceptions that the command line reports as one-line user errors (exit code 2).

Anything else that escapes a command is a bug and keeps its traceback.
"""

__all__ = ["ConfigError", "GridError", "UsageError"]


class ConfigError(Exception):
    """A configuration file is missing, unreadable or invalid.

    The message is the complete one-line error shown to the user, normally of the form
    ``<file>: <key path>: <problem>``, e.g.
    ``configs/x.yaml: ders[3].p_inst_w: must be a positive number, got -2``.
    """


class UsageError(Exception):
    """The command line asks for something that cannot be done (bad argument combination).

    The message is the complete one-line error shown to the user.
    """


class GridError(ConfigError):
    """Bad input to the grid model (unknown grid code, study case, sgen name); the message is
    one complete line for the user.

    A :class:`ConfigError`, so the command line reports it as a one-line error (exit code 2)
    even where a caller does not add the config file and key path itself.
    """
