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
from adnmesh.sim.faults import FaultPlan, PlannedFault, fault_events, resend_body
from adnmesh.sim.node import Node
from adnmesh.sim.topology import Topology
from adnmesh.names import LAUNCHER
from adnmesh.wire.envelope import encode
from adnmesh.wire.outbox import Outbox
from adnmesh.wire.units import ns

__all__ = ["LocalRun", "NodesOnOneClock", "run_local"]


@dataclass
class LocalRun:
    """The result of :func:`run_local`.

    Attributes
    ----------
    messages : list of (str, bytes)
        Every published ``(key, payload)``, in the order the agents (and, for injected faults
        and their events, ``up``) sent them.
    nodes : dict
        Agent id -> its :class:`Node` (counts, and the agent state machine as ``node.agent``);
        for a restarted agent, its last node.
    coordinator : Coordinator
        The clock, with its grant and report counts.
    """

    messages: list[tuple[str, bytes]] = field(default_factory=list)
    nodes: dict[str, Node] = field(default_factory=dict)
    coordinator: Coordinator | None = None


class NodesOnOneClock:
    """What the in-process runners share (this one and a hierarchy's,
    :mod:`adnmesh.sim.hierarchy_run`): nodes driven a grant at a time by one coordinator,
    ``up``'s own messages, and delivery straight to the receivers of the topology.

    A subclass sets ``topology``, ``run`` (with ``nodes`` and ``messages``), ``coordinator``
    and ``outbox``, and gives ``start() -> grants`` and ``_killed(agent, at_ns) -> grants``.
    """

    def send_own(self, key: str, t_send: int, body: dict, t_deliver: int | None = None) -> None:
        """A message of ``up``: recorded, delivered to the key's receivers."""
        self.deliver(key, encode(self.outbox.send(key, t_send, body, t_deliver)))

    def deliver(self, key: str, payload: bytes) -> None:
        self.run.messages.append((key, payload))
        for receiver in self.topology.receivers.get(key, ()):
            self.run.nodes[receiver].receive(key, payload)

    def step(self, grant) -> list:
        node = self.run.nodes[grant.agent]
        node.take_cut(grant.cut_keys, grant.cuts)
        if node.counts.received < grant.expect:
            raise RuntimeError(f"{grant.agent}: expected {grant.expect} messages, "
                               f"received {node.counts.received}")
        for key, payload in node.advance(grant.until_ns):
            self.deliver(key, payload)
        report = node.report()
        grants = self.coordinator.on_report(report)
        if report.killed_ns is not None:
            grants += self._killed(grant.agent, report.killed_ns)
        return grants

    def drive(self, on_progress=None) -> None:
        """Run to the end: ``on_progress(t_ns)`` with the time every node has reached, every
        1,000 grants and at the end.

        Raises
        ------
        RuntimeError
            The clock stopped before the end.
        """
        grants = self.start()
        done = 0
        while grants:
            grants.extend(self.step(grants.popleft()))
            done += 1
            if on_progress is not None and done % 1000 == 0:
                on_progress(self.coordinator.now_ns())
        if not self.coordinator.finished:
            raise RuntimeError("the sim clock stopped before the end of the run")
        if on_progress is not None:
            on_progress(self.coordinator.end_ns)


class _LocalRunner(NodesOnOneClock):
    """What ``adnmesh up`` does, in one process: nodes, clock, faults, restarts."""

    def __init__(self, config: Config, schedule, end_ns: int, q_schedule=None,
                 model_watch=None) -> None:
        self.config, self.schedule, self.q_schedule = config, schedule, q_schedule
        self.model_watch = model_watch
        self.topology = Topology.from_config(config)
        self.run = LocalRun()
        self.plan = FaultPlan(config, self.topology.agents)
        self.coordinator = self.run.coordinator = Coordinator(self.topology, end_ns,
                                                              on_rejoin=self._rejoined)
        self.outbox = Outbox(LAUNCHER)
        for agent_id in self.topology.agents:
            self.run.nodes[agent_id] = self._node(agent_id, 0)

    def _node(self, agent_id: str, start_ns: int) -> Node:
        watch = (self.model_watch() if self.model_watch is not None and agent_id == "cpfc"
                 else None)
        return Node(build_agent(agent_id, self.config, self.schedule,
                                q_schedule=self.q_schedule, model_watch=watch), self.topology,
                    self.config.runtime.seed, start_ns=start_ns)

    def inject(self, planned: PlannedFault, t_send: int, body: dict | None = None) -> None:
        keys = self.topology.keys
        body = planned.body if body is None else body
        self.coordinator.inject(self.topology.agents)
        self.send_own(keys.of("fault"), t_send, body, max(body["start_ns"], t_send))

    def start(self) -> deque:
        keys = self.topology.keys
        for node in self.run.nodes.values():
            self.coordinator.on_report(node.report())
        self.plan.from_config(self.config)
        for planned in self.plan.faults:
            self.inject(planned, 0)
            self.send_own(keys.of("event", LAUNCHER), 0, fault_events(planned))
        for agent, at in self.plan.restarts():
            self.coordinator.plan_restart(agent, at)
        return deque(self.coordinator.start())

    def _killed(self, agent: str, at_ns: int) -> list:
        keys = self.topology.keys
        restart = [t for a, t in self.plan.restarts() if a == agent and t > at_ns]
        self.send_own(keys.of("event", LAUNCHER), at_ns, {
            "level": "WARNING", "kind": "killed", "subject": agent,
            "text": f"{agent} killed at {at_ns / 1e9:g} s (injected fault)"})
        if not restart:
            return []
        node = self.run.nodes[agent] = self._node(agent, min(restart))
        return self.coordinator.on_report(node.report())

    def _rejoined(self, agent: str, now: int) -> None:
        keys = self.topology.keys
        self.send_own(keys.of("event", LAUNCHER), now, {
            "level": "INFO", "kind": "rejoined", "subject": agent,
            "text": f"{agent} restarted and rejoined at {now / 1e9:g} s"})
        for planned in self.plan.faults:
            body = resend_body(planned, now)
            if body is not None:
                self.inject(planned, now, body)


def run_local(config: Config, schedule, *, end_s: float | None = None,
              q_schedule=None, model_watch=None) -> LocalRun:
    """Run the scenario of ``config`` (to ``end_s``, default its duration) in this process,
    with the config's faults (kills and restarts included), as ``adnmesh up`` would.

    Parameters
    ----------
    config : Config
    schedule : GainSchedule
        The CPFC's gains.
    q_schedule : GainSchedule, optional
        Its Q gains (reactive power control; default tuned on demand).
    end_s : float, optional
        Last instant, s.
    model_watch : callable, optional
        ``model_watch() -> ModelWatch`` for each (re)start of the CPFC
        (:class:`adnmesh.results.model_watch.ModelWatch`, ``runtime.model_watch``; default none).
    """
    runner = _LocalRunner(config, schedule,
                          ns(config.scenario.duration_s if end_s is None else end_s), q_schedule,
                          model_watch)
    runner.drive()
    return runner.run
