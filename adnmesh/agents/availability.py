"""Availability monitor agent: DER heartbeats and availability flags in, SI out.

    python -m adnmesh.agents.availability CONFIG --connect tcp/127.0.0.1:7447

Logic: adnmesh.control.availability_monitor.AvailabilityMonitor.
"""

import argparse
import sys

from adnmesh.control.registry import build_agent
from adnmesh.runtime.process import (AgentProcess, add_agent_arguments, load_config_or_exit,
                                     open_session)
from adnmesh.sim.node import Node


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="availability", description="adnmesh availability agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    config = load_config_or_exit(args.config)
    node = Node.for_config(build_agent("availability", config), config,
                          start_ns=args.resume_at_ns)
    with open_session(args, "availability") as session:
        return AgentProcess(session, node, config.grid,
                            publishers=args.certs is None).serve()


if __name__ == "__main__":
    sys.exit(main())
