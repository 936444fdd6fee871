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

Each heartbeat costs the same whatever the number of DERs: SI and its difference to the last
one sent are kept up to date DER by DER, and the heartbeats' deadlines sit in a heap.

SI is sent **once per instant**, with every change of that instant: a heartbeat that changes SI
only sets a timer at its own delivery time, and the runtime fires timers after every message
delivered at the same time (:class:`adnmesh.runtime.node.Node`). So when several DERs change
at once (the SimBench scenario's six wind turbines at 170 s), the CPFC and the recording see
one change, not one SI per heartbeat.
"""

from __future__ import annotations

import heapq

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
        self._si = dict.fromkeys(self.der_ids, True)   # SI now, in config order
        self._sent: dict[str, bool] | None = None
        self._differ: set[str] = set()    # the DERs whose SI differs from the SI last sent
        self._deadlines: list[tuple[int, str]] = []   # heap; an entry is live while it is
        self._heap_deadlines()                         # its DER's deadline and not expired
        self._send_ns: int | None = 0   # when SI goes out if it changed (0: the initial SI)
        self._next_repeat_ns = self.period_ns
        self._quiet_until_ns = 0        # a restarted monitor sends no SI before this

    def resume(self, t_ns: int) -> None:
        """A restarted monitor at ``t_ns``: it listens for one heartbeat timeout, then sends SI
        as the heartbeats (or their absence) say."""
        self.deadline_ns = dict.fromkeys(self.der_ids, t_ns + self.timeout_ns)
        self._heap_deadlines()
        self._quiet_until_ns = t_ns + self.timeout_ns
        self._send_ns = None
        self._next_repeat_ns = self._quiet_until_ns

    def si(self) -> dict[str, bool]:
        """The current availability vector, in config order."""
        return dict(self._si)

    def _set_si(self, der_id: str) -> None:
        """SI of ``der_id`` from its flag and expiry, and whether it differs from SI sent."""
        value = self._si[der_id] = self.flag[der_id] and der_id not in self.expired
        if self._sent is not None and value == self._sent[der_id]:
            self._differ.discard(der_id)
        else:
            self._differ.add(der_id)

    def _heap_deadlines(self) -> None:
        self._deadlines = [(t, d) for d, t in self.deadline_ns.items() if d not in self.expired]
        heapq.heapify(self._deadlines)

    def _live_deadline(self) -> tuple[int, str] | None:
        """The earliest deadline of a DER not expired (entries no longer live are dropped)."""
        heap = self._deadlines
        while heap:
            t, der_id = heap[0]
            if self.deadline_ns[der_id] == t and der_id not in self.expired:
                return heap[0]
            heapq.heappop(heap)
        return None

    def next_timer_ns(self) -> int | None:
        """The earliest of: sending SI changed at this instant, a live heartbeat's deadline,
        the periodic repetition of SI."""
        live = self._live_deadline()
        times = [self._next_repeat_ns] if live is None else [live[0], self._next_repeat_ns]
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
        deadline = self.deadline_ns[der_id] = t_ns + self.timeout_ns
        heapq.heappush(self._deadlines, (deadline, der_id))
        self.expired.discard(der_id)
        self._set_si(der_id)
        if (self._differ or self._sent is None) and t_ns >= self._quiet_until_ns:
            self._send_ns = t_ns   # after the other messages of this instant
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        self._send_ns = None
        while (live := self._live_deadline()) is not None and live[0] <= t_ns:
            der_id = heapq.heappop(self._deadlines)[1]
            self.expired.add(der_id)
            self.reason[der_id] = f"no heartbeat for {self.timeout_ns / 1e9:g} s"
            self._set_si(der_id)
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
        self._differ.clear()
        return [Outgoing(self._si_key, {"si": si}), *out]
