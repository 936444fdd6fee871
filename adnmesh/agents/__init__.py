"""The agent programs: one small program per process kind, ``python -m adnmesh.agents.<kind>``.

``cpfc``, ``der`` (one process per DER), ``measurement`` and ``availability``. Each reads top
to bottom (parse arguments, open the Zenoh session, run, close) and imports all of its logic
from the library, where every agent is a plain state machine (:mod:`adnmesh.control`) that tests
drive without Zenoh. ``adnmesh up`` starts them; ``adnmesh agent KIND [--id ID] CONFIG
--connect ENDPOINT [--certs DIR]`` runs one of them against a router on another host.
"""
