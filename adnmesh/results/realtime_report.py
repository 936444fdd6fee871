"""What a realtime run says about its own timing (pure functions, for the summary).

- **Delivery errors** per link: p50, p99 and the largest, ms of sim time, from the agents'
  goodbye histograms (:mod:`adnmesh.sim.latency`; ``timer`` is the agents' own timers, ``up``
  what ``up`` sends).
- **Late arrivals**: messages that arrived after their scheduled delivery time (sender's error
  plus transport latency beyond the link's delay; for the measurement's zero-delay inputs beyond
  the tolerance it waits). Only these can make a realtime run's control result differ from the
  sim clock's: with none, every agent processes the same inputs at the same scheduled times.
- **Overruns**: events processed later than the tolerance (every agent counts them; it says so
  at once with an ``overrun`` event, at most one per sim second). A run with an overrun is
  **not real time**: its control result may differ from the sim clock's.
- **Alarms caused by lateness**: a DER marked unavailable, a watchdog fallback or a CPFC hold
  that neither an injected fault (active within the alarm's timeout before it) nor the
  scenario (a change of that DER's availability within the timeout and 1 s before it)
  explains, while an agent reported an overrun (within the timeout and 1 s before it, or 1 s
  after: the late message arrives after the alarm), is the machine's doing, not the grid's,
  and is reported as such.
"""

from __future__ import annotations

from dataclasses import dataclass

from adnmesh.names import der_agent_id
from adnmesh.sim.latency import merge, percentile

__all__ = ["ALARM_TIMEOUTS", "LateAlarm", "LinkErrors", "RealtimeFigures", "realtime_figures",
           "realtime_lines"]

ALARM_TIMEOUTS = {"unavailable": "heartbeat_timeout_s", "watchdog_fallback": "watchdog_timeout_s",
                  "hold": "measurement_timeout_s"}
"""Event kinds that are alarms, and the runtime timeout behind each."""

_AFTER_S = 1.0   # an overrun this long after an alarm can still be its cause


@dataclass(frozen=True)
class LinkErrors:
    """Delivery errors of one link, ms of sim time."""

    link: str
    events: int
    p50_ms: float
    p99_ms: float
    max_ms: float


@dataclass(frozen=True)
class LateAlarm:
    """An alarm (see the module docstring) the machine's lateness caused."""

    t_s: float
    kind: str
    subject: str
    overrun_by: str


@dataclass(frozen=True)
class RealtimeFigures:
    """Timing of a realtime run (see the module docstring)."""

    speed: float
    tolerance_ms: float
    links: tuple[LinkErrors, ...]
    overruns: int
    overrun_events: int
    first_overrun: str | None
    late_alarms: tuple[LateAlarm, ...]
    late_arrivals: int = 0

    @property
    def real_time(self) -> bool:
        """No event was processed later than the tolerance."""
        return self.overruns == 0 and self.overrun_events == 0


def realtime_figures(byes, alarms, faults, config, *, speed: float,
                     tolerance_ns: int) -> RealtimeFigures:
    """The figures of a realtime run.

    Parameters
    ----------
    byes : iterable
        The agents' ``agent_bye`` messages.
    alarms : sequence of (t_s, sender, kind, subject, text)
        The run's ``overrun`` and alarm events (:attr:`RunSeries.alarms`).
    faults : iterable of dict
        The bodies of the run's ``fault`` messages.
    config : adnmesh.config.Config
        For the alarms' timeouts and the scenario's availability changes.
    speed : float
        Sim seconds per wall second.
    tolerance_ns : int
        The overrun tolerance, ns of sim time.
    """
    byes = list(byes)
    merged = merge(b.latency for b in byes if isinstance(b.latency, dict))
    links = tuple(LinkErrors(link, sum(e.counts), percentile(e, 0.5) / 1e6,
                             percentile(e, 0.99) / 1e6, e.max_ns / 1e6)
                  for link, e in sorted(merged.items()) if sum(e.counts))
    overruns = [a for a in alarms if a[2] == "overrun"]
    late = tuple(_late_alarms(alarms, overruns, list(faults), config))
    return RealtimeFigures(float(speed), tolerance_ns / 1e6, links,
                           sum(int(b.stats.get("overruns", 0)) for b in byes), len(overruns),
                           overruns[0][4] if overruns else None, late,
                           sum(int(b.stats.get("late", 0)) for b in byes))


def _late_alarms(alarms, overruns, faults, config):
    scheduled = [(c.t_s, {der_agent_id(d) for d in c.ders}) for c in config.scenario.availability]
    for t, _, kind, subject, _ in alarms:
        if kind not in ALARM_TIMEOUTS:
            continue
        timeout = getattr(config.runtime, ALARM_TIMEOUTS[kind])
        by_fault = any(f["start_ns"] * 1e-9 <= t and
                       (f.get("end_ns") is None or f["end_ns"] * 1e-9 + timeout >= t)
                       for f in faults)
        by_scenario = any(t - timeout - _AFTER_S <= t_change <= t and subject in ders
                          for t_change, ders in scheduled)
        if by_fault or by_scenario:
            continue
        cause = next((o for o in overruns if t - timeout - _AFTER_S <= o[0] <= t + _AFTER_S),
                     None)
        if cause is not None:
            yield LateAlarm(t, kind, subject, cause[3] or cause[1])


def realtime_lines(figures: RealtimeFigures):
    """Rich renderables of the figures, for ``up``'s summary."""
    from rich.table import Table

    table = Table(title=f"realtime at speed {figures.speed:g}: delivery error per link (ms of "
                        f"sim time; tolerance {figures.tolerance_ms:g} ms)", title_justify="left")
    for column in ("link", "events", "p50", "p99", "max"):
        table.add_column(column, justify="left" if column == "link" else "right")
    for e in figures.links:
        table.add_row(e.link, str(e.events), f"{e.p50_ms:.3g}", f"{e.p99_ms:.3g}",
                      f"{e.max_ms:.3g}")
    late = figures.late_arrivals
    out = [table, f"messages that arrived after their delivery time: {late}" + (
        " (so the control result is the sim clock's)" if late == 0 else
        " (each acted as a delay longer by at most the largest delivery error)")]
    if figures.real_time:
        out.append("real time: every event within the tolerance")
    else:
        out.append(f"NOT REAL TIME: {figures.overruns} event(s) later than the tolerance "
                   f"({figures.overrun_events} overrun report(s)); first: "
                   f"{figures.first_overrun}. The control result may differ from the sim "
                   "clock's: lower --speed")
    for a in figures.late_alarms:
        out.append(f"  {a.kind} of {a.subject} at {a.t_s:.2f} s: caused by the machine's "
                   f"lateness ({a.overrun_by} overran), not by the grid or an injected fault")
    return out
