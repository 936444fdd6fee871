"""The ``adnmesh`` command line.

Each subcommand lives in its own module under :mod:`adnmesh.commands` (see there for the
interface); :data:`COMMANDS` lists them. :func:`main` turns user errors
(:class:`~adnmesh.errors.ConfigError`, :class:`~adnmesh.errors.UsageError`) into one line on
stderr and exit code 2, and Ctrl-C into exit code 130. A file the system refuses to open,
create or read (an :class:`OSError` that names its file: permissions, a folder where a file
should be, a read-only place) is one line with exit code 2 as well: commands check their
outputs before any work (:func:`adnmesh.commands.output_path`), and this catches what changes
while they run. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from adnmesh import __version__, one_blas_thread
from adnmesh.errors import ConfigError, UsageError

__all__ = ["COMMANDS", "COMMAND_NAMES", "EXIT_INTERRUPTED", "EXIT_USER_ERROR", "build_parser",
           "main"]

COMMAND_NAMES = ("init", "check", "margins", "tune", "analyze", "identify", "up", "fault", "certs",
                 "agent", "router", "device", "replay", "plot", "inspect", "export", "schema",
                 "study", "cascade", "merge")
"""The commands, in the order ``adnmesh --help`` lists them: each is the module
``adnmesh.commands.<name>``, imported only when needed (a command that reads a recording does
not wait for the libraries of the analysis)."""


def _command(name: str) -> ModuleType:
    return importlib.import_module(f"adnmesh.commands.{name}")


def __getattr__(name: str):
    if name == "COMMANDS":   # the command modules, in COMMAND_NAMES order (imports them all)
        return tuple(_command(n) for n in COMMAND_NAMES)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


EXIT_USER_ERROR = 2
"""Exit code for an invalid config or command line (the same code argparse uses)."""

EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT)."""


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Return the argument parser with one subparser per module in :data:`COMMANDS` (with
    ``only``, a name in :data:`COMMAND_NAMES`: that command's alone)."""
    parser = argparse.ArgumentParser(
        prog="adnmesh",
        description="Adaptive cross-voltage-level power flow control of an active distribution "
        "network, run as a mesh of communicating processes.",
    )
    parser.add_argument("--version", action="version", version=f"adnmesh {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in (only,) if only in COMMAND_NAMES else COMMAND_NAMES:
        module = _command(name)
        module.add_parser(subparsers).set_defaults(run=module.run)
    return parser


def _error(message: str) -> int:
    one_line = " ".join(str(message).splitlines())
    print(f"adnmesh: error: {one_line}", file=sys.stderr)
    return EXIT_USER_ERROR


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); return the exit code.

    OpenBLAS is set to one thread first (:func:`adnmesh.one_blas_thread`), before any command
    module imports numpy; the processes a command starts (tuning workers, agents) inherit it.
    """
    one_blas_thread()
    try:
        try:
            argv = list(sys.argv[1:] if argv is None else argv)
            args = build_parser(argv[0] if argv else None).parse_args(argv)
        except SystemExit as exc:  # argparse after --help, --version or a usage error
            return exc.code if isinstance(exc.code, int) else EXIT_USER_ERROR * bool(exc.code)
        return args.run(args)
    except (ConfigError, UsageError) as exc:
        return _error(str(exc))
    except OSError as exc:
        if exc.filename is None:        # not about a file the user named: a bug, traced
            raise
        also = f" -> {exc.filename2}" if exc.filename2 else ""
        return _error(f"{exc.filename}{also}: {exc.strerror or exc}")
    except KeyboardInterrupt:
        print("adnmesh: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
