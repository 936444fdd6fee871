"""Bus keys: what each key below ``adn/<grid>/`` carries and who may send it.

Keys are hierarchical and double as MCAP topics and Rerun entity paths. ``<grid>`` is the
config's ``grid``; agent ids are ``cpfc``, ``measurement``, ``availability`` and ``der/<id>``;
``up`` is ``adnmesh up`` itself (the launcher, recorder and sim-clock coordinator).

===========================  ================  =================  ===============================
key                          type              sender             to
===========================  ================  =================  ===============================
``cpfc/p_y``                 ``p_y``           ``cpfc``           every DER (P_Y; weights W)
``scenario/p_ref``           ``p_ref``         ``cpfc``           (recorded)
``der/<id>/state``           ``der_state``     ``der/<id>``       measurement (infeed)
``der/<id>/heartbeat``       ``heartbeat``     ``der/<id>``       availability monitor
``measurement/p_ip``         ``p_ip``          ``measurement``    CPFC
``measurement/grid``         ``grid_state``    ``measurement``    (recorded: the grid's extremes)
``availability/si``          ``si``            ``availability``   CPFC
``faults``                   ``fault``         ``up``             every agent (injected faults)
``event/<agent>``            ``event``         ``<agent>``/``up`` (recorded: what it noticed)
``control/fault``            ``fault_request`` ``operator``       ``up`` (``adnmesh fault``)
``clock/report/<agent>``     ``clock_report``  ``<agent>``        ``up`` (sim clock)
``clock/grant/<agent>``      ``clock_grant``   ``up``             ``<agent>`` (sim clock)
``clock/start``              ``clock_start``   ``up``             every agent
``clock/stop``               ``clock_stop``    ``up``             every agent
``clock/bye/<agent>``        ``agent_bye``     ``<agent>``        ``up``
``clock/kill/<agent>``       ``clock_stop``    ``up``             ``<agent>`` (kill noted: die)
===========================  ================  =================  ===============================

:func:`route` tells the type and the one legitimate sender of a key; receivers reject a message
whose ``src`` is not that sender. Liveliness tokens live at ``alive/<agent>`` (not messages).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

__all__ = [
    "AGENT_PATTERN",
    "ID_MAX_CHARS",
    "ID_PATTERN",
    "LAUNCHER",
    "OPERATOR",
    "Keys",
    "Route",
    "der_agent_id",
    "der_id_of",
    "route",
]

ID_PATTERN = r"[A-Za-z][A-Za-z0-9_-]*"
"""A grid name or DER id: letters, digits, ``_`` and ``-``, starting with a letter."""

ID_MAX_CHARS = 64
"""Longest DER id or grid name."""

AGENT_PATTERN = rf"(?:cpfc|measurement|availability|der/{ID_PATTERN})"
"""An agent id."""

LAUNCHER = "up"
"""The sender id of ``adnmesh up`` itself."""

OPERATOR = "operator"
"""The sender id of a person's command to a running ``up`` (``adnmesh fault``)."""

_ID = re.compile(rf"^{ID_PATTERN}$")
_SIMPLE_AGENTS = frozenset({"cpfc", "measurement", "availability"})


def der_agent_id(der_id: str) -> str:
    """Agent id of the local controller of DER ``der_id``: ``der/<id>``."""
    return f"der/{der_id}"


def der_id_of(agent_id: str) -> str | None:
    """The DER id of agent ``der/<id>``, else None."""
    return agent_id[4:] if agent_id.startswith("der/") else None


class Route(NamedTuple):
    """What a key carries: its message ``type`` and the only agent that may send it."""

    type: str
    sender: str


