"""Bus keys, built and parsed by the protocol table (:mod:`adnmesh.wire.protocol`).

Keys are hierarchical, ``adn/<grid>/<the kind's key>``, and double as MCAP topics and Rerun
entity paths. :meth:`Keys.of` builds the key of a message kind; :func:`route` tells the kind
and the one legitimate sender of a key (receivers reject a message whose ``src`` is not that
sender). Liveliness tokens live at ``alive/<party>`` (not messages).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

from adnmesh.names import ID_MAX_CHARS, ID_PATTERN, der_agent_id, der_id_of
from adnmesh.wire.protocol import KINDS, PROTOCOL, MessageKind

__all__ = ["Keys", "Route", "route"]

_GRID = re.compile(rf"^{ID_PATTERN}$")


@dataclass(frozen=True)
class Keys:
    """The bus keys of one grid, ``adn/<grid>/...``."""

    grid: str

    @property
    def root(self) -> str:
        return f"adn/{self.grid}"

    @property
    def all(self) -> str:
        """Key expression matching every message of the grid."""
        return f"adn/{self.grid}/**"

    def of(self, kind: str, who: str | None = None) -> str:
        """The key of message kind ``kind``; ``who`` fills its placeholder (a DER id for
        ``{der}``, an agent id for ``{agent}``, an agent id or ``up`` for ``{party}``).

        Raises
        ------
        KeyError
            Unknown kind.
        ValueError
            ``who`` missing for a key with a placeholder, or given for one without.
        """
        row = KINDS[kind]
        if (row.placeholder is None) != (who is None):
            raise ValueError(f"the key of {kind} takes {row.placeholder or 'no'} placeholder")
        key = row.key if who is None else row.key.replace(f"{{{row.placeholder}}}", who)
        return f"adn/{self.grid}/{key}"

    def host_grants(self, host: str) -> str:
        """Where the clock's grants to the agents of one hosting process go, in one sample
        (``host``: the process's first agent; each grant is the ``clock_grant`` envelope of
        its agent's key, the sample's attachment names the agents, one per line)."""
        return f"adn/{self.grid}/clock/grants/{host}"

    def liveliness(self, party: str) -> str:
        """Liveliness token of a running agent (``up`` itself is party ``up``)."""
        return f"adn/{self.grid}/alive/{party}"


class Route(NamedTuple):
    """What a key carries: its message kind and the only party that may send it."""

    kind: MessageKind
    sender: str

    @property
    def type(self) -> str:
        """The message type on the key."""
        return self.kind.type


_FIXED = {row.key: row for row in PROTOCOL if row.placeholder is None}
_TEMPLATED = [(re.compile(f"^{row.regex()}$"), row) for row in PROTOCOL if row.placeholder]


def _short(captured: str) -> bool:
    """No DER id (alone or in an agent id) longer than :data:`ID_MAX_CHARS`."""
    return len(der_id_of(captured) or captured) <= ID_MAX_CHARS


def _route(key: str) -> Route | None:
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != "adn" or len(parts[1]) > ID_MAX_CHARS or \
            not _GRID.match(parts[1]):
        return None
    rest = parts[2]
    row = _FIXED.get(rest)
    if row is not None:
        return Route(row, row.sender)
    for pattern, row in _TEMPLATED:
        found = pattern.match(rest)
        if found is not None:
            who = found.group(row.placeholder)
            if not _short(who):
                return None
            if row.sender == f"{{{row.placeholder}}}":
                return Route(row, who)
            if row.sender == "der":
                return Route(row, der_agent_id(who))
            return Route(row, row.sender)
    return None


_ROUTES: dict[str, Route] = {}
_ROUTES_KEPT = 32_768
"""Keys :func:`route` remembers: every key of a 1,000-DER run (about 7 per DER: state,
heartbeat, events, clock report, grant, kill and goodbye; 4,096 left most of them to a regex
search of 3.5 us at every message). Only keys that route are kept (their ids are short), so a
flood of foreign keys of any length neither grows it nor fills it."""


def route(key: str) -> Route | None:
    """The kind and legitimate sender of ``key``, or None if it is not an adnmesh message key.

    Remembers the answer for at most :data:`_ROUTES_KEPT` keys that route."""
    found = _ROUTES.get(key)
    if found is None:
        found = _route(key)
        if found is not None and len(_ROUTES) < _ROUTES_KEPT:
            _ROUTES[key] = found
    return found
