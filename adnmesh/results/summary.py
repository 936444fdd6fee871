"""The end-of-run summary, computed by pure functions from the recorded time series.

For every step of ``P_ref`` (the CPFC's ``scenario/p_ref`` records) the response of ``P_IP``
(the measurement's samples, at their sampling instants) until the next event (step, gain switch,
a DER's availability change, an injected fault) or the end: rise time (10-90 %), settling time
in ``band_pct`` % and in 2 % of the step, overshoot, peak, and the steady error ``P_ref - P_IP``
at the window's last sample, W. The figures and the windows are those of
:func:`adnmesh.loopmodel.step_figures.reference_step_figures`, the rule ``adnmesh inspect`` applies to the
recording too (:mod:`adnmesh.results.figures`), so both print the same figures.

The events that end a window are those of the one rule ``inspect`` applies too,
:class:`adnmesh.results.rules.StepWindowEnds`, found in the messages by the event rules of
:mod:`adnmesh.results.rules` (:class:`RunSeries`): a ``p_y`` message with a ``switch`` record,
a DER heartbeat whose ``available`` flag differs from the DER's previous one (every DER
counts as available before its first heartbeat), an SI message whose set of available DERs
differs from the previous SI's (the first SI is the initial state), a fault's start and end.

**Every step of the scenario** (``planned_steps``, the config's): whether and when it was
executed (a ``p_ref`` record at or after it: within one sample, ``sample_s``, it is on time;
later, a restarted CPFC applied it with the steps it missed) and, if not on time, why: the
CPFC, which sends ``P_ref``, was dead then (an injected kill or an agent ``up`` lost, until it
rejoined), or the run ended before it. A step that left no record is otherwise missing from the
step figures without a word.

For every gain switch (``cpfc/p_y`` messages with a ``switch`` record): the largest
``|P_IP - P_ref|`` in the ``window_s`` (10 s) after it and the DERs' handover
(docs/method.md#returning-ders-handover; until the next step of P_ref, whose response it is
not), the factor the switch scaled ``P_Y``
by (so that the DERs' commanded power stayed continuous; 1 when no DER returned) and the jump of
``P_Y`` (output with the new gains minus the scaled old output; 0 when the switch is bumpless).
Each step against what its table entry was certified for: :mod:`adnmesh.results.design_check`.
A scaled output outside the new DERs' range (where every one of them is saturated) is limited
to that range first; the jump is counted from the limited value and the limiting reported
apart (``p_y_limited_by``).

For every injected fault (``fault`` messages) and every agent ``up`` lost (an ``agent_lost``
event of ``up``: a process that died or stopped unplanned, fault kind ``lost`` from that event
to the agent's ``rejoined`` event, if any) its detection, deviation and recovery
(:func:`adnmesh.results.fault_figures.fault_figures`, from the run's ``event`` messages); with a grid
model the extremes of the grid over the run and the report periods with samples outside the
band (``grid_state`` messages); of a realtime run its timing: delivery errors per link,
overruns, alarms the machine's lateness caused (:mod:`adnmesh.results.realtime_report`). Plus
wall time, simulated time and their ratio, the speed factor.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import asdict, dataclass, field, replace

import msgspec
import numpy as np

from adnmesh.loopmodel.step_figures import ReferenceStep, is_own_step, reference_step_figures
from adnmesh.results.design_check import DesignCheck, design_checks, design_lines
from adnmesh.results.fault_figures import FaultFigures, fault_figures
from adnmesh.results.realtime_report import ALARM_TIMEOUTS, RealtimeFigures, realtime_lines
from adnmesh.names import LAUNCHER
from adnmesh.results.rules import (EVENTS, Event, StepWindowEnds, availability_change,
                                   available_ders)

__all__ = [
    "GridFigures",
    "RunSeries",
    "note_entry",
    "RunSummary",
    "SUMMARY_TYPES",
    "ScenarioStep",
    "Coupling",
    "SwitchFigures",
    "WINDOW_EVENTS",
    "summarize",
]

SUMMARY_TYPES = frozenset({"p_ip", "p_ref", "q_ref", "p_y", "q_y", "heartbeat", "si",
                           "fault", "event", "grid_state", "grid_guard"})
"""The message types :meth:`RunSeries.add` takes (of ``p_y`` only those with a ``switch``):
the few the summary reads, not every message type of the wire."""

_ALARM_KINDS = frozenset({"overrun", *ALARM_TIMEOUTS})
_MODEL_WATCH_KINDS = frozenset({"model_mismatch", "model_retune", "model_retuned"})

WINDOW_EVENTS = {"p_y": "gain_switch", "heartbeat": "der_available", "fault": "fault",
                 "si": "availability", "event": "event"}
"""The types of :data:`SUMMARY_TYPES` whose messages may be an event that ends a step's
window, and the kind of that event (:class:`~adnmesh.results.rules.EventRule` kinds of
:data:`~adnmesh.results.rules.EVENTS`; ``availability``: SI changes)."""

_RULES = {rule.kind: rule.rule for rule in EVENTS.values()}


class GridFold:
    """The ``grid_state`` bodies of a run folded into :class:`GridFigures` as they come.

    Each body's extremes and counts are folded the way ``min``/``max``/``sum`` over all the
    bodies would take them (the same comparisons in the same order, so a NaN is kept or
    passed over as it would be in the list); only the instants of the periods outside the
    band are kept one by one.
    """

    def __init__(self) -> None:
        self._figures: list | None = None      # v_min, v_max, line, trafo, samples, out, nc
        self._outside: list[float] = []
        self.outside_s = 0.0
        self.at = {"v_min_at": "", "v_max_at": "", "line_max_at": "", "trafo_max_at": ""}
        self.taps: list[int] = []              # the tap positions reported, min and max

    def add(self, body: dict) -> None:
        """Fold one ``grid_state`` body (KeyError if a field is missing)."""
        values = [body["v_min_pu"], body["v_max_pu"], body["line_loading_max_pct"],
                  body["trafo_loading_max_pct"], body["samples"], body["outside_band"],
                  body["not_converged"]]
        t_s = body["t_send_ns"] * 1e-9
        self.outside_s += body.get("outside_s", 0.0)
        if "tap_pos" in body:
            tap = body["tap_pos"]
            self.taps = [tap, tap] if not self.taps else [min(self.taps[0], tap),
                                                           max(self.taps[1], tap)]
        f = self._figures
        for i, name in ((0, "v_min_at"), (1, "v_max_at"), (2, "line_max_at"),
                        (3, "trafo_max_at")):
            better = f is None or (values[i] < f[i] if i == 0 else values[i] > f[i])
            if better and body.get(name):
                self.at[name] = body[name]
        if self._figures is None:
            self._figures = values
        else:
            f[0] = min(f[0], values[0])
            f[1], f[2], f[3] = max(f[1], values[1]), max(f[2], values[2]), max(f[3], values[3])
            f[4], f[5], f[6] = f[4] + values[4], f[5] + values[5], f[6] + values[6]
        if values[5]:
            self._outside.append(t_s)

    def __bool__(self) -> bool:
        return self._figures is not None

    def figures(self) -> GridFigures | None:
        """The run's grid figures, None before the first body."""
        if self._figures is None:
            return None
        return GridFigures(*self._figures, tuple(self._outside), outside_s=self.outside_s,
                           **self.at, tap_range=tuple(self.taps))