@dataclass(frozen=True)
class Keys:
    """The bus keys of one grid, ``adn/<grid>/...`` (see the module docstring)."""

    grid: str

    @property
    def root(self) -> str:
        return f"adn/{self.grid}"

    @property
    def all(self) -> str:
        """Key expression matching every message of the grid."""
        return f"adn/{self.grid}/**"

    @property
    def p_y(self) -> str:
        return f"adn/{self.grid}/cpfc/p_y"

    @property
    def p_ref(self) -> str:
        return f"adn/{self.grid}/scenario/p_ref"

    def der_state(self, der_id: str) -> str:
        return f"adn/{self.grid}/der/{der_id}/state"

    def heartbeat(self, der_id: str) -> str:
        return f"adn/{self.grid}/der/{der_id}/heartbeat"

    @property
    def p_ip(self) -> str:
        return f"adn/{self.grid}/measurement/p_ip"

    @property
    def grid_state(self) -> str:
        return f"adn/{self.grid}/measurement/grid"

    @property
    def si(self) -> str:
        return f"adn/{self.grid}/availability/si"

    @property
    def faults(self) -> str:
        return f"adn/{self.grid}/faults"

    def event(self, agent: str) -> str:
        return f"adn/{self.grid}/event/{agent}"

    @property
    def fault_request(self) -> str:
        return f"adn/{self.grid}/control/fault"

    def kill(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/kill/{agent}"

    def report(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/report/{agent}"

    def grant(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/grant/{agent}"

    @property
    def start(self) -> str:
        return f"adn/{self.grid}/clock/start"

    @property
    def stop(self) -> str:
        return f"adn/{self.grid}/clock/stop"

    def bye(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/bye/{agent}"

    def liveliness(self, agent: str) -> str:
        """Liveliness token of a running agent (``up`` itself is agent ``up``)."""
        return f"adn/{self.grid}/alive/{agent}"


def _agent(parts: list[str]) -> str | None:
    """The agent id spelled by the key levels ``parts`` (``['cpfc']``, ``['der', 'X']``)."""
    if len(parts) == 1 and parts[0] in _SIMPLE_AGENTS:
        return parts[0]
    if len(parts) == 2 and parts[0] == "der" and _is_id(parts[1]):
        return f"der/{parts[1]}"
    return None


def _is_id(text: str) -> bool:
    return len(text) <= ID_MAX_CHARS and _ID.match(text) is not None


def _route(key: str) -> Route | None:
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != "adn" or not _is_id(parts[1]):
        return None
    rest = parts[2:]
    fixed = {
        ("cpfc", "p_y"): Route("p_y", "cpfc"),
        ("scenario", "p_ref"): Route("p_ref", "cpfc"),
        ("measurement", "p_ip"): Route("p_ip", "measurement"),
        ("measurement", "grid"): Route("grid_state", "measurement"),
        ("availability", "si"): Route("si", "availability"),
        ("clock", "start"): Route("clock_start", LAUNCHER),
        ("faults",): Route("fault", LAUNCHER),
        ("control", "fault"): Route("fault_request", OPERATOR),
        ("event", LAUNCHER): Route("event", LAUNCHER),
        ("clock", "stop"): Route("clock_stop", LAUNCHER),
    }.get(tuple(rest))
    if fixed is not None:
        return fixed
    if len(rest) == 3 and rest[0] == "der" and _is_id(rest[1]) and rest[2] in ("state",
                                                                              "heartbeat"):
        return Route("der_state" if rest[2] == "state" else "heartbeat", f"der/{rest[1]}")
    if rest[0] == "event" and (agent := _agent(rest[1:])) is not None:
        return Route("event", agent)
    if len(rest) >= 3 and rest[0] == "clock" and (agent := _agent(rest[2:])) is not None:
        return {"report": Route("clock_report", agent), "grant": Route("clock_grant", LAUNCHER),
                "bye": Route("agent_bye", agent),
                "kill": Route("clock_stop", LAUNCHER)}.get(rest[1])
    return None


_ROUTES: dict[str, Route | None] = {}
_ROUTES_KEPT = 4096


def route(key: str) -> Route | None:
    """The type and legitimate sender of ``key``, or None if it is not an adnmesh message key.

    Remembers the answer for at most 4,096 keys (a flood of foreign keys cannot grow it)."""
    found = _ROUTES.get(key, False)
    if found is False:
        found = _route(key)
        if len(_ROUTES) < _ROUTES_KEPT:
            _ROUTES[key] = found
    return found
