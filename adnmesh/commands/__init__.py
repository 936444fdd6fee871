"""Subcommands of the ``adnmesh`` command line, one module each.

A command module exposes

``add_parser(subparsers) -> argparse.ArgumentParser``
    Add its subparser (``subparsers.add_parser(NAME, help=...)``) with its arguments and return it.
``run(args: argparse.Namespace) -> int``
    Do the work and return the exit code (0 success). Raise
    :class:`~adnmesh.errors.ConfigError` or :class:`~adnmesh.errors.UsageError` for user errors;
    :func:`adnmesh.cli.main` prints them as one line and exits with code 2.

To add a command, write ``adnmesh/commands/<name>.py`` and list it in ``adnmesh.cli.COMMAND_NAMES``.
"""

import argparse

__all__ = ["add_config_argument"]


def add_config_argument(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``CONFIG`` argument (path of a YAML config file) to ``parser``."""
    parser.add_argument(
        "config", metavar="CONFIG", help="configuration file (YAML), e.g. configs/simbench.yaml"
    )
