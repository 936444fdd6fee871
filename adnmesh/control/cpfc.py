"""The CPFC: gain-scheduled PI control of ``P_IP`` (SPEC §1, §5), as a bus-free state machine.

Every ``pi_period_s`` the CPFC samples ``P_ref`` (from the scenario: the initial operating point
plus the steps so far) and the last ``P_IP`` delivered by the measurement, updates its PI
(:class:`~adnmesh.control.pi.SampledPI`) and sends ``P_Y`` to the DERs on ``cpfc/p_y``. When the
availability vector SI names a new set of available DERs, it switches at its next sample to the
table entry of that set without a bump (the output stays continuous) and sends the entry's weights
W with that ``P_Y``; it repeats W every ``weights_period_s`` so that a DER that missed them
recovers. Every ``P_Y`` carries the number of the entry in use (``entry``, counted from 0 per run):
a DER applies ``P_Y`` only with the weights of the same entry.

The output is limited to the range where at least one available DER is not saturated (its
setpoint ``P_Y w_d P_inst,d + P_sched,d`` inside ``[0, P_inst,d]``); the PI's anti-windup holds
the integrator beyond it.

Gains come from a :class:`GainSchedule`: the table entry of the subset, else an entry tuned on
demand (:func:`adnmesh.tuning.tune_subset`, when that module exists), else the table's static
controller with unit weights; if none exists the CPFC keeps its gains and says so in its stats.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.pi import SampledPI, SwitchRecord
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope, Switch
from adnmesh.wire.units import ns
from adnmesh.table import SchedulingTable, TableEntry

__all__ = ["CPFC", "GainSchedule", "SwitchEvent", "initial_p_ref_w", "output_limits"]


def initial_p_ref_w(config: Config) -> float:
    """``P_ref`` before the first step: the operating point with ``P_Y = 0``, W
    (``rest_of_grid_w`` plus every DER's schedule)."""
    return config.runtime.rest_of_grid_w + sum(d.p_sched_w for d in config.ders)


def output_limits(config: Config, weights: dict[str, float]) -> tuple[float, float]:
    """``(y_min, y_max)``: beyond them every weighted DER is saturated (dimensionless).

    A DER d saturates high at ``P_Y = (P_inst - P_sched) / (w_d P_inst)`` and low at
    ``P_Y = -P_sched / (w_d P_inst)``. Without a weighted DER both limits are NaN.
    """
    highs, lows = [], []
    for der in config.ders:
        w = weights.get(der.id, 0.0)
        if w > 0:
            highs.append((der.p_inst_w - der.p_sched_w) / (w * der.p_inst_w))
            lows.append(-der.p_sched_w / (w * der.p_inst_w))
    if not highs:
        return math.nan, math.nan
    return min(lows), max(highs)


class GainSchedule:
    """Resolves a set of available DERs to its gains and weights.

    Parameters
    ----------
    config : Config
    table : SchedulingTable or None
        The gain-scheduling table (None: only on-demand tuning).
    tune : callable, optional
        ``tune(config, der_ids) -> TableEntry``; default: :func:`adnmesh.tuning.tune_subset`
        if importable.
    on_demand : bool
        Tune missing subsets at all (False: table, then static controller).
    """

    def __init__(self, config: Config, table: SchedulingTable | None,
                 tune: Callable[[Config, list[str]], TableEntry] | None = None,
                 on_demand: bool = True) -> None:
        self.config = config
        self.table = table
        self._tune = tune
        self.on_demand = on_demand
        self._tuned: dict[frozenset, TableEntry] = {}
        self.sources: dict[str, int] = {}

    def lookup(self, available: frozenset[str]) -> tuple[TableEntry | None, str]:
        """Return ``(entry, source)``; source is ``table``, ``tuned``, ``static`` or ``none``."""
        if self.table is not None:
            entry = self.table.lookup(available)
            if entry is not None and entry.feasible:
                return self._count(entry, "table")
        if available in self._tuned:
            return self._count(self._tuned[available], "tuned")
        tune = None
        if self.on_demand:
            tune = self._tune if self._tune is not None else _tuner()
        if tune is not None and available:
            ids = [d for d in self.config.der_ids() if d in available]
            entry = tune(self.config, ids)
            self._tuned[available] = entry
            return self._count(entry, "tuned")
        if self.table is not None and self.table.static is not None and available:
            static = self.table.static
            ids = tuple(d for d in self.config.der_ids() if d in available)
            return self._count(TableEntry(ids, static.kp, static.ki, dict.fromkeys(ids, 1.0)),
                               "static")
        return self._count(None, "none")

    def _count(self, entry, source):
        self.sources[source] = self.sources.get(source, 0) + 1
        return entry, source


def _tuner():
    try:
        from adnmesh.tuning import tune_subset
    except ImportError:
        return None
    return tune_subset


@dataclass(frozen=True)
class SwitchEvent:
    """A gain switch: when, to which set, how, and the output before and after (equal)."""

    t_ns: int
    available: tuple[str, ...]
    source: str
    record: SwitchRecord


class CPFC(Agent):
    """The CPFC state machine (agent id ``cpfc``; see the module docstring).

    Parameters
    ----------
    config : Config
    schedule : GainSchedule
        Must resolve the set of all DERs (available at t = 0).
    """

    agent_id = "cpfc"

    def __init__(self, config: Config, schedule: GainSchedule) -> None:
        self.config = config
        self.keys = Keys(config.grid)
        rt = config.runtime
        self.schedule = schedule
        self.period_ns = ns(rt.pi_period_s)
        self.weights_period_ns = ns(rt.weights_period_s)
        self.p_ref_w = initial_p_ref_w(config)
        self.p_meas_w = self.p_ref_w          # the run starts in the operating point
        self._steps = [(ns(s.t_s), s.delta_w) for s in config.scenario.p_ref_steps]
        self._next_step = 0
        self._ids = config.der_ids()
        self.available = frozenset(self._ids)
        self._pending: frozenset[str] | None = None
        entry, source = schedule.lookup(self.available)
        if entry is None:
            raise ValueError("no gains for the set of all DERs (table and tuning unavailable)")
        self.entry = entry
        self.entry_index = 0
        self.weights = self._weights(entry, self.available)
        self.pi = SampledPI(entry.kp, entry.ki, rt.pi_period_s)
        self.pi.set_limits(*self._limits())
        self.next_sample_ns = 0
        self._next_weights_ns = 0
        self._p_ref_sent: float | None = None
        self.switches: list[SwitchEvent] = []
        self.counts: dict[str, int] = {"samples": 0, "no_gains": 0, "rejected_si": 0}

    # -- agent interface -----------------------------------------------------------------------

    def next_timer_ns(self) -> int:
        return self.next_sample_ns

    def stats(self) -> dict[str, float]:
        return {**{k: float(v) for k, v in self.counts.items()},
                **{f"gains_{k}": float(v) for k, v in self.schedule.sources.items()}}

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.type == "p_ip":
            self.p_meas_w = message.p_ip_w
        elif message.type == "si":
            si = message.si
            if not set(si) <= set(self._ids):
                self.counts["rejected_si"] += 1
                return []
            available = frozenset(d for d in self._ids if si.get(d, False))
            self._pending = None if available == self.available else available
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out = []
        while self._next_step < len(self._steps) and self._steps[self._next_step][0] <= t_ns:
            self.p_ref_w += self._steps[self._next_step][1]
            self._next_step += 1
        if self.p_ref_w != self._p_ref_sent:
            out.append(Outgoing(self.keys.p_ref, {"p_ref_w": self.p_ref_w}))
            self._p_ref_sent = self.p_ref_w
        error_w = self.p_ref_w - self.p_meas_w
        p_y = self.pi.update(error_w)
        body = {"p_y": p_y, "p_ref_w": self.p_ref_w, "kp": self.pi.kp, "ki": self.pi.ki}
        if self._pending is not None:
            record = self._switch(t_ns, self._pending)
            self._pending = None
            if record is not None:
                body.update(p_y=record.p_y_after, kp=self.pi.kp, ki=self.pi.ki,
                            switch=Switch(record.p_y_before, record.p_y_limited,
                                          record.kp_before, record.ki_before))
                self._next_weights_ns = t_ns
        body["entry"] = self.entry_index
        if t_ns >= self._next_weights_ns:
            body["w"] = dict(self.weights)
            self._next_weights_ns = t_ns + self.weights_period_ns
        out.append(Outgoing(self.keys.p_y, body))
        self.counts["samples"] += 1
        self.next_sample_ns += self.period_ns
        return out

    # -- internals -----------------------------------------------------------------------------

    def _switch(self, t_ns: int, available: frozenset[str]) -> SwitchRecord | None:
        self.available = available
        entry, source = self.schedule.lookup(available) if available else (None, "none")
        if entry is None:
            # no actuators or no gains: keep the gains, hold the output where it is
            self.counts["no_gains"] += 1
            self.weights = self._weights(self.entry, available)
            if not self.weights:
                self.pi.set_limits(self.pi.output, self.pi.output)
            return None
        self.entry = entry
        self.entry_index += 1
        self.weights = self._weights(entry, available)
        self.pi.set_limits(*self._limits())
        record = self.pi.switch(entry.kp, entry.ki)
        self.switches.append(SwitchEvent(t_ns, tuple(d for d in self._ids if d in available),
                                         source, record))
        return record

    def _weights(self, entry: TableEntry, available: frozenset[str]) -> dict[str, float]:
        return {d: float(entry.w.get(d, 1.0)) for d in self._ids
                if d in available and d in entry.ders}

    def _limits(self) -> tuple[float, float]:
        low, high = output_limits(self.config, self.weights)
        if math.isnan(low):  # no weighted DER: hold the output
            return self.pi.output, self.pi.output
        return low, high
