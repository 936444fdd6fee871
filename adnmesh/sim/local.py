"""Run every agent of a config in one process, with the same nodes and the same sim clock.

The in-process runner drives exactly what the distributed runtime drives — one
:class:`~adnmesh.sim.node.Node` per agent, granted time by the same
:class:`~adnmesh.sim.clock.Coordinator` — but hands payloads from sender to receivers
directly instead of over Zenoh. Because a sim run is deterministic, it produces the same messages,
byte for byte, as ``adnmesh up`` with the same config and seed; tests use it as the reference of
the distributed runtime, and analyses can use it to run scenarios without processes.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from adnmesh.config import Config
from adnmesh.control.registry import build_agent
from adnmesh.sim.clock import Coordinator
from adnmesh.sim.node import Node
from adnmesh.sim.topology import Topology
from adnmesh.wire.units import ns

__all__ = ["LocalRun", "run_local"]


@dataclass
class LocalRun:
    """The result of :func:`run_local`.

    Attributes
    ----------
    messages : list of (str, bytes)
        Every published ``(key, payload)``, in the order the agents sent them.
    nodes : dict
        Agent id -> its :class:`Node` (counts, and the agent state machine as ``node.agent``).
    coordinator : Coordinator
        The clock, with its grant and report counts.
    """

    messages: list[tuple[str, bytes]] = field(default_factory=list)
    nodes: dict[str, Node] = field(default_factory=dict)
    coordinator: Coordinator | None = None


def run_local(config: Config, schedule, *, end_s: float | None = None) -> LocalRun:
    """Run the scenario of ``config`` (to ``end_s``, default its duration) in this process.

    Parameters
    ----------
    config : Config
    schedule : GainSchedule
        The CPFC's gains.
    end_s : float, optional
        Last instant, s.
    """
    topology = Topology.from_config(config)
    end_ns = ns(config.scenario.duration_s if end_s is None else end_s)
    run = LocalRun()
    for agent_id in topology.agents:
        run.nodes[agent_id] = Node(build_agent(agent_id, config, schedule), topology,
                                   config.runtime.seed)
    coordinator = run.coordinator = Coordinator(topology, end_ns)
    for node in run.nodes.values():
        coordinator.on_report(node.report())
    grants = deque(coordinator.start())
    while grants:
        grant = grants.popleft()
        node = run.nodes[grant.agent]
        if node.counts.received < grant.expect:
            raise RuntimeError(f"{grant.agent}: expected {grant.expect} messages, "
                               f"received {node.counts.received}")
        for key, payload in node.advance(grant.until_ns):
            run.messages.append((key, payload))
            for receiver in topology.receivers.get(key, ()):
                run.nodes[receiver].receive(key, payload)
        grants.extend(coordinator.on_report(node.report()))
    if not coordinator.finished:
        raise RuntimeError("the sim clock stopped before the end of the run")
    return run
