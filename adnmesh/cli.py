"""The ``adnmesh`` command line.

Each subcommand lives in its own module under :mod:`adnmesh.commands` (see there for the
interface); :data:`COMMANDS` lists them. :func:`main` turns user errors
(:class:`~adnmesh.errors.ConfigError`, :class:`~adnmesh.errors.UsageError`) into one line on
stderr and exit code 2, and Ctrl-C into exit code 130; anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from adnmesh import __version__
from adnmesh.commands import (agent, analyze, certs, check, fault, inspect, margins, plot, replay,
                              router, schema, tune, up)
from adnmesh.errors import ConfigError, UsageError

__all__ = ["COMMANDS", "EXIT_INTERRUPTED", "EXIT_USER_ERROR", "build_parser", "main"]

COMMANDS = (check, margins, tune, analyze, up, fault, certs, agent, router, replay, plot, inspect,
            schema)
"""Command modules, in the order ``adnmesh --help`` lists them."""

EXIT_USER_ERROR = 2
"""Exit code for an invalid config or command line (the same code argparse uses)."""

EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT)."""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser with one subparser per module in :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="adnmesh",
        description="Adaptive cross-voltage-level power flow control of an active distribution "
        "network, run as a mesh of communicating processes.",
    )
    parser.add_argument("--version", action="version", version=f"adnmesh {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in COMMANDS:
        module.add_parser(subparsers).set_defaults(run=module.run)
    return parser


def _error(message: str) -> int:
    one_line = " ".join(str(message).splitlines())
    print(f"adnmesh: error: {one_line}", file=sys.stderr)
    return EXIT_USER_ERROR


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as exc:  # argparse after --help, --version or a usage error
            return exc.code if isinstance(exc.code, int) else EXIT_USER_ERROR * bool(exc.code)
        return args.run(args)
    except (ConfigError, UsageError) as exc:
        return _error(str(exc))
    except KeyboardInterrupt:
        print("adnmesh: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
