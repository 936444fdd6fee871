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

import functools
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from adnmesh.config import Config, LinkSettings
from adnmesh.names import ICT_LINKS, LAUNCHER, OPERATOR, PER_DER_KIND, agent_ids, der_agent_id
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
        Computed when first asked for (the clock's coordinator does; an agent does not): for
        1,003 agents it is a million pairs.
    """

    keys: Keys
    agents: tuple[str, ...]
    routes: tuple[Route, ...] = field(repr=False)
    links: dict = field(repr=False)
    receivers: dict = field(repr=False)
    subscriptions: dict = field(repr=False)
    capacity_w: dict = field(repr=False)

    @functools.cached_property
    def lookahead_ns(self) -> dict[tuple[str, str], int]:
        """See the class docstring."""
        return _lookahead(self.agents, self.links, self.receivers)

    @property
    def der_ids(self) -> frozenset[str]:
        """The DER ids of the run (those with an installed power)."""
        return frozenset(self.capacity_w)

    @classmethod
    def from_config(cls, config: Config, features: frozenset[str] = frozenset()) -> Topology:
        """The topology of ``config``'s run; ``features`` adds protocol features the config
        does not say (``hierarchy``: the grid is a level of a hierarchy of ADNs)."""
        keys = Keys(config.grid)
        der_ids = [d.id for d in config.ders]
        agents = agent_ids(der_ids)
        params = _link_params(config)
        features = config.features() | features
        routes = tuple(_routes(keys, agents, der_ids, features))
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
        return cls(keys, agents, routes, links, receivers, _subscriptions(agents, receivers),
                   {d.id: d.p_inst_w for d in config.ders})

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


def _subscriptions(agents, receivers) -> dict[str, tuple[str, ...]]:
    """``agent -> the keys it receives``, in the order of ``receivers`` (one pass over them)."""
    keys: dict[str, list[str]] = {a: [] for a in agents}
    for key, to in receivers.items():
        for agent in to:
            if agent in keys and (not keys[agent] or keys[agent][-1] != key):
                keys[agent].append(key)
    return {a: tuple(k) for a, k in keys.items()}


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


def _routes(keys: Keys, agents: tuple[str, ...], der_ids: list[str], features=frozenset()):
    """The routes of every row of the protocol table for this run's parties (of a row that
    needs a config section, ``feature``, only if the run has it)."""
    ders = tuple(der_agent_id(d) for d in der_ids)
    for row in PROTOCOL:
        if row.feature is not None and row.feature not in features:
            continue
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
    """All-pairs least delay, ns; the diagonal holds the shortest cycle through an agent.

    Dijkstra from every agent on the graph of direct links (the least delay of any key from
    one agent to another; a delay of 0, the physical link, is an edge), in scipy's compiled
    ``shortest_path``: ``O(n (e + n log n))`` for ``n`` agents and ``e`` links, a second for
    1,003 agents where the Floyd-Warshall loop it replaced took minutes (cubic, in Python).
    The cycle through ``a`` is the least ``delay(a, j) + dist(j, a)`` over its links. Delays
    are integers of ns far below 2^53, so the float sums are exact: the result is the same
    dict, pair for pair and in the same order (``(a, b)`` for ``a``, then ``b``, in agent
    order; an unreachable pair is missing), as the Floyd-Warshall loop's that
    ``tests/lookahead_reference.py`` keeps."""
    from scipy.sparse.csgraph import csgraph_from_dense, shortest_path   # up's clock only

    index = {a: i for i, a in enumerate(agents)}
    n = len(agents)
    direct = np.full((n, n), np.inf)
    for (sender, key), link in links.items():
        i = index[sender]
        for to in receivers[key]:
            j = index[to]
            direct[i, j] = min(direct[i, j], link.min_delay_ns)
    dist = shortest_path(csgraph_from_dense(direct, null_value=np.inf), method="D")
    np.fill_diagonal(dist, np.min(direct + dist.T, axis=1))   # the shortest cycle
    rows, cols = np.nonzero(np.isfinite(dist))
    names = np.array(agents, dtype=object)
    return dict(zip(zip(names[rows].tolist(), names[cols].tolist()),
                    dist[rows, cols].astype(np.int64).tolist()))
