"""Measurement agent: P_IP at the interconnection point, sampled and sent to the CPFC.

    python agents/measurement.py CONFIG --connect tcp/127.0.0.1:7447

P_IP = sum of the DER infeeds + runtime.rest_of_grid_w, every runtime.measurement_period_s,
delivered after T_meas. Logic: adnmesh.control.measurement.Measurement.
"""

import argparse
import sys

import zenoh

from adnmesh.control.measurement import Measurement
from adnmesh.runtime.bus import add_connection_arguments, session_config
from adnmesh.runtime.node import Node
from adnmesh.runtime.process import load_config_or_exit, serve

# --- arguments ------------------------------------------------------------------------------
parser = argparse.ArgumentParser(prog="measurement", description="adnmesh measurement agent")
parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
add_connection_arguments(parser)
args = parser.parse_args()

config = load_config_or_exit(args.config)
node = Node.for_config(Measurement(config), config)

# --- run ------------------------------------------------------------------------------------
with zenoh.open(session_config(args)) as session:
    code = serve(session, node, config.grid)
sys.exit(code)