@dataclass
class RunSeries:
    """The time series a summary needs (times in ns of sim time).

    Attributes
    ----------
    p_ip_t_ns, p_ip_w : array of int64, array of float64
        Sampling instants and values of ``P_IP`` (``array.array``: 8 bytes a value, where a
        list of Python numbers costs about 40; a run of 3,600 s has 360,000 samples; any
        sequence assigned works too).
    p_ref_t_ns, p_ref_w : array of int64, array of float64
        Instants at which ``P_ref`` took a new value, and the value (the first is the initial one).
    p_ref_offset_w : array of float64
        Per ``P_ref`` record, the level above's offset it includes (an ADN of a hierarchy;
        else 0), W: its steps are the changes of the rest (:meth:`step_records`).
    q_ip_t_ns, q_ip_var, q_ref_t_ns, q_ref_var : array
        The same of ``Q_IP`` (the ``p_ip`` messages that carry it) and ``Q_REF`` (reactive
        power control), var.
    switches : list of dict
        One per gain switch: ``t_ns``, ``p_y_before``, ``p_y_limited`` (limited to the new
        output range), ``p_y_after``, ``available`` (DER ids).
    windows : StepWindowEnds
        The instants of the events that end a step's window (gain switches, a DER's
        availability flag or SI changes, an injected fault starts or ends), by the rule of
        :class:`~adnmesh.results.rules.StepWindowEnds`.
    faults : dict
        Fault number -> the body of its ``fault`` message (sent again to a restarted agent:
        kept once).
    events : list of (float, str, str)
        ``(t_s, sender, kind)`` of every event.
    alarms : list of (float, str, str, str, str)
        ``(t_s, sender, kind, subject, text)`` of the overrun and alarm events
        (:mod:`adnmesh.results.realtime_report`).
    grid : GridFold
        The ``grid_state`` bodies folded as they come (extremes, counts, the periods outside
        the band): a run's memory does not grow with its grid reports.
    lost, rejoined : list of (int, str)
        ``(t_ns, agent)`` of ``up``'s ``agent_lost`` and ``rejoined`` events.
    entries : list of dict
        The table entries the CPFC used, from its ``p_y`` messages with a switch record or
        the design figures of a new entry: ``t_ns``, ``entry`` (number), ``design`` (what the
        entry was certified for, :mod:`adnmesh.results.design_check`; None if not said) and
        ``ders`` (the weighted DERs, when the message has the weights).
    q_entries : list of dict
        The same of the Q loop's entries (its ``q_y`` messages).
    model_watch : list of (float, str, str)
        ``(t_s, kind, text)`` of the CPFC's model watch events (``model_mismatch``,
        ``model_retune``, ``model_retuned``; docs/method.md#model-watch).
    """

    p_ip_t_ns: array = field(default_factory=lambda: array("q"))
    p_ip_w: array = field(default_factory=lambda: array("d"))
    p_ref_t_ns: array = field(default_factory=lambda: array("q"))
    p_ref_w: array = field(default_factory=lambda: array("d"))
    p_ref_offset_w: array = field(default_factory=lambda: array("d"))
    q_ip_t_ns: array = field(default_factory=lambda: array("q"))
    q_ip_var: array = field(default_factory=lambda: array("d"))
    q_ref_t_ns: array = field(default_factory=lambda: array("q"))
    q_ref_var: array = field(default_factory=lambda: array("d"))
    switches: list = field(default_factory=list)
    faults: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    alarms: list = field(default_factory=list)
    grid: GridFold = field(default_factory=lambda: GridFold())
    guard_changes: list = field(default_factory=list)   # (t_ns, acting) of the grid guard
    lost: list = field(default_factory=list)
    rejoined: list = field(default_factory=list)
    entries: list = field(default_factory=list)
    q_entries: list = field(default_factory=list)
    model_watch: list = field(default_factory=list)
    windows: StepWindowEnds = field(default_factory=StepWindowEnds, repr=False)
    _previous: dict = field(default_factory=dict, repr=False)   # (type, sender) -> last body
    _steps: list = field(default_factory=lambda: [None, None, 1, []], repr=False)
    # (the P_ref values' and offsets' objects, records looked at, the step records found; the
    # values are only appended to)
    _si: frozenset | None = field(default=None, repr=False)

    def take(self, message) -> None:
        """Take one genuine message as the recorder's tap has it (a struct of
        :mod:`adnmesh.wire.messages`, made once from its payload): P_IP and P_ref by their
        fields; the few messages the summary reads more of as the dict the rules of
        :mod:`adnmesh.results.rules` read in recordings too (:meth:`add`)."""
        kind = message.type
        if kind == "p_ip":
            self.p_ip_t_ns.append(message.t_send_ns)
            self.p_ip_w.append(message.p_ip_w)
            if message.q_ip_var is not msgspec.UNSET:
                self.q_ip_t_ns.append(message.t_send_ns)
                self.q_ip_var.append(message.q_ip_var)
        elif kind == "p_ref":
            self.p_ref_t_ns.append(message.t_send_ns)
            self.p_ref_w.append(message.p_ref_w)
            self.p_ref_offset_w.append(0.0 if message.offset_w is msgspec.UNSET
                                       else message.offset_w)
        elif kind == "q_ref":
            self.q_ref_t_ns.append(message.t_send_ns)
            self.q_ref_var.append(message.q_ref_var)
        elif kind in SUMMARY_TYPES and (kind not in ("p_y", "q_y")
                                        or message.switch is not msgspec.UNSET
                                        or message.design is not msgspec.UNSET):
            self.add(kind, msgspec.to_builtins(message))

    def step_records(self) -> list[int]:
        """The indices of the ``P_ref`` records that are steps: after the first, those whose
        value less the level above's offset differs from the record before's
        (:func:`~adnmesh.loopmodel.step_figures.is_own_step`; found once per record: the
        records only grow, but for a series or offsets assigned anew)."""
        values, offsets_then, done, found = self._steps
        n = len(self.p_ref_w)
        if values is not self.p_ref_w or offsets_then is not self.p_ref_offset_w or n < done:
            done, found = 1, []
        offsets = self.p_ref_offsets()
        v = self.p_ref_w
        found += [k for k in range(done, n)
                  if is_own_step(v[k - 1], offsets[k - 1], v[k], offsets[k])]
        self._steps = [self.p_ref_w, self.p_ref_offset_w, max(n, 1), found]
        return list(found)

    def step_times_ns(self) -> list[int]:
        """The instants of the steps of ``P_ref`` (:meth:`step_records`), ns."""
        return [self.p_ref_t_ns[k] for k in self.step_records()]

    def p_ref_offsets(self):
        """The offsets per P_ref record (zeros where a series assigned none)."""
        if len(self.p_ref_offset_w) == len(self.p_ref_w):
            return self.p_ref_offset_w
        return [0.0] * len(self.p_ref_w)

    def add(self, message_type: str, body: dict) -> None:
        """Take one decoded message (envelope and body) if the summary needs it."""
        if message_type in WINDOW_EVENTS:
            self._window_event(message_type, body)
        if message_type == "p_ip":
            self.p_ip_t_ns.append(body["t_send_ns"])
            self.p_ip_w.append(body["p_ip_w"])
            if "q_ip_var" in body:
                self.q_ip_t_ns.append(body["t_send_ns"])
                self.q_ip_var.append(body["q_ip_var"])
        elif message_type == "p_ref":
            self.p_ref_t_ns.append(body["t_send_ns"])
            self.p_ref_w.append(body["p_ref_w"])
            self.p_ref_offset_w.append(body.get("offset_w", 0.0))
        elif message_type == "q_ref":
            self.q_ref_t_ns.append(body["t_send_ns"])
            self.q_ref_var.append(body["q_ref_var"])
        elif message_type == "q_y" and ("switch" in body or "design" in body):
            note_entry(self.q_entries, body)
        elif message_type == "p_y" and ("switch" in body or "design" in body):
            note_entry(self.entries, body)
            if "switch" in body:
                switch = body["switch"]
                self.switches.append({"t_ns": body["t_send_ns"],
                                      "p_y_before": switch["p_y_before"],
                                      "p_y_limited": switch.get("p_y_limited",
                                                                switch["p_y_before"]),
                                      "p_y_after": body["p_y"],
                                      "scale": switch.get("scale", 1.0),
                                      "handover_s": switch.get("handover_s", 0.0),
                                      "direction": switch.get("direction"),
                                      "keep": switch.get("keep", []),
                                      "available": sorted(body.get("w", {}))})
        elif message_type == "fault" and body["fault_id"] not in self.faults:
            self.faults[body["fault_id"]] = body
        elif message_type == "event":
            self.events.append((body["t_send_ns"] * 1e-9, body["src"], body["kind"]))
            if body["kind"] in _MODEL_WATCH_KINDS:
                self.model_watch.append((body["t_send_ns"] * 1e-9, body["kind"], body["text"]))
            if body["kind"] in _ALARM_KINDS:
                self.alarms.append((body["t_send_ns"] * 1e-9, body["src"], body["kind"],
                                    body.get("subject") or body["src"], body["text"]))
            if body["src"] == LAUNCHER and body["kind"] in ("agent_lost", "rejoined"):
                (self.lost if body["kind"] == "agent_lost" else self.rejoined).append(
                    (body["t_send_ns"], body.get("subject") or "?"))
        elif message_type == "grid_state":
            self.grid.add(body)
        elif message_type == "grid_guard":
            acting = bool(body.get("hold") or any(body.get(k) for k in
                                                  ("p_up", "p_down", "q_up", "q_down")))
            if not self.guard_changes or self.guard_changes[-1][1] != acting:
                self.guard_changes.append((body["t_send_ns"], acting))

    def _window_event(self, message_type: str, body: dict) -> None:
        """Find the event in a message by the rules of :mod:`adnmesh.results.rules` (the
        previous message of the same type and sender stands for the key's previous one) and
        give it to :attr:`windows`."""
        kind = WINDOW_EVENTS[message_type]
        if kind == "availability":
            available, _ = available_ders(body)
            found = availability_change(available, self._si)
            self._si = frozenset(available)
        else:
            sender = (message_type, body.get("src"))
            found = _RULES[kind](body, self._previous.get(sender), {})
            self._previous[sender] = body
        if found is not None:
            level, text, data = found
            self.windows.take(Event(body["t_send_ns"], kind, level, text, "", data))


