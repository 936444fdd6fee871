"""``adnmesh agent KIND [--id ID] CONFIG --connect ENDPOINT [--certs DIR]``: one agent.

Runs the agent program of KIND (:mod:`adnmesh.agents`, the same program ``adnmesh up`` starts)
in this process against a router elsewhere: ``adnmesh up CONFIG --external ...`` on the control
centre's host, or a site router (``adnmesh router``). It keeps trying to reach the router for
``--connect-timeout`` seconds, waits for the run's start, runs until the run stops and exits.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from adnmesh.errors import UsageError
from adnmesh.names import AGENT_KINDS

__all__ = ["KINDS", "add_parser", "run"]

KINDS = AGENT_KINDS
"""The agent kinds (one program each in :mod:`adnmesh.agents`)."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``agent`` subparser."""
    parser = subparsers.add_parser(
        "agent", help="run one agent against a router elsewhere (multi-host)",
        description="Run one agent of CONFIG against a remote router: 'adnmesh up CONFIG "
        "--external KIND[:ID]' on the control centre's host, or a site router. With --certs "
        "the agent uses its own certificate from DIR and a tls/ endpoint. Exit code 0 when "
        "the run ended, 1 when the router could not be reached, 2 for a user error.")
    parser.add_argument("kind", choices=KINDS, metavar="KIND", help=", ".join(KINDS))
    parser.add_argument("config", metavar="CONFIG", help="configuration file (YAML)")
    parser.add_argument("--id", dest="der_id", metavar="ID", help="der: the DER's id")
    parser.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", required=True,
                        help="the router (tcp/HOST:PORT; tls/HOST:PORT with --certs)")
    parser.add_argument("--certs", metavar="DIR", help="secure profile: certificate directory")
    parser.add_argument("--table", metavar="PATH", help="cpfc: gain-scheduling table")
    parser.add_argument("--q-table", metavar="PATH",
                        help="cpfc with reactive power control: the Q table")
    parser.add_argument("--connect-timeout", type=float, default=60.0, metavar="S",
                        help="keep trying to reach the router for S seconds (default 60)")
    parser.add_argument("--resume-at-ns", type=int, metavar="NS",
                        help="begin at this sim time (a restart, as 'adnmesh up' says)")
    return parser


def _argv(args: argparse.Namespace) -> list[str]:
    if args.kind == "der" and args.der_id is None:
        raise UsageError("der needs --id ID (the DER's id in CONFIG)")
    if args.kind != "der" and args.der_id is not None:
        raise UsageError(f"{args.kind} takes no --id")
    for flag, value in (("--table", args.table), ("--q-table", args.q_table)):
        if value and args.kind != "cpfc":
            raise UsageError(f"{flag} is for cpfc only")
    if not 0 <= args.connect_timeout <= 86400:
        raise UsageError(f"--connect-timeout must be in [0, 86400] s, got "
                         f"{args.connect_timeout:g}")
    if args.resume_at_ns is not None and not 0 <= args.resume_at_ns < 2**63:
        raise UsageError(f"--resume-at-ns must be in [0, 2**63) ns, got {args.resume_at_ns}")
    argv = [args.config]
    for endpoint in args.connect:
        argv += ["--connect", endpoint]
    options = {"--der": args.der_id, "--table": args.table, "--q-table": args.q_table,
               "--certs": args.certs,
               "--resume-at-ns": args.resume_at_ns, "--connect-timeout": args.connect_timeout}
    for flag, value in options.items():
        if value is not None:
            argv += [flag, str(value)]
    return argv


def run(args: argparse.Namespace) -> int:
    """Run the agent program; return its exit code."""
    argv = _argv(args)
    program = importlib.import_module(f"adnmesh.agents.{args.kind}")
    try:
        return program.main(argv)
    except SystemExit as exc:        # the program's own one-line errors (exit code 1 or 2)
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(exc.code, file=sys.stderr)  # sys.exit("message"), as Python itself would
        return 1
