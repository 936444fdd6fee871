"""DER agent: the local controller and dynamics of one DER, one process per DER.

    python -m adnmesh.agents.der CONFIG --der SGen1 --connect tcp/127.0.0.1:7447

Receives P_Y (and the weights W) from the CPFC, sets P_ref,d = P_Y w_d P_inst,d + P_sched,d, and
reports its infeed and heartbeats. Logic: adnmesh.control.der_controller.DERController.
"""

import argparse
import sys

from adnmesh.control.der_model import params_from_json
from adnmesh.control.registry import build_agent
from adnmesh.runtime.process import (AgentProcess, add_agent_arguments, load_config_or_exit,
                                     open_session)
from adnmesh.sim.node import Node
from adnmesh.names import der_agent_id


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="der", description="adnmesh DER agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    parser.add_argument("--der", required=True, metavar="ID", help="id of the DER in the config")
    parser.add_argument("--p-avail-w", type=float, metavar="W",
                        help="its available power, W (default: from the config's grid model)")
    parser.add_argument("--model-params", metavar="JSON",
                        help="its model's parameters (default: calibrated from the config; "
                        "adnmesh up calibrates them once and passes them)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    config = load_config_or_exit(args.config)
    if args.der not in config.der_ids():
        parser.error(f"unknown DER id {args.der!r} (known: {', '.join(config.der_ids())})")
    params = None
    if args.model_params is not None:
        try:
            params = params_from_json(args.model_params)
        except ValueError as exc:
            parser.error(f"--model-params: {exc}")
    agent = build_agent(der_agent_id(args.der), config, p_avail_w=args.p_avail_w,
                        der_params=params)
    node = Node.for_config(agent, config,
                          start_ns=args.resume_at_ns)
    with open_session(args, der_agent_id(args.der)) as session:
        return AgentProcess(session, node, config.grid,
                            publishers=args.certs is None).serve()


if __name__ == "__main__":
    sys.exit(main())