def note_entry(entries: list, body: dict) -> None:
    """Keep the table entry a ``p_y``/``q_y`` message with a switch record or design figures
    announces (see :attr:`RunSeries.entries`)."""
    if "switch" in body or not entries or entries[-1]["entry"] != body.get("entry"):
        design = body.get("design")
        entries.append({"t_ns": body["t_send_ns"], "entry": body.get("entry"),
                        "design": design if isinstance(design, dict) else None,
                        "ders": [d for d, w in body.get("w", {}).items() if w]})


@dataclass(frozen=True)
class SwitchFigures:
    """Effect of one gain switch on ``P_IP`` and ``P_Y``: ``available`` are the DERs of the
    new entry; ``handover_s`` how long the DERs took to move to their new shares (0: at once,
    docs/method.md#returning-ders-handover); ``direction`` set on a switch made because the DERs
    move the other way (docs/method.md#directional-availability)."""

    t_s: float
    available: tuple[str, ...]
    max_deviation_w: float | None
    p_y_jump: float
    p_y_limited_by: float = 0.0
    scale: float = 1.0
    handover_s: float = 0.0
    direction: str | None = None
    keep: tuple[str, ...] = ()
    """The DERs the grid guard left out that kept their power (docs/method.md#grid-guard)."""


@dataclass(frozen=True)
class GridFigures:
    """The grid over a run: its extremes and the report periods outside the band."""

    v_min_pu: float
    v_max_pu: float
    line_loading_max_pct: float
    trafo_loading_max_pct: float
    samples: int
    outside_band: int
    not_converged: int
    periods_outside_s: tuple[float, ...]
    outside_s: float = 0.0
    """Time outside the band, s (samples outside times the measurement period)."""
    v_min_at: str = ""
    v_max_at: str = ""
    line_max_at: str = ""
    trafo_max_at: str = ""
    """Where the extremes were (bus, line, transformer names; "" if not recorded)."""
    violations: int = 0
    """Episodes of violation: times a limit was crossed with none crossed before."""
    guard_blocks: int = 0
    """Times the grid guard blocked DERs (``guard_block`` events) or held the control."""
    guarded_s: float = 0.0
    """Time the guard had DERs blocked or the control held, s."""
    energy_short_kwh: float | None = None
    """``∫ |P_ref - P_IP| dt`` while the guard acted, kWh: what the guard cost the control
    (None if it never acted)."""
    steps_short: tuple[float, ...] = ()
    """The P_ref steps (their times, s) not fully delivered while the guard acted: P_IP off by
    more than the settling band of the step when P_ref changed again (or the run ended)."""
    tap_moves: int = 0
    """Steps of the tap changer (``tap`` events)."""
    tap_range: tuple[int, ...] = ()
    """The lowest and highest tap position reported (empty without a tap changer)."""


