"""Who talks to whom: the agents of a config, the keys they publish, and the links in between.

The topology is static (it follows from the config), so every process can compute it for itself:
agents use it to know what to subscribe to and which link a key goes over; the coordinator uses it
to know who receives a message (for counting messages in flight) and how far ahead every agent may
run (the lookahead: the shortest sum of link delays from one agent to another).

================  =====================  =================  ===============================
sender            key (``adn/<grid>/``)  receivers          link (least delay)
================  =====================  =================  ===============================
``cpfc``          ``cpfc/p_y``           every DER          ``cpfc_to_der`` (T_com)
``cpfc``          ``scenario/p_ref``     (recorded only)    ``local`` (0)
``der/<id>``      ``der/<id>/state``     ``measurement``    ``physical`` (0)
``der/<id>``      ``der/<id>/heartbeat`` availability,      ``der_to_availability``
                                         ``cpfc`` (acks)
``measurement``   ``measurement/p_ip``   ``cpfc``           ``measurement_to_cpfc`` (T_meas)
``measurement``   ``measurement/grid``   (recorded only)    ``local`` (0)
``availability``  ``availability/si``    ``cpfc``           ``availability_to_cpfc``
any agent         ``event/<agent>``      (recorded only)    ``local`` (0)
``up``            ``faults``             every agent        (``up``'s own, not a link)
================  =====================  =================  ===============================

:data:`ICT_LINKS` are the links an injected fault can disturb; ``physical`` (a DER's infeed is
physics, not communication) and ``local`` (records nobody receives) are not among them.

Every cycle passes CPFC → DERs, whose delay ``t_com_s`` is positive, so the lookahead around
every cycle is positive and the conservative clock always makes progress.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from adnmesh.config import Config, LinkSettings
from adnmesh.sim.links import LinkParams
from adnmesh.wire.keys import Keys, der_agent_id

__all__ = ["ICT_LINKS", "INF_NS", "Topology"]

ICT_LINKS = frozenset({"cpfc_to_der", "measurement_to_cpfc", "der_to_availability",
                       "availability_to_cpfc"})
"""The links that are communication (and can fail)."""

INF_NS = math.inf
"""'Never' on the nanosecond time axis."""


@dataclass(frozen=True)
class Topology:
    """The static message graph of a config.

    Attributes
    ----------
    keys : Keys
        Bus keys of the grid.
    agents : tuple of str
        Agent ids: ``cpfc``, ``measurement``, ``availability``, then ``der/<id>`` in config order.
    links : dict
        ``(sender, key) -> LinkParams`` for every key an agent publishes.
    receivers : dict
        ``key -> tuple of agent ids`` that subscribe to it (empty for records nobody consumes).
    subscriptions : dict
        ``agent -> tuple of keys`` it subscribes to.
    lookahead_ns : dict
        ``(a, b) -> ns``: least total link delay of any message chain from ``a`` to ``b``
        (``(a, a)``: around the shortest cycle through ``a``); missing if ``b`` is unreachable.
    """

    keys: Keys
    agents: tuple[str, ...]
    links: dict = field(repr=False)
    receivers: dict = field(repr=False)
    subscriptions: dict = field(repr=False)
    lookahead_ns: dict = field(repr=False)

    @property
    def der_ids(self) -> frozenset[str]:
        """The DER ids of the run."""
        return frozenset(a[4:] for a in self.agents if a.startswith("der/"))

    @classmethod
    def from_config(cls, config: Config) -> Topology:
        keys = Keys(config.grid)
        rt = config.runtime
        ders = [der_agent_id(d.id) for d in config.ders]
        agents = ("cpfc", "measurement", "availability", *ders)
        to_der = LinkParams.from_settings("cpfc_to_der", rt.links.cpfc_to_der, config.t_com_s)
        to_cpfc = LinkParams.from_settings("measurement_to_cpfc", rt.links.measurement_to_cpfc,
                                           config.t_meas_s)
        heartbeat = LinkParams.from_settings("der_to_availability",
                                             rt.links.der_to_availability)
        si = LinkParams.from_settings("availability_to_cpfc", rt.links.availability_to_cpfc)
        physical = LinkParams.from_settings("physical", LinkSettings(delay_s=0.0))
        local = LinkParams.from_settings("local", LinkSettings(delay_s=0.0))

        links: dict[tuple[str, str], LinkParams] = {}
        receivers: dict[str, tuple[str, ...]] = {}

        def route(sender: str, key: str, link: LinkParams, to: tuple[str, ...]) -> None:
            links[(sender, key)] = link
            receivers[key] = to

        route("cpfc", keys.p_y, to_der, tuple(ders))
        route("cpfc", keys.p_ref, local, ())
        route("measurement", keys.p_ip, to_cpfc, ("cpfc",))
        route("measurement", keys.grid_state, local, ())
        route("availability", keys.si, si, ("cpfc",))
        for der in config.ders:
            agent = der_agent_id(der.id)
            route(agent, keys.der_state(der.id), physical, ("measurement",))
            route(agent, keys.heartbeat(der.id), heartbeat, ("availability", "cpfc"))
        for agent in agents:
            route(agent, keys.event(agent), local, ())
        receivers[keys.faults] = agents

        subscriptions = {a: tuple(k for k, to in receivers.items() if a in to) for a in agents}
        return cls(keys, agents, links, receivers, subscriptions,
                   _lookahead(agents, links, receivers))

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
        """Keys ``agent`` publishes."""
        return tuple(k for (a, k) in self.links if a == agent)


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
