"""CPFC agent: gain-scheduled PI control of the power at the interconnection point.

    python -m adnmesh.agents.cpfc CONFIG [--table PATH] --connect tcp/127.0.0.1:7447

PI on P_err = P_ref - P_meas; bumpless gain switch when SI changes; sends P_Y (and the weights W
on a switch) to the DERs. Gains: the table matching CONFIG (default
tables/<name>.<design hash[:12]>.json next to the config), tuning missing subsets on demand.
Logic: adnmesh.control.cpfc_controller.CPFC.
"""

import argparse
import sys
from pathlib import Path

from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.control.registry import build_agent
from adnmesh.errors import ConfigError
from adnmesh.reactive import reactive_view
from adnmesh.runtime.place import place_or_exit
from adnmesh.runtime.process import AgentProcess, add_agent_arguments, open_session
from adnmesh.tuning.table import default_table_path, load_table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cpfc", description="adnmesh CPFC agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    parser.add_argument("--table", metavar="PATH",
                        help="gain-scheduling table (default: the one matching CONFIG)")
    parser.add_argument("--q-table", metavar="PATH",
                        help="reactive power control: the Q table (default: the one matching "
                        "CONFIG's reactive view; none: tuned on demand)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    place = place_or_exit(args)
    config = place.config
    q_schedule = None
    try:
        schedule = place.schedule(lambda: GainSchedule(config, load_table(
            args.table or default_table_path(config), config)))
        if config.reactive is not None:
            view = reactive_view(config)
            q_path = Path(args.q_table) if args.q_table else default_table_path(view)
            q_table = load_table(q_path, view) if args.q_table or q_path.exists() else None
            q_schedule = GainSchedule(view, q_table)
    except ConfigError as exc:
        print(f"adnmesh agent: error: {exc}", file=sys.stderr)
        return 2
    watch = None
    if config.runtime.model_watch != "off":
        from adnmesh.results.model_watch import ModelWatch   # step figures: numba
        watch = ModelWatch(config, keep_setpoints=config.runtime.model_watch == "retune")
    node = place.node(place.agent("cpfc", lambda: build_agent(
        "cpfc", config, schedule, q_schedule=q_schedule, model_watch=watch)), args.resume_at_ns)
    with open_session(args, place.identity("cpfc")) as session:
        return AgentProcess(session, node, config.grid,
                            publishers=args.certs is None).serve()


if __name__ == "__main__":
    sys.exit(main())
