"""DER agent: the local controller and dynamics of one DER, one process per DER.

    python -m adnmesh.agents.der CONFIG --der SGen1 --connect tcp/127.0.0.1:7447

Receives P_Y (and the weights W) from the CPFC, sets P_ref,d = P_Y w_d P_inst,d + P_sched,d, and
reports its infeed and heartbeats. Logic: adnmesh.control.der_controller.DERController. A DER
whose plant is a device (the config's ``plant:``) is that device's gateway
(:mod:`adnmesh.devices.gateway`): it writes the set-points and reads the infeed over the
device's protocol.

With ``--der`` given several times the process hosts that many DER agents on one Zenoh session
(``runtime.ders_per_process``, scale mode: :mod:`adnmesh.runtime.host`); ``--p-avail-w`` and
``--model-params``, if given, then come once per ``--der``, in the same order.
"""

import argparse
import sys

from adnmesh.control.der_model import params_from_json
from adnmesh.control.registry import build_agent
from adnmesh.runtime.host import serve_hosted
from adnmesh.runtime.place import place_or_exit
from adnmesh.runtime.process import AgentProcess, add_agent_arguments, open_session
from adnmesh.sim.topology import Topology
from adnmesh.names import der_agent_id


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="der", description="adnmesh DER agent")
    parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
    parser.add_argument("--der", required=True, action="append", metavar="ID",
                        help="id of the DER in the config (again for each DER this process "
                        "hosts)")
    parser.add_argument("--p-avail-w", type=float, action="append", metavar="W",
                        help="its available power, W (default: from the config's grid model)")
    parser.add_argument("--model-params", action="append", metavar="JSON",
                        help="its model's parameters (default: calibrated from the config; "
                        "adnmesh up calibrates them once and passes them)")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)

    place = place_or_exit(args)
    config = place.config
    ders = args.der
    for name in ("p_avail_w", "model_params"):
        given = getattr(args, name)
        if given is not None and len(given) != len(ders):
            parser.error(f"--{name.replace('_', '-')} must be given once per --der "
                         f"({len(ders)}), got {len(given)}")
    if len(set(ders)) != len(ders):
        parser.error("a DER is named twice in --der")
    if len(ders) > 1 and args.certs is not None:
        parser.error("several --der need the open profile: a certificate is one DER's "
                     "identity")
    nodes, gateways = [], []
    topology = place.topology() or Topology.from_config(config)   # one for the process's DERs
    for i, der in enumerate(ders):
        if der not in config.der_ids():
            parser.error(f"unknown DER id {der!r} (known: {', '.join(config.der_ids())})")
        device = _gateway(config, der)
        if device is not None:
            gateways.append(device)
        params = None
        if args.model_params is not None:
            try:
                params = params_from_json(args.model_params[i])
            except ValueError as exc:
                parser.error(f"--model-params of {der}: {exc}")
        p_avail_w = None if args.p_avail_w is None else args.p_avail_w[i]
        agent = place.agent(der_agent_id(der), lambda: build_agent(
            der_agent_id(der), config, p_avail_w=p_avail_w, der_params=params, device=device))
        nodes.append(place.node(agent, args.resume_at_ns, topology))
    try:
        with open_session(args, place.identity(der_agent_id(ders[0]))) as session:
            if len(nodes) > 1:
                return serve_hosted(session, nodes, config.grid)
            return AgentProcess(session, nodes[0], config.grid,
                                publishers=args.certs is None).serve()
    finally:
        for gateway in gateways:
            gateway.stop()


def _gateway(config, der_id: str):
    """The started gateway to the DER's plant device, or None if its plant is simulated; a
    device that cannot be described (its TLS files, its points) is a one-line error."""
    (der,) = config.ders_by_id([der_id])
    if der.plant is None:
        return None
    from adnmesh.devices.connect import gateway_for
    from adnmesh.errors import ConfigError
    try:
        gateway = gateway_for(der, config)
    except ConfigError as exc:
        print(f"adnmesh agent: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    gateway.start(first_within_s=3 * der.plant.timeout_s)
    return gateway


if __name__ == "__main__":
    sys.exit(main())
