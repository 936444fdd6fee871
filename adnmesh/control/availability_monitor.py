"""The availability monitor: heartbeats and availability flags in, the SI vector out.

A DER counts as available (``SI_d = true``) while the last heartbeat it delivered said
``available: true`` in a mode other than ``watchdog`` (a DER in its watchdog fallback does not
follow the CPFC) and was delivered less than ``heartbeat_timeout_s`` ago: a DER that stops
sending (ICT fault, dead process) drops out when its heartbeat times out, after
``floor(heartbeat_timeout_s / heartbeat_period_s)`` missed heartbeats (2 by default), and comes
back with its next heartbeat. Every DER is available at t = 0. The monitor sends SI on
``availability/si`` at t = 0, whenever it changes and every ``heartbeat_period_s`` (so that a
restarted CPFC learns it), and every change of a DER as an event (``event/availability``).
A **restarted** monitor knows nothing: it listens for ``heartbeat_timeout_s`` (every live DER
is heard at least twice, a silent one times out) before its first SI, so that it never
announces a DER that left while it was down.

SI is sent **once per instant**, with every change of that instant: a heartbeat that changes SI
only sets a timer at its own delivery time, and the runtime fires timers after every message
delivered at the same time (:class:`adnmesh.runtime.node.Node`). So when several DERs change
at once (the SimBench scenario's six wind turbines at 170 s), the CPFC and the recording see
one change, not one SI per heartbeat.
"""

from __future__ import annotations

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.names import der_agent_id, der_id_of
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["AvailabilityMonitor"]


class AvailabilityMonitor(Agent):
    """Builds SI from heartbeats (agent id ``availability``; see the module docstring)."""

    agent_id = "availability"

    def __init__(self, config: Config) -> None:
        keys = Keys(config.grid)
        self._si_key = keys.of("si")
        self._event_key = keys.of("event", self.agent_id)
        self.timeout_ns = ns(config.runtime.heartbeat_timeout_s)
        self.period_ns = ns(config.runtime.heartbeat_period_s)
        self.der_ids = config.der_ids()
        self.flag = dict.fromkeys(self.der_ids, True)
        self.reason = dict.fromkeys(self.der_ids, "")
        self.deadline_ns = dict.fromkeys(self.der_ids, self.timeout_ns)
        self.expired: set[str] = set()
        self._sent: dict[str, bool] | None = None
        self._send_ns: int | None = 0   # when SI goes out if it changed (0: the initial SI)
        self._next_repeat_ns = self.period_ns
        self._quiet_until_ns = 0        # a restarted monitor sends no SI before this

    def resume(self, t_ns: int) -> None:
        """A restarted monitor at ``t_ns``: it listens for one heartbeat timeout, then sends SI
        as the heartbeats (or their absence) say."""
        self.deadline_ns = dict.fromkeys(self.der_ids, t_ns + self.timeout_ns)
        self._quiet_until_ns = t_ns + self.timeout_ns
        self._send_ns = None
        self._next_repeat_ns = self._quiet_until_ns

    def si(self) -> dict[str, bool]:
        """The current availability vector, in config order."""
        return {d: self.flag[d] and d not in self.expired for d in self.der_ids}

    def next_timer_ns(self) -> int | None:
        """The earliest of: sending SI changed at this instant, a live heartbeat's deadline,
        the periodic repetition of SI."""
        times = [t for d, t in self.deadline_ns.items() if d not in self.expired]
        times.append(self._next_repeat_ns)
        if self._send_ns is not None:
            times.append(self._send_ns)
        return min(times)

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        der_id = der_id_of(message.src)
        if der_id not in self.flag:
            return []
        self.flag[der_id] = message.available and message.mode != "watchdog"
        self.reason[der_id] = "" if self.flag[der_id] else (
            "in watchdog fallback" if message.mode == "watchdog" else
            "its heartbeat says it is not available")
        self.deadline_ns[der_id] = t_ns + self.timeout_ns
        self.expired.discard(der_id)
        if self.si() != self._sent and t_ns >= self._quiet_until_ns:
            self._send_ns = t_ns   # after the other messages of this instant
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        self._send_ns = None
        for der_id, deadline in self.deadline_ns.items():
            if deadline <= t_ns and der_id not in self.expired:
                self.expired.add(der_id)
                self.reason[der_id] = f"no heartbeat for {self.timeout_ns / 1e9:g} s"
        repeat = t_ns >= self._next_repeat_ns
        if repeat:
            self._next_repeat_ns = t_ns + self.period_ns
        return self._publish(t_ns, repeat)

    def _publish(self, t_ns: int, repeat: bool) -> list[Outgoing]:
        si = self.si()
        if si == self._sent and not repeat:
            return []
        out = []
        if self._sent is not None:
            for der_id in self.der_ids:
                if si[der_id] != self._sent[der_id]:
                    out.append(Outgoing(self._event_key, {
                        "level": "INFO" if si[der_id] else "WARNING",
                        "kind": "available" if si[der_id] else "unavailable",
                        "subject": der_agent_id(der_id),
                        "text": f"{der_id} available again" if si[der_id] else
                                f"{der_id} unavailable: {self.reason[der_id]}"}))
        self._sent = si
        return [Outgoing(self._si_key, {"si": si}), *out]
