"""The distributed runtime behind ``adnmesh up``: the only package that talks to Zenoh.

- :mod:`~adnmesh.runtime.bus`: Zenoh session configuration and the shared connection flags;
- :mod:`~adnmesh.runtime.process`: an agent process (:class:`AgentProcess`: startup, run,
  goodbye) around a :class:`~adnmesh.sim.node.Node`; what ``agents/*.py`` run;
- :mod:`~adnmesh.runtime.children`: starting the agent processes and tracking them by PID;
- :mod:`~adnmesh.runtime.roster`: who is alive, ready, said goodbye, gone;
- :mod:`~adnmesh.runtime.tap`: the recorder tap (validate, then record; rejects apart);
- :mod:`~adnmesh.runtime.launcher_bus`: ``up``'s own messages and the sim clock's grants;
- :mod:`~adnmesh.runtime.launcher`: ``adnmesh up`` as phases: startup, run, shutdown, verify;
- :mod:`~adnmesh.results.summary`: the end-of-run figures, from the recorded series;
- the secure profile: :mod:`~adnmesh.runtime.identity` (who is who, where the certificates
  are), :mod:`~adnmesh.runtime.certificates` (making them), :mod:`~adnmesh.runtime.acl` (the access
  control, from the topology), :mod:`~adnmesh.runtime.security` (mutual TLS and access control
  in a Zenoh config), :mod:`~adnmesh.runtime.sessions` (the router's links per identity).

Below it: :mod:`adnmesh.sim` (node, links, topology, sim clock, in-process runner; bus-free),
:mod:`adnmesh.control` (the agents' state machines), :mod:`adnmesh.wire` (the protocol).
"""
