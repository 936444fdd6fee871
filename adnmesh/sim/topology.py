"""Who talks to whom: the agents of a config, the keys they publish, and the links in between.

The topology is static: it follows from the config and the protocol table
(:mod:`adnmesh.wire.protocol`), so every process computes it for itself. Agents use it to know
what to subscribe to and which link a key goes over; the coordinator uses it to know who
receives a message (for counting messages in flight) and how far ahead every agent may run (the
lookahead: the shortest sum of link delays from one agent to another); the secure profile
derives every identity's rights from its :attr:`~Topology.routes`.

A row's ``link`` names the link its messages take; the ICT links' delays, jitter, loss and
outages come from the config's ``runtime.links`` (the CPFC -> DER delay defaults to ``t_com_s``,
the measurement -> CPFC delay to ``t_meas_s``); ``physical`` and ``local`` have none.
:data:`adnmesh.names.ICT_LINKS` are the links an injected fault can disturb.

Every cycle passes CPFC → DERs, whose delay ``t_com_s`` is positive, so the lookahead around
every cycle is positive and the conservative clock always makes progress.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

from adnmesh.config import Config, LinkSettings
from adnmesh.names import (ICT_LINKS, LAUNCHER, OPERATOR, PER_DER_KIND, agent_ids, der_agent_id,
                           der_id_of)
from adnmesh.sim.links import LinkParams
from adnmesh.wire.keys import Keys
from adnmesh.wire.protocol import EVERY_AGENT, PROTOCOL, MessageKind

__all__ = ["INF_NS", "Route", "Topology"]

INF_NS = math.inf
"""'Never' on the nanosecond time axis."""


class Route(NamedTuple):
    """One key of a run: its kind, its one sender and the agents that receive it."""

    kind: MessageKind
    sender: str
    key: str
    receivers: tuple[str, ...]


@dataclass(frozen=True)
class Topology:
    """The static message graph of a config.

    Attributes
    ----------
    keys : Keys
        Bus keys of the grid.
    agents : tuple of str
        Agent ids: ``cpfc``, ``measurement``, ``availability``, then ``der/<id>`` in config order.
    routes : tuple of Route
        Every key any party of the run sends (``up`` and ``operator`` included), in the order
        of the protocol table.
    links : dict
        ``(sender, key) -> LinkParams`` for every key an agent publishes through its node.
    receivers : dict
        ``key -> tuple of agent ids`` that receive it through their nodes (empty for records
        nobody consumes).
    subscriptions : dict
        ``agent -> tuple of keys`` it receives through its node.
    capacity_w : dict
        DER id -> its installed power P_inst, W (what its messages may say it feeds in).
    lookahead_ns : dict
        ``(a, b) -> ns``: least total link delay of any message chain from ``a`` to ``b``
        (``(a, a)``: around the shortest cycle through ``a``); missing if ``b`` is unreachable.
    """

    keys: Keys
    agents: tuple[str, ...]
    routes: tuple[Route, ...] = field(repr=False)
    links: dict = field(repr=False)
    receivers: dict = field(repr=False)
    subscriptions: dict = field(repr=False)
    capacity_w: dict = field(repr=False)
    lookahead_ns: dict = field(repr=False)

    @property
    def der_ids(self) -> frozenset[str]:
        """The DER ids of the run."""
        return frozenset(d for a in self.agents if (d := der_id_of(a)) is not None)

    @classmethod
    def from_config(cls, config: Config) -> Topology:
        keys = Keys(config.grid)
        der_ids = [d.id for d in config.ders]
        agents = agent_ids(der_ids)
        params = _link_params(config)
        routes = tuple(_routes(keys, agents, der_ids))
        links: dict[tuple[str, str], LinkParams] = {}
        receivers: dict[str, tuple[str, ...]] = {}
        for r in routes:
            if r.kind.clock:
                continue                       # spoken by the agent process, not its node
            if r.kind.link is not None and r.sender in agents:
                links[(r.sender, r.key)] = params[r.kind.link]
                receivers[r.key] = r.receivers
            elif r.receivers:                  # up's own to agents (faults)
                receivers[r.key] = r.receivers
        subscriptions = {a: tuple(k for k, to in receivers.items() if a in to) for a in agents}
        return cls(keys, agents, routes, links, receivers, subscriptions,
                   {d.id: d.p_inst_w for d in config.ders}, _lookahead(agents, links, receivers))

    def link(self, sender: str, key: str) -> LinkParams:
        """The link that carries ``key`` from ``sender``.

        Raises
        ------
        KeyError
            If ``sender`` does not publish ``key``.
        """
        return self.links[(sender, key)]

    def inbound_link(self, key: str) -> str | None:
        """Name of the link that brings ``key`` (None for ``up``'s own messages)."""
        for (_, k), link in self.links.items():
            if k == key:
                return link.name
        return None

    def publishes(self, agent: str) -> tuple[str, ...]:
        """Keys ``agent`` publishes through its node."""
        return tuple(k for (a, k) in self.links if a == agent)

    def sends(self, party: str) -> tuple[str, ...]:
        """Every key ``party`` (an agent, ``up`` or ``operator``) sends, clock protocol
        included."""
        return tuple(r.key for r in self.routes if r.sender == party)

    def gets(self, agent: str) -> tuple[str, ...]:
        """Every key ``agent`` receives, clock protocol included."""
        return tuple(r.key for r in self.routes if agent in r.receivers)


def _link_params(config: Config) -> dict[str, LinkParams]:
    """Every link's parameters, by name."""
    settings = config.runtime.links
    default_delay_s = {"cpfc_to_der": config.t_com_s, "measurement_to_cpfc": config.t_meas_s}
    params = {name: LinkParams.from_settings(name, getattr(settings, name),
                                             default_delay_s.get(name))
              for name in ICT_LINKS}
    for name in ("physical", "local"):
        params[name] = LinkParams.from_settings(name, LinkSettings(delay_s=0.0))
    return params


def _routes(keys: Keys, agents: tuple[str, ...], der_ids: list[str]):
    """The routes of every row of the protocol table for this run's parties."""
    ders = tuple(der_agent_id(d) for d in der_ids)
    for row in PROTOCOL:
        if row.sender == PER_DER_KIND:
            senders = [(der_agent_id(d), d) for d in der_ids]
        elif row.sender == "{agent}":
            senders = [(a, a) for a in agents]
        elif row.sender == "{party}":
            senders = [(a, a) for a in (*agents, LAUNCHER)]
        elif row.placeholder == "agent":       # up's messages to one agent each
            senders = [(row.sender, a) for a in agents]
        else:
            senders = [(row.sender, None)]
        for sender, who in senders:
            to: list[str] = []
            for name in row.receivers:
                if name == EVERY_AGENT:
                    to += agents
                elif name == PER_DER_KIND:
                    to += ders
                elif name == f"{{{row.placeholder}}}":
                    to.append(who)
                elif name not in (LAUNCHER, OPERATOR):
                    to.append(name)
            yield Route(row, sender, keys.of(row.name, who), tuple(to))


def _lookahead(agents, links, receivers) -> dict[tuple[str, str], int]:
    """All-pairs least delay (Floyd-Warshall); the diagonal holds the shortest cycle."""
    dist = {(a, b): INF_NS for a in agents for b in agents}
    for (sender, key), link in links.items():
        for to in receivers[key]:
            dist[(sender, to)] = min(dist[(sender, to)], link.min_delay_ns)
    for k in agents:
        for i in agents:
            d_ik = dist[(i, k)]
            if d_ik == INF_NS:
                continue
            for j in agents:
                through = d_ik + dist[(k, j)]
                if through < dist[(i, j)]:
                    dist[(i, j)] = through
    return {pair: int(d) for pair, d in dist.items() if d != INF_NS}
