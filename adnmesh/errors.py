"""Exceptions that the command line reports as one-line user errors (exit code 2).

Anything else that escapes a command is a bug and keeps its traceback.
"""

__all__ = ["ConfigError", "UsageError"]


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
