"""Zenoh access control of the secure profile, derived from the topology (bus-free).

Every identity (the CN of its certificate, :mod:`adnmesh.runtime.certificates`) gets exactly the rights
the message graph of the config gives it, and nothing else: the router denies by default.

=================  ==========================================  ==================================
identity           may publish (``put``, ingress)              may subscribe to and is sent
=================  ==========================================  ==================================
``cpfc``           ``cpfc/p_y``, ``scenario/p_ref``            ``measurement/p_ip``,
                                                               ``availability/si``, heartbeats
``der/<id>``       ``der/<id>/state``, ``der/<id>/heartbeat``  ``cpfc/p_y``
``measurement``    ``measurement/p_ip``                        every ``der/<id>/state``
``availability``   ``availability/si``                         every ``der/<id>/heartbeat``
every agent        ``event/<agent>``, ``clock/report/<agent>``  ``faults``, ``clock/start``,
                   ``clock/bye/<agent>``; liveliness token     ``clock/stop``,
                   ``alive/<agent>``                           ``clock/grant/<agent>``,
                                                               ``clock/kill/<agent>``; the
                                                               liveliness of ``alive/up``
``operator``       ``control/fault``                           ``event/up``
=================  ==========================================  ==================================

``up`` is the router's own session (grants, start, stop, kill, faults, the recorder's
subscription to everything): Zenoh filters transports, not the router's local session. A **peer
router** (a site router of ``adnmesh router``, or ``up`` seen from one) carries the messages of
the agents behind it: it may publish every key of the run except ``up``'s own and forward the
agents' liveliness tokens (``up`` may publish all keys and tokens), declare subscribers and
liveliness subscribers on ``adn/<grid>/**``, and is sent everything; each router enforces the
rules above on its own clients.

:func:`rights` is the table above computed from a :class:`~adnmesh.sim.topology.Topology` (the
routes of the protocol table, :mod:`adnmesh.wire.protocol`);
:func:`access_control` turns it into the ``access_control`` section of a router's Zenoh config.
"""

from __future__ import annotations

from dataclasses import dataclass

from adnmesh.names import LAUNCHER, OPERATOR
from adnmesh.sim.topology import Topology
from adnmesh.wire.keys import Keys

__all__ = ["Rights", "access_control", "launcher_keys", "rights"]

_INGRESS, _EGRESS = ["ingress"], ["egress"]
_PEER_DECLARATIONS = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


@dataclass(frozen=True)
class Rights:
    """What one identity may do on the bus.

    Attributes
    ----------
    identity : str
    publishes : tuple of str
        Keys it may put.
    receives : tuple of str
        Keys it may subscribe to, and that the router sends it.
    token : str or None
        Its liveliness token.
    watches : tuple of str
        Liveliness keys it may subscribe to (and whose tokens it is sent).
    """

    identity: str
    publishes: tuple[str, ...]
    receives: tuple[str, ...]
    token: str | None = None
    watches: tuple[str, ...] = ()


def launcher_keys(topology: Topology) -> tuple[str, ...]:
    """The keys only ``up`` publishes: clock start, stop, grants and kills; faults; its
    events."""
    return topology.sends(LAUNCHER)


def rights(topology: Topology) -> dict[str, Rights]:
    """The rights of every client identity of a run (agents and ``operator``), by identity:
    what the protocol table has it send and receive (:mod:`adnmesh.wire.protocol`); the
    operator also hears ``up``'s events, where ``up`` answers its requests. In a hierarchy's
    topology an agent is ``<grid>:<agent id>``, its liveliness that of its grid."""
    keys = topology.keys
    found = {}
    for agent in topology.agents:
        own = _grid_keys(topology, agent)
        found[agent] = Rights(agent, topology.sends(agent), topology.gets(agent),
                              own.liveliness(_local(agent)), (own.liveliness(LAUNCHER),))
    found[OPERATOR] = Rights(OPERATOR, topology.sends(OPERATOR), (keys.of("event", LAUNCHER),))
    return found


def _local(agent: str) -> str:
    """The agent id of a (possibly ``<grid>:``-qualified) agent name."""
    return agent.split(":", 1)[1] if ":" in agent else agent


def _grid_keys(topology: Topology, agent: str) -> Keys:
    """The keys of the grid of ``agent`` (a hierarchy's name ``<grid>:<agent id>``)."""
    return Keys(agent.split(":", 1)[0]) if ":" in agent else topology.keys


