"""The steps over their design, found as a run is recorded: for the recorder's Foxglove log
(:class:`adnmesh.results.eventlog.EventLog`), by the rule of
:mod:`adnmesh.results.design_check` on the figures of ``adnmesh up``'s summary
(docs/method.md#said-when-over)."""

from __future__ import annotations

import json
from array import array
from dataclasses import dataclass

import numpy as np
from adnmesh.loopmodel.step_figures import reference_step_figures
from adnmesh.results.design_check import DesignCheck, design_checks, design_lines, entry_at
from adnmesh.results.summary import RunSeries

__all__ = ["GRACE_NS", "OverDesign", "OverDesignWatch", "WATCHED_TYPES"]

#: sim time a step's window is left open after its end, so that every message before the end
#: has been recorded (messages of one clock window arrive in any order), ns
GRACE_NS = 1_000_000_000

_TRIM = 20_000      # P_IP samples (200 s at 10 ms) between two trims of the checked ones

WATCHED_TYPES = frozenset({"p_ip", "p_ref", "p_y", "heartbeat", "si", "fault", "event",
                           "clock_start", "clock_stop"})
"""The message types the watch reads; it ignores every other."""


@dataclass(frozen=True)
class OverDesign:
    """A step over its design: its window's end (``closed_ns``, where the figures stop) and
    the check (:class:`~adnmesh.results.design_check.DesignCheck`: the step, its entry and
    DERs, each figure against its design)."""

    closed_ns: int
    check: DesignCheck

    @property
    def text(self) -> str:
        """The words of :func:`~adnmesh.results.design_check.design_lines`."""
        return design_lines([self.check])[0].strip()