@dataclass(frozen=True)
class ScenarioStep:
    """One step of the config's scenario and what became of it.

    ``status``: ``executed`` (at its time, within one sample), ``late`` (executed at
    ``executed_s``, later: the CPFC was down at its time and applied it when it restarted) or
    ``not executed``; ``reason`` says why when it is not ``executed`` (else empty).
    """

    t_s: float
    step_w: float
    status: str
    executed_s: float | None = None
    reason: str = ""


@dataclass(frozen=True)
class Coupling:
    """How much the two loops disturb each other through the grid (reactive power control;
    docs/method.md#coupling-of-p-and-q): the largest ``|P_IP - P_ref|`` in the window of a
    Q_ref step, W, and of ``|Q_IP - Q_ref|`` in the window of a P_ref step, var, each also in %
    of the step that caused it (None without such steps)."""

    p_deviation_in_q_steps_w: float | None
    p_deviation_in_q_steps_pct: float | None
    q_deviation_in_p_steps_var: float | None
    q_deviation_in_p_steps_pct: float | None


@dataclass(frozen=True)
class RunSummary:
    """Everything ``adnmesh up`` prints at the end (and writes with ``--summary-json``)."""

    steps: tuple[ReferenceStep, ...]
    switches: tuple[SwitchFigures, ...]
    band_pct: float
    sim_time_s: float
    wall_time_s: float | None
    speed_factor: float | None
    extra: dict = field(default_factory=dict)
    faults: tuple[FaultFigures, ...] = ()
    grid: GridFigures | None = None
    realtime: RealtimeFigures | None = None
    scenario_steps: tuple[ScenarioStep, ...] = ()
    design_checks: tuple[DesignCheck, ...] = ()
    q_steps: tuple[ReferenceStep, ...] = ()
    coupling: Coupling | None = None
    q_design_checks: tuple[DesignCheck, ...] = ()
    model_watch: tuple[tuple[float, str, str], ...] = ()

    def to_json(self) -> dict:
        """Plain data for ``json.dump`` (NaN and infinities become null)."""
        data = asdict(self)
        if self.realtime is not None:
            data["realtime"]["real_time"] = self.realtime.real_time
        return _finite(data)


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _p_ref_at(series: RunSeries, t_ns: np.ndarray) -> np.ndarray:
    ref_t = np.asarray(series.p_ref_t_ns, dtype=np.int64)
    ref_v = np.asarray(series.p_ref_w, dtype=float)
    if ref_v.size == 0:
        return np.full(np.shape(t_ns), np.nan)
    idx = np.searchsorted(ref_t, t_ns, side="right") - 1
    return np.where(idx >= 0, ref_v[np.maximum(idx, 0)], np.nan)


