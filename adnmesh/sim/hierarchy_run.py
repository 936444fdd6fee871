"""Run a hierarchy of ADNs in one process on the sim clock (docs/hierarchy.md).

The upper grid's agents (its CPFC on the upper table, its availability monitor, its measurement
of the sum of the ADNs' exchanges) and every ADN's agents (its CPFC, measurement, availability
monitor and DERs, on its own config and table) run as the nodes of one hierarchy topology
(:mod:`adnmesh.sim.hierarchy_topology`) under one coordinator, exactly as
:mod:`adnmesh.sim.local` runs one grid: the same agent state machines, the same nodes and ICT
links, the same clock. The upper grid's DER for ADN ``a`` is its site agent
(:class:`~adnmesh.control.adn_site.AdnSite`); each ADN's measurement also sends its exchange to
it. Faults of every level's config are injected as ``adnmesh up`` injects them (kills with
restarts included); a site cut off from the level above is the upper config's ``der_offline``
of its ADN.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from adnmesh.config import Config
from adnmesh.control.registry import build_agent
from adnmesh.control.operating_point import initial_p_ip_w
from adnmesh.names import LAUNCHER
from adnmesh.sim.clock import Coordinator
from adnmesh.sim.faults import FaultPlan, fault_events, resend_body
from adnmesh.sim.hierarchy_levels import hierarchy_agent
from adnmesh.sim.hierarchy_topology import grid_of, hierarchy_topology, qualified
from adnmesh.sim.local import NodesOnOneClock
from adnmesh.sim.node import Node
from adnmesh.wire.keys import Keys
from adnmesh.wire.outbox import Outbox
from adnmesh.wire.units import ns

__all__ = ["HierarchyRun", "Level", "run_hierarchy"]


@dataclass(frozen=True)
class Level:
    """One grid of the hierarchy: its config and its CPFC's gain schedule
    (:class:`~adnmesh.control.cpfc_controller.GainSchedule`); the upper level's CPFC also
    applies the rule for the ADNs' own gain switches
    (:class:`~adnmesh.cascade.switches.LowerSwitchRule`, optional)."""

    config: Config
    schedule: object
    lower_switch_rule: object = None


@dataclass
class HierarchyRun:
    """The result of :func:`run_hierarchy`.

    Attributes
    ----------
    messages : list of (str, bytes)
        Every published ``(key, payload)`` of every grid, in the order they were sent.
    nodes : dict
        ``<grid>:<agent id>`` -> its :class:`~adnmesh.sim.node.Node` (the last one of a
        restarted agent).
    coordinator : Coordinator
        The clock.
    """

    messages: list[tuple[str, bytes]] = field(default_factory=list)
    nodes: dict[str, Node] = field(default_factory=dict)
    coordinator: Coordinator | None = None
    _by_key: dict[str, list[bytes]] | None = field(default=None, repr=False)

    def _index(self) -> dict[str, list[bytes]]:
        """Key -> its payloads in send order, built at the first call (once the run is
        over)."""
        if self._by_key is None:
            self._by_key = {}
            for k, payload in self.messages:
                self._by_key.setdefault(k, []).append(payload)
        return self._by_key

    def payloads(self, key: str) -> list[bytes]:
        """Every payload sent on ``key``, in send order."""
        return self._index().get(key, [])

    @property
    def keys(self) -> list[str]:
        """Every key a message was sent on, in order of the first."""
        return list(self._index())


class _HierarchyRunner(NodesOnOneClock):
    """What ``adnmesh up`` does for one grid, for every grid of a hierarchy."""

    def __init__(self, upper: Level, adns: Mapping[str, Level],
                 offset_delay_s: Mapping[str, float], end_ns: int) -> None:
        self.upper, self.adns = upper, dict(adns)
        self.levels = {upper.config.grid: upper,
                       **{level.config.grid: level for level in adns.values()}}
        self.topology = hierarchy_topology(upper.config, {a: lv.config for a, lv in adns.items()},
                                           offset_delay_s)
        self.run = HierarchyRun()
        self.coordinator = self.run.coordinator = Coordinator(self.topology, end_ns,
                                                              on_rejoin=self._rejoined)
        self.outbox = Outbox(LAUNCHER)
        self.p_ip0_w = {adn: initial_p_ip_w(level.config) for adn, level in self.adns.items()}
        self.plans = {grid: FaultPlan(lv.config, tuple(grid_of(a)[1] for a in self._agents(grid)))
                      for grid, lv in self.levels.items()}
        for name in self.topology.agents:
            self.run.nodes[name] = self._node(name, 0)

    def _agents(self, grid: str) -> list[str]:
        return [a for a in self.topology.agents if grid_of(a)[0] == grid]

    def _agent(self, name: str):
        grid, agent_id = grid_of(name)
        level = self.levels[grid]
        return hierarchy_agent(agent_id, level.config, self.upper.config, self.p_ip0_w,
                               lambda: build_agent(agent_id, level.config, level.schedule),
                               self.upper.lower_switch_rule)

    def _node(self, name: str, start_ns: int) -> Node:
        seed = self.levels[grid_of(name)[0]].config.runtime.seed
        return Node(self._agent(name), self.topology, seed, start_ns=start_ns, node_id=name)

    def inject(self, grid: str, planned, t_send: int, body: dict | None = None) -> None:
        body = planned.body if body is None else body
        self.coordinator.inject(self._agents(grid))
        self.send_own(Keys(grid).of("fault"), t_send, body, max(body["start_ns"], t_send))

    def start(self) -> deque:
        for node in self.run.nodes.values():
            self.coordinator.on_report(node.report())
        for grid, plan in self.plans.items():
            plan.from_config(self.levels[grid].config)
            for planned in plan.faults:
                self.inject(grid, planned, 0)
                self.send_own(Keys(grid).of("event", LAUNCHER), 0, fault_events(planned))
            for agent, at in plan.restarts():
                self.coordinator.plan_restart(qualified(grid, agent), at)
        return deque(self.coordinator.start())

    def _killed(self, name: str, at_ns: int) -> list:
        grid, agent = grid_of(name)
        restart = [t for a, t in self.plans[grid].restarts() if a == agent and t > at_ns]
        self.send_own(Keys(grid).of("event", LAUNCHER), at_ns, {
            "level": "WARNING", "kind": "killed", "subject": agent,
            "text": f"{agent} of {grid} killed at {at_ns / 1e9:g} s (injected fault)"})
        if not restart:
            return []
        node = self.run.nodes[name] = self._node(name, min(restart))
        return self.coordinator.on_report(node.report())

    def _rejoined(self, name: str, now: int) -> None:
        grid, agent = grid_of(name)
        self.send_own(Keys(grid).of("event", LAUNCHER), now, {
            "level": "INFO", "kind": "rejoined", "subject": agent,
            "text": f"{agent} of {grid} restarted and rejoined at {now / 1e9:g} s"})
        for planned in self.plans[grid].faults:
            body = resend_body(planned, now)
            if body is not None:
                self.inject(grid, planned, now, body)


def run_hierarchy(upper: Level, adns: Mapping[str, Level], offset_delay_s: Mapping[str, float],
                  *, end_s: float | None = None, on_progress=None) -> HierarchyRun:
    """Run the hierarchy (to ``end_s``, default the upper config's duration) in this process.

    Parameters
    ----------
    upper : Level
        The upper grid: the config ``adnmesh cascade`` wrote and its table's schedule.
    adns : mapping
        ADN id (a DER of the upper config) -> its level.
    offset_delay_s : mapping
        ADN id -> delay of its offset link, s (its inter-site delay less the upper config's
        ``t_com_s``).
    on_progress : callable, optional
        ``on_progress(t_ns)`` with the sim time every level has reached, every 1,000 grants
        and at the end.

    Raises
    ------
    ValueError
        Levels that do not make a hierarchy (:func:`~adnmesh.sim.hierarchy_topology.
        hierarchy_topology`).
    RuntimeError
        The clock stopped before the end.
    """
    duration = upper.config.scenario.duration_s if end_s is None else end_s
    runner = _HierarchyRunner(upper, adns, offset_delay_s, ns(duration))
    runner.drive(on_progress)
    return runner.run
