"""The measurement at the interconnection point, as a bus-free state machine.

Every ``measurement_period_s`` it samples ``P_IP`` from the DER infeeds reported at the same
instant (the DERs report at the same sampling times, over the lossless zero-delay ``physical``
path, and the runtime delivers them before the sampling timer of that instant) and sends it to
the CPFC on ``measurement/p_ip`` over the ``measurement_to_cpfc`` link (delay ``T_meas``):

- with the config's ``grid_model``: the AC power flow of the SimBench grid at the study case,
  the DERs' sgens at their infeeds (:mod:`adnmesh.grid`, warm-started from the last sample):
  P_IP and Q_IP are the slack's exchange, MV → HV positive. A power flow that does not converge
  leaves the last values and is counted. Every ``grid_model.report_period_s`` it sends the
  grid's extremes over the period on ``measurement/grid`` (lowest and highest bus voltage,
  highest line and transformer loading, the samples outside ``grid_model.limits``);
- without it: ``P_IP = runtime.rest_of_grid_w + Σ_d P_d``.

As a level of a hierarchy of ADNs (docs/hierarchy.md) it also sends each sample's P_IP at once,
over the ``physical`` path, on ``measurement/exchange``: the ADN's exchange with the level above,
for its site agent.

With reactive power control (the config's ``reactive``) the DERs' reactive infeeds enter the
power flow as their sgens' ``q_mvar`` (without a grid model ``Q_IP = reactive.rest_of_grid_var +
Σ_d Q_d``), every ``p_ip`` carries Q_IP, and ``q_held`` says when every DER following Q_Y is
held back by its capability in one direction (the Q loop's anti-windup).

**A DER that stops reporting** (its process died, or ``up`` quarantined it) is taken at its
schedule ``P_sched,d`` once its state has been missing for ``watchdog_timeout_s``: a plant that
lost its controller falls back to its schedule as its watchdog does when commands stop, and a
restarted DER begins there too. Until then its last reported infeed stands. Holding the last
infeed for good would leave the dead DER's share of the last ``P_Y`` in ``P_IP`` for the rest of
the run, an offset the remaining DERs may be unable to take back (the reference scenario with
SGen1 dead from 60 s: the 420 s step ended 165 kW short). The DER also leaves the limit states
(``held``) the CPFC's anti-windup reads. The measurement says so with an event
(``der_silent``; ``der_reporting`` when its states return, a restarted DER).
"""

from __future__ import annotations

import math

from msgspec import UNSET

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.grid_side import GridSide
from adnmesh.control.operating_point import grid_solver, initial_p_ip_w, initial_q_ip_var
from adnmesh.names import der_agent_id, der_id_of
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["Measurement"]