def summarize(series: RunSeries, *, end_ns: int, band_pct: float = 5.0,
              wall_time_s: float | None = None, window_s: float = 10.0,
              extra: dict | None = None,
              realtime: RealtimeFigures | None = None,
              planned_steps=(), sample_s: float = 0.0) -> RunSummary:
    """Compute the summary of a run from its series (see the module docstring).

    Parameters
    ----------
    series : RunSeries
    end_ns : int
        End of the run, ns (closes the last step's window).
    band_pct : float
        Settling band, % of the step.
    wall_time_s : float, optional
        Wall time the run took, s (for the speed factor).
    window_s : float
        Window after a gain switch, s.
    extra : dict, optional
        Further figures to carry along (message counts, clock grants, ...).
    realtime : RealtimeFigures, optional
        The timing of a realtime run.
    planned_steps : sequence of (float, float)
        The scenario's steps of P_ref, ``(t_s, delta_w)`` in the config's order.
    sample_s : float
        The CPFC's sampling period, s: a step recorded within it of its time is on time.
    """
    reactive = len(series.q_ref_t_ns) > 0
    q_changes = list(series.q_ref_t_ns[1:]) if reactive else []
    steps = reference_step_figures(
        series.p_ip_t_ns, series.p_ip_w, series.p_ref_t_ns, series.p_ref_w,
        sorted([*series.windows.instants, *q_changes]), end_ns, band_pct=band_pct,
        offset_w=series.p_ref_offsets())
    p_steps = series.step_times_ns()
    q_steps, coupling = (), None
    if reactive:
        q_steps = reference_step_figures(
            series.q_ip_t_ns, series.q_ip_var, series.q_ref_t_ns, series.q_ref_var,
            sorted([*series.windows.instants, *p_steps]), end_ns, band_pct=band_pct)
        coupling = Coupling(*_cross(q_steps, series.p_ip_t_ns, series.p_ip_w,
                                    series.p_ref_t_ns, series.p_ref_w),
                            *_cross(steps, series.q_ip_t_ns, series.q_ip_var,
                                    series.q_ref_t_ns, series.q_ref_var))
    t_ip = np.asarray(series.p_ip_t_ns, dtype=np.int64)
    p_ip = np.asarray(series.p_ip_w, dtype=float)
    switches = []
    for s in series.switches:
        handover_s = float(s.get("handover_s") or 0.0)
        inside = (t_ip >= s["t_ns"]) & (t_ip <= s["t_ns"] + int((window_s + handover_s) * 1e9))
        next_step = min((t for t in p_steps if t > s["t_ns"]), default=None)
        if next_step is not None:                 # what follows is the step's response
            inside &= t_ip < next_step
        deviation = np.abs(p_ip[inside] - _p_ref_at(series, t_ip[inside]))
        limited, scale = s["p_y_limited"], s.get("scale", 1.0)
        switches.append(SwitchFigures(s["t_ns"] * 1e-9, tuple(s["available"]),
                                      float(np.nanmax(deviation)) if deviation.size else None,
                                      float(s["p_y_after"] - limited),
                                      float(limited - s["p_y_before"] * scale), float(scale),
                                      handover_s, s.get("direction"),
                                      tuple(s.get("keep", ()))))
    sim_s = end_ns * 1e-9
    speed = sim_s / wall_time_s if wall_time_s else None
    return RunSummary(steps, tuple(switches), band_pct, sim_s, wall_time_s, speed,
                      dict(extra or {}), _faults(series, sim_s, band_pct),
                      _grid(series, end_ns, band_pct),
                      realtime, scenario_steps(series, planned_steps, end_ns, sample_s,
                                               (extra or {}).get("ended")),
                      design_checks(steps, series.entries), q_steps, coupling,
                      design_checks(q_steps, series.q_entries), tuple(series.model_watch))


