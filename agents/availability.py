"""Availability monitor agent: DER heartbeats and availability flags in, SI out.

    python agents/availability.py CONFIG --connect tcp/127.0.0.1:7447

A DER is available while its last heartbeat said so and is younger than
runtime.heartbeat_timeout_s; SI goes to the CPFC when it changes.
Logic: adnmesh.control.availability.AvailabilityMonitor.
"""

import argparse
import sys

import zenoh

from adnmesh.control.availability import AvailabilityMonitor
from adnmesh.runtime.bus import add_connection_arguments, session_config
from adnmesh.runtime.node import Node
from adnmesh.runtime.process import load_config_or_exit, serve

# --- arguments ------------------------------------------------------------------------------
parser = argparse.ArgumentParser(prog="availability", description="adnmesh availability monitor")
parser.add_argument("config", metavar="CONFIG", help="adnmesh config file (YAML)")
add_connection_arguments(parser)
args = parser.parse_args()

config = load_config_or_exit(args.config)
node = Node.for_config(AvailabilityMonitor(config), config)

# --- run ------------------------------------------------------------------------------------
with zenoh.open(session_config(args)) as session:
    code = serve(session, node, config.grid)
sys.exit(code)
