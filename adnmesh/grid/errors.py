"""The error the grid package raises for bad input (unknown grid code, study case, sgen name)."""

from __future__ import annotations

from adnmesh.errors import ConfigError

__all__ = ["GridError"]


class GridError(ConfigError):
    """Bad input to the grid model; the message is one complete line for the user.

    A :class:`~adnmesh.errors.ConfigError`, so the command line reports it as a one-line error
    (exit code 2) even where a caller does not add the config file and key path itself.
    """