def _cross(steps, t_ns, values, ref_t_ns, ref_values) -> tuple[float | None, float | None]:
    """The largest ``|value - reference|`` of the other quantity in the windows of ``steps``
    and that deviation in % of the step that caused it (None, None without steps)."""
    t = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(values, dtype=float)
    ref_t = np.asarray(ref_t_ns, dtype=np.int64)
    ref_v = np.asarray(ref_values, dtype=float)
    worst, worst_pct = None, None
    for step in steps:
        start = int(round(step.t_s * 1e9))
        inside = (t >= start) & (t < start + int(round(step.window_s * 1e9)))
        if not inside.any() or ref_v.size == 0:
            continue
        index = np.searchsorted(ref_t, t[inside], side="right") - 1
        valid = index >= 0
        if not valid.any():
            continue
        deviation = float(np.nanmax(np.abs(v[inside][valid] - ref_v[index[valid]])))
        if worst is None or deviation > worst:
            worst = deviation
        pct = 100.0 * deviation / abs(step.step_w) if step.step_w else None
        if pct is not None and (worst_pct is None or pct > worst_pct):
            worst_pct = pct
    return worst, worst_pct


def _cpfc_down(series: RunSeries) -> list[tuple[int, float, str]]:
    """``(from_ns, to_ns or inf, how)`` of every span the CPFC was dead: injected kills and
    the agents ``up`` lost."""
    spans = []
    for f in [*series.faults.values(), *lost_faults(series)]:
        if f.get("kind") not in ("kill", "lost") or f.get("agent") != "cpfc":
            continue
        end = math.inf if f.get("end_ns") is None else f["end_ns"]
        how = (f"killed at {f['start_ns'] / 1e9:g} s (fault {f['fault_id']})"
               if f["kind"] == "kill" else f"lost at {f['start_ns'] / 1e9:g} s (it died "
               "unplanned)")
        how += "" if end == math.inf else f" and restarted at {end / 1e9:g} s"
        spans.append((f["start_ns"], end, how))
    return spans


def scenario_steps(series: RunSeries, planned, end_ns: int, sample_s: float = 0.0,
                   ended: str | None = None) -> tuple[ScenarioStep, ...]:
    """What became of every step of the scenario (see the module docstring)."""
    records = series.step_times_ns()          # the first record is the initial P_ref
    down = _cpfc_down(series)
    sample_ns = int(round(sample_s * 1e9))
    out = []
    for t_s, delta_w in planned:
        t_ns = int(round(t_s * 1e9))
        at = next((t for t in records if t >= t_ns), None)
        dead = next((how for start, stop, how in down if start <= t_ns < stop), None)
        if at is not None and at - t_ns <= sample_ns:
            out.append(ScenarioStep(t_s, delta_w, "executed", at * 1e-9))
            continue
        source = f"the CPFC, which sends P_ref, was {dead}" if dead is not None else None
        if at is not None:
            reason = source or "its P_ref was recorded later than one sample after it"
            out.append(ScenarioStep(t_s, delta_w, "late", at * 1e-9, reason))
            continue
        if source is not None:
            reason = source
        elif t_ns > end_ns:
            reason = f"the run ended at {end_ns / 1e9:g} s" + (f" ({ended})" if ended and
                                                            ended != "finished" else "")
        else:
            reason = "no P_ref was recorded at or after it"
        out.append(ScenarioStep(t_s, delta_w, "not executed", None, reason))
    return tuple(out)


def lost_faults(series: RunSeries) -> list[dict]:
    """The agents ``up`` lost, as fault bodies of kind ``lost`` (numbered after the injected
    faults, in time order): from the ``agent_lost`` event to the agent's next ``rejoined``
    event (a restart planned for it), else open."""
    number = max((f["fault_id"] for f in series.faults.values()), default=0)
    out = []
    for t_ns, agent in sorted(series.lost):
        number += 1
        end = min((t for t, a in series.rejoined if a == agent and t > t_ns), default=None)
        out.append({"fault_id": number, "kind": "lost", "agent": agent, "start_ns": t_ns,
                    "end_ns": end, "origin": "unplanned"})
    return out


def _faults(series: RunSeries, end_s: float, band_pct: float) -> tuple[FaultFigures, ...]:
    """Per-fault figures (injected faults and the agents lost); recovery band: ``band_pct`` %
    of the largest P_ref step (1 MW without steps); a step of P_ref ends a fault's after window
    (what follows is the step's)."""
    ref = np.asarray(series.p_ref_w, dtype=float)
    at = series.step_records()
    steps = np.abs(ref[at] - ref[np.subtract(at, 1)]) if at else np.zeros(0)
    band_w = band_pct / 100 * (float(steps.max()) if steps.size and steps.max() > 0 else 1e6)
    scenario = [t * 1e-9 for t in series.step_times_ns()]     # the steps end an after window
    faults = [*series.faults.values(), *lost_faults(series)]
    return tuple(fault_figures(faults, series.events,
                               np.asarray(series.p_ip_t_ns) * 1e-9, series.p_ip_w,
                               np.asarray(series.p_ref_t_ns) * 1e-9, series.p_ref_w,
                               end_s=end_s, band_w=band_w, events_s=scenario))


