"""The end-of-run summary, computed by pure functions from the recorded time series.

For every step of ``P_ref`` (the CPFC's ``scenario/p_ref`` records) the response of ``P_IP``
(the measurement's samples, at their sampling instants) until the next event (step, gain switch,
a DER's availability change, an injected fault) or the end: rise time (10-90 %), settling time
in ``band_pct`` % and in 2 % of the step, overshoot, peak, and the steady error ``P_ref - P_IP``
at the window's last sample, W. The figures and the windows are those of
:func:`adnmesh.stepfigures.reference_step_figures`, the rule ``adnmesh inspect`` applies to the
recording too (:mod:`adnmesh.recording.figures`), so both print the same figures.

The events that end a window (:class:`RunSeries`): a ``p_y`` message with a ``switch`` record,
a DER heartbeat whose ``available`` flag differs from the DER's previous one (every DER
counts as available before its first heartbeat), an SI message whose set of available DERs
differs from the previous SI's (the first SI is the initial state), every ``fault`` message.

For every gain switch (``cpfc/p_y`` messages with a ``switch`` record): the largest
``|P_IP - P_ref|`` in the ``window_s`` (10 s) after it, and the jump of ``P_Y`` at the switch
(output with the new gains minus output with the old ones at the switching sample; 0 when the
switch is bumpless). An old output outside the new DERs' range (where every one of them is
saturated) is limited to that range first; the jump is counted from the limited value and the
limiting reported apart (``p_y_limited_by``). Plus wall time, simulated time and their ratio, the speed factor.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from adnmesh.stepfigures import ReferenceStep, reference_step_figures

__all__ = [
    "MESSAGE_TYPES",
    "RunSeries",
    "RunSummary",
    "SwitchFigures",
    "summarize",
]

MESSAGE_TYPES = frozenset({"p_ip", "p_ref", "p_y", "heartbeat", "si", "fault"})
"""The message types :meth:`RunSeries.add` takes (of ``p_y`` only those with a ``switch``)."""


@dataclass
class RunSeries:
    """The time series a summary needs (times in ns of sim time).

    Attributes
    ----------
    p_ip_t_ns, p_ip_w : list
        Sampling instants and values of ``P_IP``.
    p_ref_t_ns, p_ref_w : list
        Instants at which ``P_ref`` took a new value, and the value (the first is the initial one).
    switches : list of dict
        One per gain switch: ``t_ns``, ``p_y_before``, ``p_y_limited`` (limited to the new
        output range), ``p_y_after``, ``available`` (DER ids).
    disturbances_ns : list of int
        Instants of other events that disturb ``P_IP`` (a DER's availability flag or SI
        changes, an injected fault starts or ends); a step's window ends at the next one.
    """

    p_ip_t_ns: list = field(default_factory=list)
    p_ip_w: list = field(default_factory=list)
    p_ref_t_ns: list = field(default_factory=list)
    p_ref_w: list = field(default_factory=list)
    switches: list = field(default_factory=list)
    disturbances_ns: list = field(default_factory=list)
    _flags: dict = field(default_factory=dict, repr=False)
    _si: frozenset | None = field(default=None, repr=False)

    def add(self, message_type: str, body: dict) -> None:
        """Take one decoded message (envelope and body) if the summary needs it."""
        if message_type == "p_ip":
            self.p_ip_t_ns.append(body["t_send_ns"])
            self.p_ip_w.append(body["p_ip_w"])
        elif message_type == "p_ref":
            self.p_ref_t_ns.append(body["t_send_ns"])
            self.p_ref_w.append(body["p_ref_w"])
        elif message_type == "p_y" and "switch" in body:
            switch = body["switch"]
            self.switches.append({"t_ns": body["t_send_ns"],
                                  "p_y_before": switch["p_y_before"],
                                  "p_y_limited": switch.get("p_y_limited", switch["p_y_before"]),
                                  "p_y_after": body["p_y"],
                                  "available": sorted(body.get("w", {}))})
        elif message_type == "heartbeat":
            if self._flags.get(body["src"], True) != body["available"]:
                self.disturbances_ns.append(body["t_send_ns"])
            self._flags[body["src"]] = body["available"]
        elif message_type == "si":
            available = frozenset(d for d, flag in body["si"].items() if flag)
            if self._si is not None and self._si != available:
                self.disturbances_ns.append(body["t_send_ns"])
            self._si = available
        elif message_type == "fault":
            self.disturbances_ns.append(body["t_send_ns"])


@dataclass(frozen=True)
class SwitchFigures:
    """Effect of one gain switch on ``P_IP`` and ``P_Y``."""

    t_s: float
    available: tuple[str, ...]
    max_deviation_w: float | None
    p_y_jump: float
    p_y_limited_by: float = 0.0


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

    def to_json(self) -> dict:
        """Plain data for ``json.dump`` (NaN and infinities become null)."""
        return _finite(asdict(self))


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
    idx = np.searchsorted(ref_t, t_ns, side="right") - 1
    return np.where(idx >= 0, ref_v[np.maximum(idx, 0)], np.nan)


def summarize(series: RunSeries, *, end_ns: int, band_pct: float = 5.0,
              wall_time_s: float | None = None, window_s: float = 10.0,
              extra: dict | None = None) -> RunSummary:
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
    """
    steps = reference_step_figures(
        series.p_ip_t_ns, series.p_ip_w, series.p_ref_t_ns, series.p_ref_w,
        [*(s["t_ns"] for s in series.switches), *series.disturbances_ns], end_ns,
        band_pct=band_pct)
    t_ip = np.asarray(series.p_ip_t_ns, dtype=np.int64)
    p_ip = np.asarray(series.p_ip_w, dtype=float)
    switches = []
    for s in series.switches:
        inside = (t_ip >= s["t_ns"]) & (t_ip <= s["t_ns"] + int(window_s * 1e9))
        deviation = np.abs(p_ip[inside] - _p_ref_at(series, t_ip[inside]))
        limited = s["p_y_limited"]
        switches.append(SwitchFigures(s["t_ns"] * 1e-9, tuple(s["available"]),
                                      float(np.nanmax(deviation)) if deviation.size else None,
                                      float(s["p_y_after"] - limited),
                                      float(limited - s["p_y_before"])))
    sim_s = end_ns * 1e-9
    speed = sim_s / wall_time_s if wall_time_s else None
    return RunSummary(steps, tuple(switches), band_pct, sim_s, wall_time_s, speed,
                      dict(extra or {}))