class Measurement(Agent):
    """Samples ``P_IP`` (agent id ``measurement``; see the module docstring)."""

    agent_id = "measurement"

    def __init__(self, config: Config, exchange: bool = False) -> None:
        keys = Keys(config.grid)
        self._p_ip_key, self._grid_key = keys.of("p_ip"), keys.of("grid_state")
        # a level of a hierarchy of ADNs: each P_IP also goes, at once, to the site agent
        self._exchange_key = keys.of("adn_exchange") if exchange else None
        self._event_key = keys.of("event", self.agent_id)
        self.period_ns = ns(config.runtime.measurement_period_s)
        self.rest_of_grid_w = config.runtime.rest_of_grid_w
        # infeed per DER agent, in config order (fixed summation order: reproducible sums)
        self.infeed_w = {der_agent_id(d.id): d.p_sched_w for d in config.ders}
        self.held: dict[str, int] = {}          # DERs that follow P_Y: their limit state
        self.q_held: dict[str, int] = {}        # DERs that follow Q_Y: their limit state
        self.reactive = config.reactive is not None
        self.q_sched_var = {der_agent_id(d.id): d.q_sched_var for d in config.ders}
        self.infeed_var = dict(self.q_sched_var)
        self.rest_of_grid_var = 0.0 if config.reactive is None else \
            config.reactive.rest_of_grid_var
        self.p_sched_w = {der_agent_id(d.id): d.p_sched_w for d in config.ders}
        self.silent_after_ns = ns(config.runtime.watchdog_timeout_s)
        self.last_state_ns = dict.fromkeys(self.infeed_w, 0)   # when each DER last reported
        self.silent: set[str] = set()           # DERs taken at their schedule (not reporting)
        self._back: set[str] = set()            # silent DERs that reported again
        self._order = {der: i for i, der in enumerate(self.infeed_w)}
        self._next_check_ns = self.silent_after_ns   # no DER can fall silent before this
        self.next_sample_ns = 0
        self.solver = grid_solver(config)
        self.p_ip_w = self.q_ip_var = 0.0
        if self.solver is not None:     # the operating point, should the first flow fail
            self.p_ip_w = initial_p_ip_w(config)
            self.q_ip_var = initial_q_ip_var(config)
        self.grid = None
        if self.solver is not None:
            self.grid = GridSide(config, self.solver)
            self._guard_key = keys.of("grid_guard")
            self.report_period_ns = ns(config.grid_model.report_period_s)
            self.next_report_ns = self.report_period_ns
        self.counts = {"samples": 0, "not_converged": 0}

    def next_timer_ns(self) -> int:
        return self.next_sample_ns

    def resume(self, t_ns: int) -> None:
        """A restarted measurement at ``t_ns``: samples from the next sampling instant on."""
        self.next_sample_ns = -(-t_ns // self.period_ns) * self.period_ns
        self.last_state_ns = dict.fromkeys(self.infeed_w, t_ns)
        self._next_check_ns = t_ns + self.silent_after_ns
        if self.solver is not None:
            self.next_report_ns = -(-t_ns // self.report_period_ns) * self.report_period_ns

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.src in self.infeed_w:
            self.infeed_w[message.src] = message.p_w
            self.last_state_ns[message.src] = t_ns
            if message.src in self.silent:
                self._back.add(message.src)
                self._next_check_ns = min(self._next_check_ns, t_ns + self.silent_after_ns)
            if message.held is UNSET:
                self.held.pop(message.src, None)
            else:
                self.held[message.src] = message.held
            if self.reactive:
                if message.q_var is not UNSET:
                    self.infeed_var[message.src] = message.q_var
                if message.q_held is UNSET:
                    self.q_held.pop(message.src, None)
                else:
                    self.q_held[message.src] = message.q_held
        return []

    def _held(self) -> dict:
        """``{"held": "up"|"down"}`` when every DER that follows P_Y is held that way (and
        ``q_held`` the same for Q_Y)."""
        found = {}
        for field, held in (("held", self.held), ("q_held", self.q_held)):
            states = set(held.values())
            if states == {1}:
                found[field] = "up"
            elif states == {-1}:
                found[field] = "down"
        return found

    def _silent(self, t_ns: int) -> list[Outgoing]:
        """DERs whose state has been missing for ``watchdog_timeout_s`` go to their schedule;
        one that reports again is back (see the module docstring)."""
        out = []
        for der in sorted(self._back, key=self._order.__getitem__):
            self.silent.discard(der)
            out.append(Outgoing(self._event_key, {
                "level": "INFO", "kind": "der_reporting", "subject": der,
                "text": f"{der_id_of(der)} reports its state again"}))
        self._back.clear()
        if t_ns < self._next_check_ns:
            return out
        earliest = None
        for der, last in self.last_state_ns.items():
            if der in self.silent:
                continue
            if t_ns - last < self.silent_after_ns:
                earliest = last if earliest is None else min(earliest, last)
                continue
            self.silent.add(der)
            self.infeed_w[der] = self.p_sched_w[der]
            self.infeed_var[der] = self.q_sched_var[der]
            self.held.pop(der, None)
            self.q_held.pop(der, None)
            text = (f"{der_id_of(der)} sent no state for {self.silent_after_ns / 1e9:g} s: its "
                    f"infeed is taken at its schedule, {self.p_sched_w[der] / 1e3:.6g} kW")
            out.append(Outgoing(self._event_key, {"level": "WARNING", "kind": "der_silent",
                                                  "subject": der, "text": text}))
        self._next_check_ns = math.inf if earliest is None else earliest + self.silent_after_ns
        return out

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out = self._sample(t_ns)
        if self._exchange_key is not None:     # out[0] is the sample's p_ip
            body = out[0].body
            out.append(Outgoing(self._exchange_key, {"p_ip_w": body["p_ip_w"], **{
                k: body[k] for k in ("held",) if k in body}}))
        return out

    def _sample(self, t_ns: int) -> list[Outgoing]:
        self.next_sample_ns += self.period_ns
        self.counts["samples"] += 1
        events = self._silent(t_ns)
        if self.solver is None:
            p_ip = self.rest_of_grid_w
            for p_w in self.infeed_w.values():
                p_ip += p_w
            body = {"p_ip_w": p_ip, **self._held()}
            if self.reactive:
                q_ip = self.rest_of_grid_var
                for q_var in self.infeed_var.values():
                    q_ip += q_var
                body["q_ip_var"] = q_ip
            return [Outgoing(self._p_ip_key, body), *events]
        held = self._held()
        pressing = frozenset((quantity, 1 if way == "up" else -1)
                             for quantity, way in (("p", held.get("held")),
                                                   ("q", held.get("q_held"))) if way)
        sample, guard, grid_events = self.grid.sample(
            t_ns, list(self.infeed_w.values()),
            list(self.infeed_var.values()) if self.reactive else None, pressing)
        if sample.converged:
            self.p_ip_w, self.q_ip_var = float(sample.p_ip_w), float(sample.q_ip_var)
        else:
            self.counts["not_converged"] += 1
        out = [Outgoing(self._p_ip_key, {"p_ip_w": self.p_ip_w, "q_ip_var": self.q_ip_var,
                                         **held}), *events]
        if guard is not None:
            out.append(Outgoing(self._guard_key, guard))
        out += [Outgoing(self._event_key, event) for event in grid_events]
        if t_ns >= self.next_report_ns:
            report, again = self.grid.report_bodies(self.q_ip_var)
            out.append(Outgoing(self._grid_key, report))
            if again is not None and guard is None:
                out.append(Outgoing(self._guard_key, again))
            self.next_report_ns += self.report_period_ns
        return out

    def stats(self) -> dict[str, float]:
        out = {k: float(v) for k, v in self.counts.items()}
        if self.grid is not None:
            out.update({f"guard_{k}": float(v) for k, v in self.grid.guard.counts.items()})
            if self.grid.tap is not None:
                out["tap_moves"] = float(self.grid.tap.moves)
        return out
