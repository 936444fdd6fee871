"""The local controller of one DER (SPEC §1 Eq. 1, §5), as a bus-free state machine.

The controller turns the CPFC's ``P_Y`` into the DER's setpoint

    P_ref,d = P_Y · w_d · C_d + P_sched,d,        C_d = P_inst,d,

limited to ``[0, P_avail,d]`` (``P_avail,d = P_inst,d`` for the reference model), and drives the
DER's dynamics (:mod:`adnmesh.control.dynamics`) with it. Its mode says where the setpoint comes
from:

``control``
    available and in contact: Eq. 1 with the weight ``w_d`` of the CPFC's current entry (0 if the
    entry does not use the DER);
``schedule``
    unavailable (scenario ``availability``): the DER leaves the control and runs at
    ``P_sched,d``;
``watchdog``
    no valid command for ``watchdog_timeout_s``: back to ``P_sched,d`` until commands return.

A ``P_Y`` is valid if its ``entry`` matches the entry whose weights the DER holds (weights come
with the switch and are repeated periodically). Every ``measurement_period_s`` the DER reports its
infeed and setpoint on ``der/<id>/state`` (exact at that instant); every ``heartbeat_period_s``,
and at once when its availability changes, it sends a heartbeat with its availability flag.
During an injected ICT fault (``runtime.faults.der_offline``) it receives no commands and sends
no heartbeats, and records the fault's start and end on ``fault/der/<id>``.
"""

from __future__ import annotations

from adnmesh.config import DER, Config
from msgspec import UNSET

from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.dynamics import PT1DelayParams, PT1DelayState, infeed_at, set_point
from adnmesh.wire.keys import Keys, der_agent_id
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["DERController"]

_NEVER = 1 << 62


class DERController(Agent):
    """Local controller of DER ``der`` (agent id ``der/<id>``; see the module docstring)."""

    def __init__(self, der: DER, config: Config) -> None:
        self.der = der
        self.agent_id = der_agent_id(der.id)
        keys = Keys(config.grid)
        self._state_key = keys.der_state(der.id)
        self._heartbeat_key = keys.heartbeat(der.id)
        self._fault_key = keys.fault(self.agent_id)
        rt = config.runtime
        self.params = PT1DelayParams.from_der(der)
        self.state = PT1DelayState.steady(der.p_sched_w)
        self.sample_period_ns = ns(rt.measurement_period_s)
        self.heartbeat_period_ns = ns(rt.heartbeat_period_s)
        self.watchdog_ns = ns(rt.watchdog_timeout_s)
        # scheduled changes of availability and of the ICT fault state: (t_ns, new value)
        changes = [(ns(c.t_s), c.available) for c in config.scenario.availability
                   if der.id in c.ders]
        self._availability = sorted(changes, key=lambda c: c[0])
        offline = []
        for fault in config.runtime.faults.der_offline:
            if fault.der == der.id:
                offline += [(ns(fault.t_s), True), (ns(fault.t_s + fault.duration_s), False)]
        self._offline_changes = sorted(offline, key=lambda c: c[0])
        self.available = True
        self.offline = False
        self.next_sample_ns = 0
        self.next_heartbeat_ns = 0
        self.watchdog_deadline_ns = self.watchdog_ns
        self.watchdog_expired = False
        self.weight = 0.0
        self.entry: int | None = None
        self.p_y = 0.0
        self.setpoint_w = der.p_sched_w
        self.mode = "control"
        self.counts = {"commands": 0, "stale_commands": 0, "dropped_offline": 0,
                       "watchdog_trips": 0}
        self._plan()

    # -- agent interface -----------------------------------------------------------------------

    def next_timer_ns(self) -> int:
        return self._next_timer_ns

    def _plan(self) -> None:
        """Recompute the next timer (after every change of the state it depends on)."""
        t = min(self.next_sample_ns, self.next_heartbeat_ns)
        if not self.watchdog_expired and self.watchdog_deadline_ns < t:
            t = self.watchdog_deadline_ns
        if self._availability and self._availability[0][0] < t:
            t = self._availability[0][0]
        if self._offline_changes and self._offline_changes[0][0] < t:
            t = self._offline_changes[0][0]
        self._next_timer_ns = t

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.type != "p_y":
            return []
        counts = self.counts
        if self.offline:
            counts["dropped_offline"] += 1
            return []
        if message.w is not UNSET:
            self.weight = float(message.w.get(self.der.id, 0.0))
            self.entry = message.entry
        if message.entry != self.entry:
            counts["stale_commands"] += 1
            return []
        counts["commands"] += 1
        self.p_y = message.p_y
        self.watchdog_deadline_ns = t_ns + self.watchdog_ns
        self.watchdog_expired = False
        self._update_setpoint(t_ns)
        self._plan()
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out: list[Outgoing] = []
        heartbeat_now = False
        while self._availability and self._availability[0][0] <= t_ns:
            available = self._availability.pop(0)[1]
            heartbeat_now |= available != self.available
            self.available = available
        setpoint_inputs_changed = heartbeat_now   # availability changed
        while self._offline_changes and self._offline_changes[0][0] <= t_ns:
            offline = self._offline_changes.pop(0)[1]
            if offline != self.offline:
                self.offline = offline
                heartbeat_now |= not offline
                out.append(Outgoing(self._fault_key, {"fault": "der_offline",
                                                      "agent": self.agent_id,
                                                      "active": offline}))
        if not self.watchdog_expired and t_ns >= self.watchdog_deadline_ns:
            self.watchdog_expired = True
            self.counts["watchdog_trips"] += 1
            setpoint_inputs_changed = True
        if setpoint_inputs_changed:   # else on_message has set it from the same inputs
            self._update_setpoint(t_ns)
        if t_ns == self.next_sample_ns:
            p_w = infeed_at(self.params, self.state, t_ns)
            out.append(Outgoing(self._state_key, {"p_w": p_w, "setpoint_w": self.setpoint_w,
                                                  "mode": self.mode}))
            self.next_sample_ns += self.sample_period_ns
        if t_ns == self.next_heartbeat_ns:
            heartbeat_now = True
            self.next_heartbeat_ns += self.heartbeat_period_ns
        if heartbeat_now and not self.offline:
            out.append(Outgoing(self._heartbeat_key, {"available": self.available}))
        self._plan()
        return out

    def stats(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.counts.items()}

    # -- internals -----------------------------------------------------------------------------

    def _update_setpoint(self, t_ns: int) -> None:
        der = self.der
        if not self.available:
            setpoint, mode = der.p_sched_w, "schedule"
        elif self.watchdog_expired:
            setpoint, mode = der.p_sched_w, "watchdog"
        else:
            setpoint = self.p_y * self.weight * der.p_inst_w + der.p_sched_w
            setpoint = min(max(setpoint, 0.0), der.p_inst_w)
            mode = "control"
        self.mode = mode
        if setpoint != self.setpoint_w:
            self.setpoint_w = setpoint
            set_point(self.params, self.state, t_ns, setpoint)
