"""Availability monitor agent: DER heartbeats and availability flags in, SI out.

    python -m adnmesh.agents.availability CONFIG --connect tcp/127.0.0.1:7447

Logic: adnmesh.control.availability_monitor.AvailabilityMonitor.
"""

import argparse
import sys

from adnmesh.control.registry import build_agent
from adnmesh.runtime.place import place_or_exit
from adnmesh.runtime.process import AgentProcess, add_agent_arguments, open_session


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="availability", description="adnmesh availability agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    place = place_or_exit(args)
    config = place.config
    node = place.node(place.agent("availability", lambda: build_agent("availability", config)),
                      args.resume_at_ns)
    with open_session(args, place.identity("availability")) as session:
        return AgentProcess(session, node, config.grid,
                            publishers=args.certs is None).serve()


if __name__ == "__main__":
    sys.exit(main())
