"""DER agent: the local controller and dynamics of one DER, one process per DER.

    python agents/der.py CONFIG --der SGen1 --connect tcp/127.0.0.1:7447

Receives P_Y (and the weights W) from the CPFC, sets P_ref,d = P_Y w_d P_inst,d + P_sched,d, and
reports its infeed and heartbeats. Logic: adnmesh.control.der.DERController.
"""

import argparse
import sys

import zenoh

from adnmesh.control.der import DERController
from adnmesh.runtime.bus import add_connection_arguments, session_config
from adnmesh.runtime.node import Node
from adnmesh.runtime.process import load_config_or_exit, serve

# --- arguments ------------------------------------------------------------------------------
parser = argparse.ArgumentParser(prog="der", description="adnmesh DER agent")
parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
parser.add_argument("--der", required=True, metavar="ID", help="id of the DER in the config")
add_connection_arguments(parser)
args = parser.parse_args()

config = load_config_or_exit(args.config)
if args.der not in config.der_ids():
    parser.error(f"unknown DER id {args.der!r} (known: {', '.join(config.der_ids())})")
(der,) = config.ders_by_id([args.der])
node = Node.for_config(DERController(der, config), config)

# --- run ------------------------------------------------------------------------------------
with zenoh.open(session_config(args)) as session:
    code = serve(session, node, config.grid)
sys.exit(code)
