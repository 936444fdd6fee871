"""Who talks to whom in a hierarchy of ADNs: the upper grid's and every ADN's topology as one.

A hierarchy (docs/hierarchy.md) is several grids on one bus: the upper grid, whose DERs are the
ADNs, and one grid per ADN. Each grid's own routes are its config's
(:class:`~adnmesh.sim.topology.Topology`, with the protocol's ``hierarchy`` kinds). Agent ids are
per grid (every ADN has a ``cpfc``), so here an agent is named ``<grid>:<agent id>``
(:func:`qualified`); keys already carry their grid. Three routes cross grids, per ADN ``a``:

- ``adn/<upper>/der/<a>/offset`` from the site agent (the upper grid's ``der/<a>``) to the ADN's
  CPFC, over a link whose delay is the part of the ADN's inter-site delay the upper config's
  ``t_com_s`` does not carry (``adnmesh cascade`` puts the shortest inter-site delay there);
- ``adn/<a>/measurement/exchange`` from the ADN's measurement to the site agent (``physical``);
- ``adn/<a>/cpfc/actuator``, the ADN's announcements, from its CPFC to the upper CPFC over the
  inter-site link (the ADN's inter-site delay; the upper CPFC applies the rule for lower
  switches). Not through the site agent: without a delay there, CPFC -> site -> CPFC would be a
  cycle the conservative clock cannot advance.

The result is an ordinary :class:`~adnmesh.sim.topology.Topology` over the qualified ids, so the
sim clock's coordinator and the nodes run a hierarchy as they run one grid. Its ``der_ids`` are
every grid's DER ids and its ``capacity_w`` the largest installed power any grid gives an id
(the gate's bound on a reported infeed).
"""

from __future__ import annotations

from collections.abc import Mapping

from adnmesh.config import Config, LinkSettings
from adnmesh.names import der_agent_id
from adnmesh.sim.links import LinkParams
from adnmesh.sim.topology import Route, Topology, _subscriptions

__all__ = ["HIERARCHY", "grid_of", "hierarchy_topology", "qualified"]

HIERARCHY = frozenset({"hierarchy"})
"""The protocol feature of a grid that is a level of a hierarchy."""

SEPARATOR = ":"


def qualified(grid: str, agent: str) -> str:
    """The name of agent ``agent`` of grid ``grid`` in a hierarchy: ``<grid>:<agent>``."""
    return f"{grid}{SEPARATOR}{agent}"


def grid_of(name: str) -> tuple[str, str]:
    """``(grid, agent id)`` of a qualified name."""
    grid, agent = name.split(SEPARATOR, 1)
    return grid, agent


def hierarchy_topology(upper: Config, adns: Mapping[str, Config],
                       offset_delay_s: Mapping[str, float]) -> Topology:
    """The topology of the hierarchy with upper config ``upper`` and ADN configs ``adns``
    (ADN id -> config; every id a DER of ``upper``); ``offset_delay_s`` gives each ADN's
    offset link delay, s (see the module docstring).

    Raises
    ------
    ValueError
        An ADN that is not a DER of the upper config, or two levels on one grid name.
    """
    grids = [upper.grid, *(c.grid for c in adns.values())]
    if len(set(grids)) != len(grids):
        raise ValueError(f"every level needs a grid name of its own, got {grids}")
    missing = sorted(set(adns) - set(upper.der_ids()))
    if missing:
        raise ValueError(f"ADNs {missing} are not DERs of the upper config")
    levels = {upper.grid: Topology.from_config(upper, HIERARCHY)}
    levels.update({c.grid: Topology.from_config(c, HIERARCHY) for c in adns.values()})
    agents, routes, links, receivers, capacity = [], [], {}, {}, {}
    for grid, t in levels.items():
        agents += [qualified(grid, a) for a in t.agents]
        for r in t.routes:
            routes.append(Route(r.kind, qualified(grid, r.sender) if r.sender in t.agents
                                else r.sender, r.key, tuple(qualified(grid, a)
                                                            for a in r.receivers)))
        links.update({(qualified(grid, a), k): p for (a, k), p in t.links.items()})
        receivers.update({k: tuple(qualified(grid, a) for a in to)
                          for k, to in t.receivers.items()})
        for der, p_inst in t.capacity_w.items():
            capacity[der] = max(capacity.get(der, 0.0), p_inst)
    up = levels[upper.grid]
    for adn, config in adns.items():
        site = qualified(upper.grid, der_agent_id(adn))
        lower = levels[config.grid]
        offset = up.keys.of("adn_offset", adn)
        links[(site, offset)] = LinkParams.from_settings(
            "local", LinkSettings(delay_s=offset_delay_s[adn]))
        receivers[offset] = (qualified(config.grid, "cpfc"),)
        exchange = lower.keys.of("adn_exchange")
        receivers[exchange] = (*receivers.get(exchange, ()), site)
        announcement = lower.keys.of("adn_actuator")
        links[(qualified(config.grid, "cpfc"), announcement)] = LinkParams.from_settings(
            "local", LinkSettings(delay_s=upper.t_com_s + offset_delay_s[adn]))
        receivers[announcement] = (qualified(upper.grid, "cpfc"),)
    routes = [r._replace(receivers=receivers[r.key]) if r.key in receivers else r
              for r in routes]
    return Topology(up.keys, tuple(agents), tuple(routes), links, receivers,
                    _subscriptions(agents, receivers), capacity)