def format_summary(summary: RunSummary):
    """Rich renderables (tables and lines) of a summary, for the console."""
    from rich.table import Table

    from adnmesh.recording.figures import step_table

    def num(value, fmt):
        return "-" if value is None else format(value, fmt)

    out = [step_table(summary.steps, summary.band_pct, "P_ref steps: P_IP")]
    switches = Table(title="gain switches", title_justify="left")
    for column in ("t [s]", "available DERs", "max |P_IP - P_ref| in 10 s [W]", "P_Y jump"):
        switches.add_column(column, justify="right" if column != "available DERs" else "left")
    for s in summary.switches:
        names = ", ".join(s.available) if len(s.available) <= 4 else \
            f"{', '.join(s.available[:3])}, ... ({len(s.available)})"
        switches.add_row(f"{s.t_s:.2f}", names, num(s.max_deviation_w, ".4g"),
                         f"{s.p_y_jump:.3g}")
    if not summary.switches:
        switches.add_row("", "no switches", "", "")
    out.append(switches)
    for s in summary.switches:
        if s.p_y_limited_by:
            out.append(f"  at {s.t_s:.2f} s P_Y lay outside the new DERs' output range (every "
                       f"one saturated) and was limited by {s.p_y_limited_by:.3g} first")
    line = f"run: {summary.sim_time_s:g} s simulated"
    if summary.wall_time_s is not None:
        line += f" in {summary.wall_time_s:.2f} s wall"
    if summary.speed_factor is not None:
        line += f", speed factor {summary.speed_factor:.1f}x real time"
    out.append(line)
    if summary.extra:
        out.append(", ".join(f"{k} {_fmt(v)}" for k, v in summary.extra.items()))
    return out


def _fmt(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
