"""``adnmesh up CONFIG``: start the distributed runtime (not implemented yet, issue 5)."""

import argparse
import sys

from adnmesh.commands import add_config_argument
from adnmesh.config import load_config

__all__ = ["EXIT_NOT_IMPLEMENTED", "add_parser", "run"]

EXIT_NOT_IMPLEMENTED = 3
"""Exit code of ``up`` while the runtime does not exist."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``up`` subparser."""
    parser = subparsers.add_parser(
        "up",
        help="start the CPFC, DER, measurement and availability agents (not implemented yet)",
        description="Start every agent of CONFIG as its own process around an embedded Zenoh "
        "router and record the run. Not implemented yet (issue 5): for now only CONFIG is "
        "validated, and the exit code is 3.",
    )
    add_config_argument(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    """Validate the config, then report that the runtime does not exist yet (exit code 3)."""
    load_config(args.config)
    print("adnmesh up: the distributed runtime is not implemented yet (issue 5)", file=sys.stderr)
    return EXIT_NOT_IMPLEMENTED