def _steps_short(series: RunSeries, t: np.ndarray, error: np.ndarray, intervals,
                 end_ns: int, band_pct: float) -> tuple[float, ...]:
    """The P_ref steps (their times, s) not fully delivered while the guard acted: at the
    last P_IP sample before P_ref changes again (or the run ends), ``|P_ref - P_IP|`` is
    more than ``band_pct`` % of the step, and the guard acted after the step."""
    ref_t = list(series.p_ref_t_ns)
    ref_v = list(series.p_ref_w)
    records = series.step_records()
    out = []
    for n, k in enumerate(records):
        start = ref_t[k]
        stop = ref_t[records[n + 1]] if n + 1 < len(records) else end_ns
        step = abs(ref_v[k] - ref_v[k - 1])
        last = np.flatnonzero((t >= start) & (t < stop))
        if not step or not last.size or not any(a < stop and b > start for a, b in intervals):
            continue
        if error[last[-1]] > band_pct / 100.0 * step:
            out.append(start * 1e-9)
    return tuple(out)


def _grid(series: RunSeries, end_ns: int, band_pct: float = 5.0) -> GridFigures | None:
    """The grid figures with the violations, the guard's actions and their cost, and the
    tap changer's steps."""
    figures = series.grid.figures()
    if figures is None:
        return None
    kinds = [kind for _, _, kind in series.events]
    intervals, start = [], None
    for t_ns, acting in series.guard_changes:
        if acting and start is None:
            start = t_ns
        elif not acting and start is not None:
            intervals.append((start, t_ns))
            start = None
    if start is not None:
        intervals.append((start, end_ns))
    guarded_s = sum(b - a for a, b in intervals) * 1e-9
    energy, short = None, ()
    if intervals:
        t = np.asarray(series.p_ip_t_ns, dtype=np.int64)
        error = np.abs(np.asarray(series.p_ip_w, dtype=float) - _p_ref_at(series, t))
        joules = 0.0
        for a, b in intervals:          # each sample holds until the next (or the end)
            inside = (t >= a) & (t < b)
            held_s = np.diff(np.append(t[inside], b)) * 1e-9
            joules += float(np.nansum(error[inside] * held_s))
        energy = joules / 3.6e6
        short = _steps_short(series, t, error, intervals, end_ns, band_pct)
    return replace(figures, violations=kinds.count("limit_violated"),
                   guard_blocks=kinds.count("guard_block") + kinds.count("guard_hold"),
                   guarded_s=guarded_s, energy_short_kwh=energy, steps_short=short,
                   tap_moves=kinds.count("tap"))


def format_summary(summary: RunSummary):
    """Rich renderables (tables and lines) of a summary, for the console."""
    from rich.table import Table

    from adnmesh.results.figures import step_table

    def num(value, fmt):
        return "-" if value is None else format(value, fmt)

    out = [step_table(summary.steps, summary.band_pct, "P_ref steps: P_IP",
                      summary.design_checks)]
    out += design_lines(summary.design_checks)
    out += scenario_lines(summary.scenario_steps)
    if summary.coupling is not None:
        out.append(step_table(summary.q_steps, summary.band_pct, "Q_ref steps: Q_IP",
                              summary.q_design_checks, unit="var"))
        out += design_lines(summary.q_design_checks, unit="var")
        out.append(coupling_line(summary.coupling))
    switches = Table(title="gain switches", title_justify="left")
    for column in ("t [s]", "available DERs", "max |P_IP - P_ref| in 10 s [W]", "P_Y jump"):
        switches.add_column(column, justify="right" if column != "available DERs" else "left",
                            overflow="fold")
    for s in summary.switches:
        # every name, however many (a long list folds over lines; none is cut off)
        names = ", ".join(s.available) + (f" ({len(s.available)})" if len(s.available) > 4
                                          else "")
        switches.add_row(f"{s.t_s:.2f}", names, num(s.max_deviation_w, ".4g"),
                         f"{s.p_y_jump:.3g}")
    if not summary.switches:
        switches.add_row("", "no switches", "", "")
    out.append(switches)
    for s in summary.switches:
        if s.direction:
            out.append(f"  at {s.t_s:.2f} s the DERs were to move {s.direction}: the entry of "
                       "those that can (directional availability)")
        if s.keep:
            out.append(f"  at {s.t_s:.2f} s the grid guard capped {', '.join(s.keep)} at the "
                       "power they had (left out, not sent back to their schedules)")
        if s.scale != 1.0:
            out.append(f"  at {s.t_s:.2f} s P_Y was scaled by {s.scale:.4g} so that the DERs' "
                       "commanded power stayed continuous")
        if s.handover_s:
            out.append(f"  at {s.t_s:.2f} s the DERs moved to their new shares in "
                       f"{s.handover_s:.3g} s (handover); max |P_IP - P_ref| counted over it "
                       "and 10 s more")
        if s.p_y_limited_by:
            out.append(f"  at {s.t_s:.2f} s P_Y lay outside the new DERs' output range (every "
                       f"one saturated) and was limited by {s.p_y_limited_by:.3g} first")
    if summary.model_watch:
        out.append("the CPFC's model watch (docs/method.md#model-watch):")
        out += [f"  {t:.2f} s {kind}: {text}" for t, kind, text in summary.model_watch]
    if summary.faults:
        out.append(fault_table(summary.faults))
    if summary.grid is not None:
        out.append(grid_line(summary.grid))
    if summary.realtime is not None:
        out += realtime_lines(summary.realtime)
    line = f"run: {summary.sim_time_s:g} s simulated"
    if summary.wall_time_s is not None:
        line += f" in {summary.wall_time_s:.2f} s wall"
    if summary.speed_factor is not None:
        line += f", speed factor {summary.speed_factor:.1f}x real time"
    out.append(line)
    if summary.extra:
        out.append(", ".join(f"{k} {_fmt(v)}" for k, v in summary.extra.items()))
    return out


