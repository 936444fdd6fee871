"""The end-of-run summary, computed by pure functions from the recorded time series.

For every step of ``P_ref`` (the CPFC's ``scenario/p_ref`` records) the response of ``P_IP``
(the measurement's samples, at their sampling instants) until the next event (step, gain switch,
a DER's availability change, an injected fault) or the end:

- **rise time**: from 10 % to 90 % of the step (first crossings, interpolated linearly), s;
- **settling time**: from the step until ``P_IP`` stays within ``band_pct`` % of the step around
  the new reference (interpolated), s; None if it never settles in the window;
- **overshoot**: beyond the new reference in the step's direction, % of the step;
- **steady error**: ``P_ref - P_IP`` at the last sample of the window, W.

For every gain switch (``cpfc/p_y`` messages with a ``switch`` record): the largest
``|P_IP - P_ref|`` in the ``window_s`` (10 s) after it, and the jump of ``P_Y`` at the switch
(output with the new gains minus output with the old ones at the switching sample; 0 when the
switch is bumpless). An old output outside the new DERs' range (where every one of them is
saturated) is limited to that range first; the jump is counted from the limited value and the
limiting reported apart (``p_y_limited_by``). Plus wall time, simulated time and their ratio, the speed factor.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = [
    "RunSeries",
    "RunSummary",
    "StepFigures",
    "SwitchFigures",
    "step_figures",
    "summarize",
]


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
        Instants of other events that disturb ``P_IP`` (a DER's availability changes, an
        injected fault starts or ends); a step's window ends at the next one.
    """

    p_ip_t_ns: list = field(default_factory=list)
    p_ip_w: list = field(default_factory=list)
    p_ref_t_ns: list = field(default_factory=list)
    p_ref_w: list = field(default_factory=list)
    switches: list = field(default_factory=list)
    disturbances_ns: list = field(default_factory=list)
    _flags: dict = field(default_factory=dict, repr=False)

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
        elif message_type == "fault":
            self.disturbances_ns += [t for t in (body["start_ns"], body["end_ns"])
                                     if t is not None]


@dataclass(frozen=True)
class StepFigures:
    """Response of ``P_IP`` to one step of ``P_ref`` (see the module docstring)."""

    t_s: float
    step_w: float
    p_ref_w: float
    rise_time_s: float | None
    settling_time_s: float | None
    overshoot_pct: float | None
    steady_error_w: float | None
    window_s: float


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

    steps: tuple[StepFigures, ...]
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


def _crossing(t: np.ndarray, y: np.ndarray, level: float) -> float | None:
    """First time ``y`` reaches ``level`` (from below), linearly interpolated; None if never."""
    above = np.nonzero(y >= level)[0]
    if above.size == 0:
        return None
    i = int(above[0])
    if i == 0:
        return float(t[0])
    t0, t1, y0, y1 = t[i - 1], t[i], y[i - 1], y[i]
    return float(t0 + (t1 - t0) * (level - y0) / (y1 - y0))


def step_figures(t_s: Sequence[float], y: Sequence[float], band: float = 0.05):
    """Rise time, settling time and overshoot of a normalised step response.

    Parameters
    ----------
    t_s : sequence of float
        Times from the step, s (increasing, starting at or after 0).
    y : sequence of float
        Response normalised to the step (0 before, 1 at the target).
    band : float
        Settling band as a fraction of the step.

    Returns
    -------
    (rise_time_s, settling_time_s, overshoot_pct)
        Each None where undefined (no samples, 90 % never reached, not settled at the end).
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size == 0:
        return None, None, None
    t10, t90 = _crossing(t, y, 0.1), _crossing(t, y, 0.9)
    rise = None if t10 is None or t90 is None else t90 - t10
    overshoot = max(0.0, 100.0 * (float(y.max()) - 1.0))
    outside = np.nonzero(np.abs(y - 1.0) > band)[0]
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] == t.size - 1:
        settling = None
    else:
        i = int(outside[-1])
        target = 1.0 + band if y[i] > 1.0 else 1.0 - band
        settling = float(t[i] + (t[i + 1] - t[i]) * (target - y[i]) / (y[i + 1] - y[i]))
    return rise, settling, overshoot


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
    t_ip = np.asarray(series.p_ip_t_ns, dtype=np.int64)
    p_ip = np.asarray(series.p_ip_w, dtype=float)
    order = np.argsort(t_ip, kind="stable")
    t_ip, p_ip = t_ip[order], p_ip[order]
    steps = []
    ref_t, ref_v = list(series.p_ref_t_ns), list(series.p_ref_w)
    ends = sorted([*ref_t, *(s["t_ns"] for s in series.switches), *series.disturbances_ns,
                   end_ns + 1])
    for k in range(1, len(ref_t)):
        t0 = ref_t[k]
        t1 = ends[int(np.searchsorted(ends, t0, side="right"))]
        before, after = ref_v[k - 1], ref_v[k]
        step = after - before
        if step == 0:
            continue
        inside = (t_ip >= t0) & (t_ip < t1)
        t_rel = (t_ip[inside] - t0) * 1e-9
        y = (p_ip[inside] - before) / step
        rise, settle, overshoot = step_figures(t_rel, y, band_pct / 100.0)
        steady = float(after - p_ip[inside][-1]) if inside.any() else None
        steps.append(StepFigures(t0 * 1e-9, step, after, rise, settle, overshoot, steady,
                                 (t1 - t0) * 1e-9))
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
    return RunSummary(tuple(steps), tuple(switches), band_pct, sim_s, wall_time_s, speed,
                      dict(extra or {}))


def format_summary(summary: RunSummary):
    """Rich renderables (tables and lines) of a summary, for the console."""
    from rich.table import Table

    def num(value, fmt):
        return "-" if value is None else format(value, fmt)

    out = []
    steps = Table(title=f"P_ref steps (P_IP; settling band {summary.band_pct:g} %)",
                  title_justify="left")
    for column in ("t [s]", "step [MW]", "rise [s]", "settling [s]", "overshoot [%]",
                   "steady error [W]"):
        steps.add_column(column, justify="right")
    for s in summary.steps:
        steps.add_row(f"{s.t_s:.2f}", f"{s.step_w / 1e6:+.3f}", num(s.rise_time_s, ".3f"),
                      num(s.settling_time_s, ".3f"), num(s.overshoot_pct, ".3f"),
                      num(s.steady_error_w, ".3g"))
    if not summary.steps:
        steps.add_row("", "no steps", "", "", "", "")
    out.append(steps)
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
