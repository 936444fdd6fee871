"""The local controller of one DER (docs/method.md#control-structure, Eq. 1), as a bus-free state
machine.

The controller turns the CPFC's ``P_Y`` into the DER's setpoint

    P_ref,d = P_Y · w_d · C_d + P_sched,d,        C_d = P_inst,d,

limited to ``[0, P_avail,d]`` (the DER's available power: its sgen's at the grid model's study
case, else ``P_inst,d``), and drives the DER's dynamics with it: the reference PT1 or the
detailed model of its type (``runtime.der_models``, :mod:`adnmesh.control.der_model`). Its mode
says where the setpoint comes from:

``control``
    available and in contact: Eq. 1 with the weight ``w_d`` of the CPFC's current entry (0 if the
    entry does not use the DER);
``schedule``
    unavailable (scenario ``availability``): the DER leaves the control and runs at
    ``P_sched,d``;
``watchdog``
    no valid command for ``watchdog_timeout_s``: back to ``P_sched,d`` until commands return.

A ``P_Y`` is valid if its ``entry`` matches the entry whose weights the DER holds (weights come
with the switch and are repeated periodically). A switch that gives a handover time
(``handover_s``, docs/method.md#returning-ders-handover) does not move the DER's setpoint at
once: it keeps the power it was commanded and moves to its share of the new entry linearly in
that time, following every change of P_Y with the new weight at once. A DER the switch names
in ``keep`` (left out by the grid guard) keeps that power until the next switch. Every ``measurement_period_s`` the DER reports its
infeed and setpoint on ``der/<id>/state`` (exact at that instant); every ``heartbeat_period_s``,
and at once when its availability or its mode changes, it sends a heartbeat with its
availability flag, its mode and the last P_Y it applied with that command's entry: the
availability monitor counts a DER in ``watchdog`` as unavailable, and a restarted CPFC resumes
from the acknowledged P_Y (docs/method.md#watchdog-and-holds), so that the DERs return to their
setpoints before the fault. A watchdog fallback is also an event (``event/der/<id>``).
Injected ICT faults are the node's business (:mod:`adnmesh.sim.node`): the DER only notices that
commands stop.

**Reactive power** (the config's ``reactive`` section; docs/method.md#reactive-power): the DER
also follows the CPFC's ``Q_Y`` on ``cpfc/q_y`` with the weights of the Q table's entry,
``Q_ref,d = Q_Y · w_d^Q · C_d^Q + Q_sched,d``, and both setpoints are limited together by its
P-Q capability (:func:`adnmesh.reactive.limit_pq`: its reactive range and apparent power, the
config's priority when S binds). Its reactive power follows the reference PT1 behind a dead
time with its reactive dynamics (``t_delay_q_s``, ``t_rise_q_s``). It reports Q with its state,
``q_held`` when the capability holds its reactive setpoint back, and the last Q_Y it applied
with its heartbeat. Outside ``control`` mode (unavailable, watchdog) it runs at ``Q_sched,d``;
one watchdog serves both loops, whose commands come from the one CPFC over the same link. A
switch of the Q table moves the DERs' reactive shares at once (Q is fast; no handover).

**A plant device** (``device``, the config's ``plant:``; :mod:`adnmesh.control.plant_device`):
the controller hands every new set-point pair to the device and reports the device's last
measured P (and Q). Whether the plant is held by a rate or range limit (``held``, for the
CPFC's anti-windup) is said by neither protocol: it comes from the DER's model, which the
controller keeps running on the same set-points (without it, the CPFC's integrator wound up
while the CHPs ramped: 7.3 % overshoot at the reference case's 200 s step against 2.0 %),
unless the device says it itself (``DeviceStatus.held``: an ADN as a DER of the level above). A
device that is not healthy (unreachable, silent, refusing set-points, a stale measurement, not
connected to the grid) makes the DER unavailable, as a scenario availability change would
(heartbeat at once, the schedule as set-point, the CPFC switches), until it is healthy again;
each change is an event (``device_lost`` with the reason, ``device_back``). The controller
looks at the device at each of its timers.
"""

from __future__ import annotations

from msgspec import UNSET

from adnmesh.config import DER, Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.der_model import der_params, usable_available_w
from adnmesh.control.plant_device import PlantDevice
from adnmesh.dermodels import infeed_at, reference_pt1, set_point, steady_state
from adnmesh.dermodels.limits import infeed_and_held
from adnmesh.reactive import capability_of, limit_pq, q_dynamics
from adnmesh.names import der_agent_id
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["DERController"]


