"""Measurement agent: P_IP at the interconnection point, sampled and sent to the CPFC.

    python -m adnmesh.agents.measurement CONFIG --connect tcp/127.0.0.1:7447

Logic: adnmesh.control.measurement_point.Measurement.
"""

import argparse
import sys

from adnmesh.control.registry import build_agent
from adnmesh.runtime.place import place_or_exit
from adnmesh.runtime.process import AgentProcess, add_agent_arguments, open_session


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="measurement", description="adnmesh measurement agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    place = place_or_exit(args)
    config = place.config
    node = place.node(place.agent("measurement", lambda: build_agent("measurement", config)),
                      args.resume_at_ns)
    with open_session(args, place.identity("measurement")) as session:
        return AgentProcess(session, node, config.grid,
                            publishers=args.certs is None).serve()


if __name__ == "__main__":
    sys.exit(main())
