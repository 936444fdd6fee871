"""Who connects to ``up``'s router: links per certificate identity, and the unexpected ones.

The router cannot count what its access control refuses (Zenoh drops a denied message without a
trace outside its own trace log, and the Python build has no statistics), but it knows every
link it accepts and, in the secure profile, the identity (certificate CN) behind it. A
:class:`SessionWatch` (a link-events listener on the router's session) counts the links opened
per identity and the most open at once, and calls **unexpected**: an identity that is not part
of the run (a certificate of the same CA made for another config), and an agent or site router
with more than one link at once (a second process using its certificate: a stolen key, or an
agent started twice). ``operator`` (``adnmesh fault``) may connect any number of times.
In the open profile links carry no identity; only their number is known.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import zenoh

from adnmesh.names import OPERATOR

__all__ = ["SessionReport", "SessionWatch"]

_ANONYMOUS = "(no certificate)"


@dataclass
class SessionReport:
    """Links the router accepted.

    Attributes
    ----------
    opened : dict
        Identity (``(no certificate)`` in the open profile) -> links opened.
    most_at_once : dict
        Identity -> the most links open at the same time.
    unexpected : list of str
        One line per unexpected identity (see the module docstring).
    """

    opened: dict[str, int] = field(default_factory=dict)
    most_at_once: dict[str, int] = field(default_factory=dict)
    unexpected: list[str] = field(default_factory=list)


class SessionWatch:
    """Counts the router's links by identity (thread-safe; see the module docstring).

    Parameters
    ----------
    identities : iterable of str
        The agents and site routers of the run: one link each at a time.
    """

    def __init__(self, identities) -> None:
        self.identities = frozenset(identities)
        self._lock = threading.Lock()
        self._open: dict[str, int] = {}
        self._report = SessionReport()
        self._listener = None

    def declare(self, session: zenoh.Session) -> None:
        """Start listening to ``session``'s link events."""
        self._listener = session.info.declare_link_events_listener(self.on_link, history=True)

    def undeclare(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.undeclare()

    def on_link(self, event: zenoh.LinkEvent) -> None:
        """A link was added or removed."""
        identity = event.link.auth_identifier or _ANONYMOUS
        with self._lock:
            now = self._open.get(identity, 0)
            if event.kind == zenoh.SampleKind.PUT:
                now += 1
                opened = self._report.opened
                opened[identity] = opened.get(identity, 0) + 1
                most = self._report.most_at_once
                most[identity] = max(most.get(identity, 0), now)
            else:
                now = max(0, now - 1)
            self._open[identity] = now

    def report(self) -> SessionReport:
        """What was seen so far, with the unexpected identities."""
        with self._lock:
            opened = dict(self._report.opened)
            most = dict(self._report.most_at_once)
        unexpected = []
        for identity in sorted(opened):
            if identity in (_ANONYMOUS, OPERATOR):
                continue
            if identity not in self.identities:
                unexpected.append(f"{identity} is not part of this run ({opened[identity]} "
                                  "link(s); its certificate is from this CA)")
            elif most[identity] > 1:
                unexpected.append(f"{identity} had {most[identity]} links at once (one "
                                  "expected: a second process with its certificate)")
        return SessionReport(opened, most, unexpected)