def _first_at_or_after(t_ns: int, period_ns: int) -> int:
    return -(-t_ns // period_ns) * period_ns


class DERController(Agent):
    """Local controller of DER ``der`` (agent id ``der/<id>``; see the module docstring)."""

    def __init__(self, der: DER, config: Config, p_avail_w: float | None = None,
                 params=None, device: PlantDevice | None = None,
                 watchdog_holds: bool = False) -> None:
        self.der = der
        # the watchdog keeps the last setpoint instead of the schedule, and so does a command
        # without a weight for it after the watchdog, until a weight comes (an ADN as a DER of
        # the level above: cut off from it, it runs on its last reference; adn_site.py)
        self.watchdog_holds = watchdog_holds
        self._holding = False
        self.p_avail_w = usable_available_w(der, p_avail_w)
        self.agent_id = der_agent_id(der.id)
        keys = Keys(config.grid)
        self._state_key = keys.of("der_state", der.id)
        self._heartbeat_key = keys.of("heartbeat", der.id)
        self._event_key = keys.of("event", self.agent_id)
        rt = config.runtime
        self.params = der_params(der, config, self.p_avail_w) if params is None else params
        self.state = steady_state(self.params, der.p_sched_w)
        self.sample_period_ns = ns(rt.measurement_period_s)
        self.heartbeat_period_ns = ns(rt.heartbeat_period_s)
        self.watchdog_ns = ns(rt.watchdog_timeout_s)
        # scheduled changes of availability: (t_ns, new value)
        changes = [(ns(c.t_s), c.available) for c in config.scenario.availability
                   if der.id in c.ders]
        self._availability = sorted(changes, key=lambda c: c[0])
        self.available = True
        self._scheduled = True           # available by the scenario
        self.device = device
        self._device_ok = True
        self._last_device = None         # the device's status at the last look (no device: None)
        self.next_sample_ns = 0
        self.next_heartbeat_ns = 0
        self.watchdog_deadline_ns = self.watchdog_ns
        self.watchdog_expired = False
        self.weight = 0.0
        self.entry: int | None = None
        self.p_y = 0.0
        self.setpoint_w = der.p_sched_w
        self.mode = "control"
        self._inputs = (True, False)     # (available, watchdog expired) of the setpoint
        self._clamped = 0                # +1 / -1: the setpoint is at its upper / lower limit
        self._handover: tuple[int, int, float] | None = None   # (start, duration ns, offset W)
        self._q_changed = False          # the reactive setpoint changed (for the device)
        self.counts = {"commands": 0, "stale_commands": 0, "watchdog_trips": 0}
        if device is not None:
            self.counts.update(device_lost=0, device_back=0)
            self._last_device = device.status()      # healthy until the first look says not
        self.reactive = config.reactive
        if self.reactive is not None:
            self.capability = capability_of(der, self.reactive)
            delay, rise = q_dynamics(der)
            self.q_params = reference_pt1(self.capability.capacity_var or 1.0, delay,
                                          rise / config.rise_per_lag)
            self.q_state = steady_state(self.q_params, der.q_sched_var)
            self.q_weight, self.q_entry, self.q_y = 0.0, None, 0.0
            self.q_setpoint_var = der.q_sched_var
            self._q_clamped = 0
            self._q_kept_var = 0.0          # reactive power the grid guard keeps, var
            self.counts.update(q_commands=0, q_stale_commands=0)
        self._command_device()
        self._plan()

    # -- agent interface -----------------------------------------------------------------------

    def next_timer_ns(self) -> int:
        return self._next_timer_ns

    def resume(self, t_ns: int) -> None:
        """A restarted controller at ``t_ns``: the plant at its schedule, no command yet."""
        while self._availability and self._availability[0][0] < t_ns:
            self._scheduled = self._availability.pop(0)[1]
        self.available = self._scheduled and self._device_ok
        self.state = steady_state(self.params, self.der.p_sched_w, t_ns)
        if self.reactive is not None:
            self.q_state = steady_state(self.q_params, self.der.q_sched_var, t_ns)
        self.next_sample_ns = _first_at_or_after(t_ns, self.sample_period_ns)
        self.next_heartbeat_ns = t_ns
        self.watchdog_deadline_ns = t_ns + self.watchdog_ns
        self.mode = "control" if self.available else "schedule"
        self._command_device()
        self._plan()

    def _plan(self) -> None:
        """Recompute the next timer (after every change of the state it depends on)."""
        t = min(self.next_sample_ns, self.next_heartbeat_ns)
        if not self.watchdog_expired and self.watchdog_deadline_ns < t:
            t = self.watchdog_deadline_ns
        if self._availability and self._availability[0][0] < t:
            t = self._availability[0][0]
        self._next_timer_ns = t

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.type == "q_y" and self.reactive is not None:
            self._on_q_y(t_ns, message)
            return []
        if message.type != "p_y":
            return []
        counts = self.counts
        if message.w is not UNSET:
            if message.entry != self.entry:
                self._hand_over(t_ns, message)
            self.weight = float(message.w.get(self.der.id, 0.0))
            self.entry = message.entry
        if message.entry != self.entry:
            counts["stale_commands"] += 1
            return []
        counts["commands"] += 1
        self.p_y = message.p_y
        self.watchdog_deadline_ns = t_ns + self.watchdog_ns
        self.watchdog_expired = False
        mode = self.mode
        self._update_setpoint(t_ns)
        self._plan()
        if self.mode != mode:      # back from the watchdog: say so at once
            self.next_heartbeat_ns = t_ns
            self._plan()
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out: list[Outgoing] = []
        mode, available = self.mode, self.available
        while self._availability and self._availability[0][0] <= t_ns:
            self._scheduled = self._availability.pop(0)[1]
        if self.device is not None:
            self._look_at_device(out)
        self.available = self._scheduled and self._device_ok
        if not self.watchdog_expired and t_ns >= self.watchdog_deadline_ns:
            self.watchdog_expired = True
            self.counts["watchdog_trips"] += 1
        if self.watchdog_expired and mode == "control" and self.available:
            out.append(Outgoing(self._event_key, {
                "level": "WARNING", "kind": "watchdog_fallback", "subject": self.agent_id,
                "text": f"{self.der.id}: no valid command for "
                        f"{self.watchdog_ns / 1e9:g} s, " + (
                            "holding its last set-point" if self.watchdog_holds
                            else "back to its schedule")}))
        if (self.available, self.watchdog_expired) != self._inputs:
            self._update_setpoint(t_ns)   # else on_message has set it from the same inputs
        if t_ns == self.next_sample_ns:
            device = self._last_device
            # the model runs beside a device too (it gives the hold flag): advancing it
            # here also consumes its queue of set-point changes, which would otherwise grow
            p_w, held = infeed_and_held(self.params, self.state, t_ns)
            if device is not None:
                p_w = self.der.p_sched_w if device.p_w is None else min(max(device.p_w, 0.0),
                                                                        self.der.p_inst_w)
            state = {"p_w": p_w, "setpoint_w": self.setpoint_w, "mode": self.mode}
            if self.mode == "control" and self.weight > 0:   # a device's by its model (below)
                said = None if device is None else device.held
                state["held"] = self._clamped or (held if said is None else said)
            if self.reactive is not None:
                q_var = infeed_at(self.q_params, self.q_state, t_ns)
                if device is not None:
                    q_var = device.q_var if device.q_var is not None else self.der.q_sched_var
                state["q_var"] = q_var
                state["q_setpoint_var"] = self.q_setpoint_var
                if self.mode == "control" and self.q_weight > 0:
                    state["q_held"] = self._q_clamped
            out.append(Outgoing(self._state_key, state))
            self.next_sample_ns += self.sample_period_ns
        if t_ns >= self.next_heartbeat_ns or self.mode != mode or self.available != available:
            out.append(Outgoing(self._heartbeat_key, self._heartbeat()))
            self.next_heartbeat_ns = _first_at_or_after(t_ns + 1, self.heartbeat_period_ns)
        self._plan()
        return out

    def stats(self) -> dict[str, float]:
        stats = {k: float(v) for k, v in self.counts.items()}
        if self.device is not None:
            stats.update(self.device.stats())
        return stats

    # -- internals -----------------------------------------------------------------------------

    def _command_device(self) -> None:
        """Hand the set-points to the device, if the plant is one."""
        if self.device is not None:
            self.device.command(self.setpoint_w, None if self.reactive is None else
                                self.q_setpoint_var)

    def _look_at_device(self, out: list[Outgoing]) -> None:
        """Take the device's status; a change of health is an event."""
        status = self._last_device = self.device.status()
        if status.ok == self._device_ok:
            return
        self._device_ok = status.ok
        self.counts["device_lost" if not status.ok else "device_back"] += 1
        text = (f"{self.der.id}: device back" if status.ok else
                f"{self.der.id}: device {status.reason}: {status.detail}; the DER is "
                "unavailable until it is back")
        out.append(Outgoing(self._event_key, {
            "level": "INFO" if status.ok else "WARNING",
            "kind": "device_back" if status.ok else "device_lost",
            "subject": self.agent_id, "text": text[:500]}))

    def _heartbeat(self) -> dict:
        beat = {"available": self.available, "mode": self.mode, "p_y": self.p_y,
                "entry": self.entry}
        if self.reactive is not None:
            beat["q_y"] = self.q_y
        return beat

    def _on_q_y(self, t_ns: int, message) -> None:
        """A Q_Y command: its weights (on a switch and repeated), then Q_Y if of that entry."""
        if message.w is not UNSET:
            if message.entry != self.q_entry:          # a switch: kept by the guard?
                switch = message.switch
                keep = (switch is not UNSET and switch.keep is not UNSET
                        and self.der.id in switch.keep)
                self._q_kept_var = (self.q_setpoint_var - self.der.q_sched_var) if keep else 0.0
            self.q_weight = float(message.w.get(self.der.id, 0.0))
            self.q_entry = message.entry
        if message.entry != self.q_entry:
            self.counts["q_stale_commands"] += 1
            return
        self.counts["q_commands"] += 1
        self.q_y = message.q_y
        if self.mode == "control":
            self._update_setpoint(t_ns)

    def _hand_over(self, t_ns: int, message) -> None:
        """A command of a new entry with a switch record that gives a handover time: the DER
        keeps the power it was commanded and moves to its share of the new entry in that time
        (docs/method.md#returning-ders-handover); else it takes its share at once.

        The offset is the DER's setpoint above its schedule less its share by the new weight
        of the P_Y it last applied, scaled as the switch scaled it (``switch.scale``), both
        limited: what the switch moves between DERs. The change of P_Y of the switching
        sample itself is followed with the new weight at once. A switch without a handover
        time moves no DER's power (the CPFC found none to move): a handover still running
        goes on, or the DER would jump by what it has yet to hand over."""
        switch = message.switch
        if switch is UNSET or not self.available:
            self._handover = None
            return
        der = self.der
        keep = switch.keep is not UNSET and der.id in switch.keep
        if switch.handover_s is UNSET and not keep:
            return        # the switch moves no DER's power: a running handover goes on
        self._handover = None
        weight = float(message.w.get(der.id, 0.0))
        share_w = min(max(self.p_y * switch.scale * weight * der.p_inst_w + der.p_sched_w, 0.0),
                      self.p_avail_w)
        offset_w = self.setpoint_w - share_w
        if offset_w != 0.0:        # kept by the grid guard: for good, until the next switch
            self._handover = (t_ns, None if keep else ns(switch.handover_s), offset_w)

    def _handover_offset_w(self, t_ns: int) -> float:
        """What the running handover adds to Eq. 1 at ``t_ns``, W (0 once it is over)."""
        start_ns, duration_ns, offset_w = self._handover
        if duration_ns is None:
            return offset_w
        left = 1.0 - (t_ns - start_ns) / duration_ns
        if left <= 0.0:
            self._handover = None
            return 0.0
        return offset_w * left

    def _update_setpoint(self, t_ns: int) -> None:
        der = self.der
        self._inputs = (self.available, self.watchdog_expired)
        if not self.available:
            setpoint, mode = der.p_sched_w, "schedule"
            self._handover = None            # it belongs to the control it interrupts
        elif self.watchdog_expired:
            self._holding = self.watchdog_holds
            setpoint = self.setpoint_w if self._holding else der.p_sched_w
            mode = "watchdog"
            self._handover = None
        elif self._holding and self.weight == 0:
            setpoint, mode = self.setpoint_w, "control"
        else:
            self._holding = False
            wanted = self.p_y * self.weight * der.p_inst_w + der.p_sched_w
            if self._handover is not None:
                wanted += self._handover_offset_w(t_ns)
            setpoint = min(max(wanted, 0.0), self.p_avail_w)
            self._clamped = (wanted > setpoint) - (wanted < setpoint)
            mode = "control"
        self.mode = mode
        if self.reactive is not None:
            setpoint = self._limit_pq(t_ns, setpoint, mode == "control")
        changed = setpoint != self.setpoint_w
        if changed:
            self.setpoint_w = setpoint
            set_point(self.params, self.state, t_ns, setpoint)
        if changed or self._q_changed:
            self._command_device()
        self._q_changed = False

    def _limit_pq(self, t_ns: int, p_setpoint_w: float, control: bool) -> float:
        """Set the reactive setpoint (Eq. 1 for Q in control, else the schedule) and limit it
        with ``p_setpoint_w`` by the capability; return the active setpoint, W."""
        der = self.der
        wanted = (self.q_y * self.q_weight * self.capability.capacity_var + der.q_sched_var
                  + self._q_kept_var
                  if control else der.q_sched_var)
        p, q, p_held, q_held = limit_pq(self.capability, p_setpoint_w, wanted, self.p_avail_w,
                                        self.reactive.priority)
        if control:
            self._q_clamped = q_held
            self._clamped = self._clamped or p_held
        if q != self.q_setpoint_var:
            self.q_setpoint_var = q
            set_point(self.q_params, self.q_state, t_ns, q)
            self._q_changed = True
        return p