def coupling_line(coupling: Coupling) -> str:
    """One line on how much each loop's steps disturbed the other quantity."""
    def part(value, pct, unit, what):
        if value is None:
            return f"no {what} step"
        share = "" if pct is None else f" ({pct:.3g} % of the step)"
        return f"{value / 1e3:.4g} k{unit}{share}"

    return ("coupling through the grid: largest |P_IP - P_ref| after a Q_ref step "
            f"{part(coupling.p_deviation_in_q_steps_w, coupling.p_deviation_in_q_steps_pct, 'W', 'Q_ref')}"
            "; largest |Q_IP - Q_ref| after a P_ref step "
            f"{part(coupling.q_deviation_in_p_steps_var, coupling.q_deviation_in_p_steps_pct, 'var', 'P_ref')}")


def scenario_lines(planned) -> list[str]:
    """One line per step of the scenario that was not executed at its time, with why."""
    out = []
    for s in planned:
        if s.status == "executed":
            continue
        what = "NOT EXECUTED" if s.executed_s is None else \
            f"executed late, at {s.executed_s:.2f} s"
        out.append(f"  scenario step at {s.t_s:g} s ({s.step_w / 1e6:+.3f} MW): {what}: "
                   f"{s.reason}")
    return out


def fault_table(faults):
    """The per-fault table (``adnmesh up`` and ``adnmesh inspect``)."""
    from rich.table import Table

    def kw(value):
        return "-" if value is None else f"{value / 1e3:.1f}"

    table = Table(title="faults (|dP| = |P_IP - P_ref|, kW)", title_justify="left")
    for column in ("#", "fault", "window [s]", "detected", "max |dP| during", "after",
                   "recovery [s]"):
        table.add_column(column, justify="left" if column in ("fault", "detected")
                         else "right", overflow="fold")
    for f in faults:
        window = f"{f.start_s:g}-" + ("end" if f.end_s is None else f"{f.end_s:g}")
        seen = "no" if f.detected_by is None else \
            f"{f.detected_by} +{f.detection_delay_s:.2f} s"
        table.add_row(str(f.fault_id), f"{f.kind} {f.target}", window, seen,
                      kw(f.max_deviation_during_w), kw(f.max_deviation_after_w),
                      "-" if f.recovery_time_s is None else f"{f.recovery_time_s:.2f}")
    return table


def grid_line(grid: GridFigures) -> str:
    """The grid's extremes and the samples outside the band (one line); with violations, a
    guard that acted or a tap changer, a line on each."""
    text = (f"grid: bus voltages {grid.v_min_pu:.4f} to {grid.v_max_pu:.4f} p.u., highest "
            f"loading {grid.line_loading_max_pct:.1f} % (lines), {grid.trafo_loading_max_pct:.1f}"
            f" % (transformers); {grid.outside_band} of {grid.samples} samples outside the band")
    if grid.periods_outside_s:
        shown = ", ".join(f"{t:g}" for t in grid.periods_outside_s[:5])
        text += f" (periods ending at {shown} s{', ...' if len(grid.periods_outside_s) > 5 else ''})"
    if grid.not_converged:
        text += f"; {grid.not_converged} power flows did not converge (last value kept)"
    lines = [text]
    if grid.violations or grid.outside_s:
        worst = [f"{grid.v_max_pu:.4f} p.u. at {grid.v_max_at or '?'}",
                 f"{grid.v_min_pu:.4f} p.u. at {grid.v_min_at or '?'}",
                 f"line {grid.line_max_at or '?'} {grid.line_loading_max_pct:.1f} %",
                 f"trafo {grid.trafo_max_at or '?'} {grid.trafo_loading_max_pct:.1f} %"]
        lines.append(f"grid limits: {grid.violations} violation(s), {grid.outside_s:.2f} s "
                     f"outside the band; extremes {'; '.join(worst)}")
    if grid.guard_blocks or grid.guarded_s:
        short = (", ".join(f"{t:g} s" for t in grid.steps_short) or "none")
        lines.append(f"grid guard: acted {grid.guard_blocks} time(s), {grid.guarded_s:.2f} s "
                     f"with DERs blocked or the control held; cost: "
                     f"{grid.energy_short_kwh or 0.0:.3f} kWh of |P_ref - P_IP| meanwhile, "
                     f"steps not fully delivered: {short}")
    if grid.tap_range:
        lines.append(f"tap changer: {grid.tap_moves} step(s), positions {grid.tap_range[0]} "
                     f"to {grid.tap_range[1]}")
    return "\n".join(lines)


def _fmt(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