def _all_keys(topology: Topology) -> list[str]:
    """``adn/<grid>/**`` of every grid of the run (one, or a hierarchy's levels)."""
    return sorted({_grid_keys(topology, a).all for a in topology.agents} | {topology.keys.all})


def access_control(topology: Topology, peers=(), clients=None, carries=None) -> dict:
    """The ``access_control`` section of a router's Zenoh config (deny by default).

    Parameters
    ----------
    topology : Topology
    peers : iterable of str
        Identities of the routers this one links to (``up``, ``router/<name>``).
    clients : collection of str, optional
        The identities that may be this router's clients (a hierarchy's: ``up``'s router
        takes the upper level's agents not behind a site, a site router its site's agents;
        ``operator`` always); default every agent of the topology.
    carries : dict, optional
        Peer -> the agents behind it (a hierarchy's site router): it may forward only what
        they send and their liveliness, declare and be sent only what they receive; default
        every agent's (see the module docstring).
    """
    rules, subjects, policies = [], [], []

    def allow(identity: str, what: str, flows, messages, key_exprs) -> str | None:
        if not key_exprs:
            return None
        rule_id = f"{identity} {what}"
        rules.append({"id": rule_id, "permission": "allow", "flows": flows,
                      "messages": messages, "key_exprs": sorted(set(key_exprs))})
        return rule_id

    def subject(identity: str, rule_ids) -> None:
        subjects.append({"id": identity, "cert_common_names": [identity]})
        policies.append({"id": identity, "rules": [r for r in rule_ids if r is not None],
                         "subjects": [identity]})

    for r in rights(topology).values():
        if clients is not None and r.identity not in clients and r.identity != OPERATOR:
            continue
        subject(r.identity, [
            allow(r.identity, "publishes", _INGRESS, ["put"], r.publishes),
            allow(r.identity, "subscribes", _INGRESS, ["declare_subscriber"], r.receives),
            allow(r.identity, "receives", _EGRESS, ["put"], r.receives),
            allow(r.identity, "is alive", _INGRESS, ["liveliness_token"],
                  [r.token] if r.token else []),
            allow(r.identity, "watches", _INGRESS, ["declare_liveliness_subscriber"],
                  r.watches),
            allow(r.identity, "is told", _EGRESS, ["liveliness_token"], r.watches),
        ])
    for peer in dict.fromkeys(peers):
        subject(peer, _peer_rules(topology, peer, (carries or {}).get(peer), allow))
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def _peer_rules(topology: Topology, peer: str, behind, allow) -> list:
    """The rule ids of peer router ``peer``: everything (``up``), every agent's but ``up``'s
    own keys (a site router of one grid), or what the agents ``behind`` it send, receive and
    watch (a hierarchy's site router; what is declared to it stays everything: ``up``'s
    recorders subscribe to every grid)."""
    everything = _all_keys(topology)
    if behind is not None:
        found = rights(topology)
        sends = [k for a in behind for k in found[a].publishes]
        gets = [k for a in behind for k in (*found[a].receives, *found[a].watches)]
        tokens = [found[a].token for a in behind if found[a].token]
        return [allow(peer, "forwards", _INGRESS, ["put"], sends),
                allow(peer, "is sent", _EGRESS, ["put", "liveliness_token"], gets),
                allow(peer, "declares", _INGRESS, _PEER_DECLARATIONS, gets),
                allow(peer, "is declared", _EGRESS, _PEER_DECLARATIONS, everything),
                allow(peer, "forwards tokens", _INGRESS, ["liveliness_token"], tokens)]
    own = set(launcher_keys(topology))
    every_key = _every_key(topology)
    carried = every_key if peer == LAUNCHER else [k for k in every_key if k not in own]
    tokens = everything if peer == LAUNCHER else [
        _grid_keys(topology, a).liveliness(_local(a)) for a in topology.agents]
    return [allow(peer, "forwards", _INGRESS, ["put"], carried),
            allow(peer, "is sent", _EGRESS, ["put", "liveliness_token"], everything),
            allow(peer, "declares", ["ingress", "egress"], _PEER_DECLARATIONS, everything),
            allow(peer, "forwards tokens", _INGRESS, ["liveliness_token"], tokens)]


def _every_key(topology: Topology) -> list[str]:
    """Every key anyone of the run may publish."""
    found = list(launcher_keys(topology))
    for r in rights(topology).values():
        found += r.publishes
    return sorted(set(found))
