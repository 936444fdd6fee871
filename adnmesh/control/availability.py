"""The availability monitor: heartbeats and availability flags in, the SI vector out.

A DER counts as available (``SI_d = true``) while the last heartbeat it delivered said
``available: true`` and was delivered less than ``heartbeat_timeout_s`` ago: a DER that stops
sending (ICT fault, crash) drops out when its heartbeat times out. Every DER is available at
t = 0. The monitor sends SI on ``availability/si`` at t = 0 and whenever it changes.

SI is sent **once per instant**, with every change of that instant: a heartbeat that changes SI
only sets a timer at its own delivery time, and the runtime fires timers after every message
delivered at the same time (:class:`adnmesh.runtime.node.Node`). So when several DERs change
at once (the SimBench scenario's six wind turbines at 170 s), the CPFC and the recording see
one change, not one SI per heartbeat.
"""

from __future__ import annotations

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.wire.keys import Keys, der_id_of
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["AvailabilityMonitor"]


class AvailabilityMonitor(Agent):
    """Builds SI from heartbeats (agent id ``availability``; see the module docstring)."""

    agent_id = "availability"

    def __init__(self, config: Config) -> None:
        keys = Keys(config.grid)
        self._si_key = keys.si
        self.timeout_ns = ns(config.runtime.heartbeat_timeout_s)
        self.der_ids = config.der_ids()
        self.flag = dict.fromkeys(self.der_ids, True)
        self.deadline_ns = dict.fromkeys(self.der_ids, self.timeout_ns)
        self.expired: set[str] = set()
        self._sent: dict[str, bool] | None = None
        self._send_ns: int | None = 0   # when SI goes out if it changed (0: the initial SI)

    def si(self) -> dict[str, bool]:
        """The current availability vector, in config order."""
        return {d: self.flag[d] and d not in self.expired for d in self.der_ids}

    def next_timer_ns(self) -> int | None:
        """The earliest of: sending SI changed at this instant, a live heartbeat's deadline."""
        times = [t for d, t in self.deadline_ns.items() if d not in self.expired]
        if self._send_ns is not None:
            times.append(self._send_ns)
        return min(times) if times else None

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        der_id = der_id_of(message.src)
        if der_id not in self.flag:
            return []
        self.flag[der_id] = message.available
        self.deadline_ns[der_id] = t_ns + self.timeout_ns
        self.expired.discard(der_id)
        if self.si() != self._sent:
            self._send_ns = t_ns   # after the other messages of this instant
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        self._send_ns = None
        for der_id, deadline in self.deadline_ns.items():
            if deadline <= t_ns:
                self.expired.add(der_id)
        return self._publish_if_changed()

    def _publish_if_changed(self) -> list[Outgoing]:
        si = self.si()
        if si == self._sent:
            return []
        self._sent = si
        return [Outgoing(self._si_key, {"si": si})]