class OverDesignWatch:
    """Says, as a run is recorded, which steps are over their design (for the recorder's
    Foxglove log, :class:`adnmesh.results.eventlog.EventLog`).

    It keeps the messages ``adnmesh up``'s summary reads (:class:`~adnmesh.results.summary.
    RunSeries`; P_IP only as far back as a step still to be checked needs it, so its memory
    does not grow with the run) and, once a step's window has closed (the next step or window-ending event,
    seen :data:`GRACE_NS` of P_IP samples later; the last one at the clock's stop), takes its
    figures by the summary's rule and checks them (:func:`design_checks`). Each step over its
    design gives one ``(t_ns, text)``: its window's end and the words of :func:`design_lines`
    (the log records it at the message that closed the window, a grace later).

    With ``early_settlings`` (the CPFC's model watch, docs/method.md#model-watch) a step is
    judged at the latest that many of its entry's design settling times after it, on the
    window up to then, rather than only when the next step or event ends its window.
    """

    def __init__(self, band_pct: float | None = None,
                 early_settlings: float | None = None) -> None:
        self.series = RunSeries()
        self._band_pct = band_pct
        self._early = early_settlings
        #: P_IP samples from this instant on are kept whatever the steps need (ns; None: no
        #: such wish), for a watch of its own on the same series
        self.keep_from_ns: int | None = None
        self._end_ns: int | None = None
        self._checked = 0                  # steps (P_ref changes) already checked
        self._due_ns = 0                   # no step can close before this P_IP sample
        self._known = (0, 0, 0)            # window ends, P_ref values, entries seen at _due_ns
        self._trim_at = _TRIM              # P_IP samples held when the next trim is due

    def observe(self, schema_name: str, payload: bytes, t_ns: int) -> list[tuple[int, str]]:
        """The over-design findings a recorded message closes (usually none), as
        ``(window end, words)``."""
        if schema_name not in WATCHED_TYPES or (schema_name == "p_y" and b'"switch"' not in payload
                                           and b'"design"' not in payload):
            return []
        try:
            body = json.loads(payload)
        except ValueError:
            return []
        if not isinstance(body, dict):
            return []
        return [(found.closed_ns, found.text) for found in self.observe_body(schema_name, body)]

    def observe_body(self, schema_name: str, body: dict) -> list[OverDesign]:
        """The steps over their design that one decoded message (envelope and body, as
        :meth:`RunSeries.add <adnmesh.results.summary.RunSeries.add>` takes it) closes."""
        if schema_name not in WATCHED_TYPES:
            return []
        if schema_name == "clock_start":
            if isinstance(body.get("end_ns"), int):
                self._end_ns = body["end_ns"]
            return []
        if schema_name == "clock_stop":
            return self._close(final=True)
        try:
            self.series.add(schema_name, body)
        except (KeyError, TypeError):
            return []
        if schema_name == "p_y" and isinstance(body.get("design"), dict):
            self._band_pct = float(body["design"].get("settling_band_pct", self._band_pct or 5))
        if schema_name != "p_ip":
            return []
        found = self._close(final=False)
        self._forget_checked()
        return found

    def _forget_checked(self) -> None:
        """Drop the P_IP samples no step still to be checked can use (before the first such
        step's start, and more than :data:`GRACE_NS` before the newest sample), so that the
        watch holds the open windows, not the run: every :data:`_TRIM` samples, O(samples)."""
        series = self.series
        if len(series.p_ip_t_ns) < self._trim_at:
            return
        starts = series.step_times_ns()
        cutoff = series.p_ip_t_ns[-1] - GRACE_NS
        if self._checked < len(starts):
            cutoff = min(cutoff, starts[self._checked])
        if self.keep_from_ns is not None:
            cutoff = min(cutoff, self.keep_from_ns)
        t = np.asarray(series.p_ip_t_ns, dtype=np.int64)
        keep = t >= cutoff
        series.p_ip_t_ns = array("q", t[keep].tobytes())
        series.p_ip_w = array("d", np.asarray(series.p_ip_w, dtype=float)[keep].tobytes())
        self._trim_at = len(series.p_ip_t_ns) + _TRIM

    def _early_end(self, start_ns: int) -> int | None:
        """When the step at ``start_ns`` is judged at the latest (``early_settlings`` of its
        entry's design settling times after it), ns; None without them."""
        if self._early is None:
            return None
        announced = entry_at(self.series.entries, start_ns)
        design = None if announced is None else announced.get("design")
        if not design:
            return None
        return start_ns + int(round(self._early * float(design["settling_time_s"]) * 1e9))

    def _close(self, final: bool) -> list[OverDesign]:
        series = self.series
        if not series.p_ip_t_ns or len(series.p_ref_t_ns) < 2:
            return []
        now = series.p_ip_t_ns[-1]
        known = (len(series.windows.instants), len(series.p_ref_t_ns), len(series.entries))
        if not final and now < self._due_ns and known == self._known:
            return []
        starts = series.step_times_ns()     # an offset from a level above is no step
        if self._checked >= len(starts):
            return []
        ends = sorted(set(series.windows.instants) | set(starts))
        found = []
        while self._checked < len(starts):
            start = starts[self._checked]
            later = [t for t in ends if t > start]
            early = self._early_end(start)
            cut = [early] if early is not None and (not later or early < later[0]) else []
            later = cut or later
            if later and now >= later[0] + GRACE_NS:
                end_ns = now                   # the window ends at later[0], exclusive
            elif final:
                end_ns = self._end_ns if self._end_ns is not None and now >= self._end_ns else now
            else:
                self._due_ns = later[0] + GRACE_NS if later else 2**63
                self._known = known
                break
            steps = reference_step_figures(series.p_ip_t_ns, series.p_ip_w, series.p_ref_t_ns,
                                           series.p_ref_w, [*series.windows.instants, *cut],
                                           end_ns, band_pct=self._band_pct or 5.0,
                                           offset_w=series.p_ref_offsets())
            step = next((s for s in steps if int(round(s.t_s * 1e9)) == start), None)
            self._checked += 1
            if step is None:
                continue
            closed = start + int(round(step.window_s * 1e9))
            found += [OverDesign(closed, check)
                      for check in design_checks([step], series.entries) if check.over]
        return found
