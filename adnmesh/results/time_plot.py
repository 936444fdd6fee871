"""The paper-style time plot of a recorded run (``adnmesh plot``).

Panels over sim time, in the units of :data:`adnmesh.results.rules.DISPLAY_UNITS`:

1. P_ref (dashed steps) and the measured P_IP in MW; every time span in which the set of
   available DERs differs from the first one is shaded grey and labelled with the number
   available (labels stacked where they would overlap, kept inside the axes), faults are
   shaded red (an instant fault is a red line);
2. every DER's infeed (solid) and set-point (dashed, a lighter shade of the DER's colour) in
   MW, every DER in the legend;
3. the controller output P_Y (per unit of each DER's ``w·P_inst``);
4. the active gains as steps on a log axis, K_P in 1/MW and K_I in 1/(MW s), with ticks below
   and above both;
5. with a grid model (``measurement/grid`` records): the lowest and highest bus voltage per
   report period (p.u.; the slack's voltage is not among them, see
   :mod:`adnmesh.grid.solver`) with the configured band (``grid_model.limits``) dashed;
6. the highest line and transformer loading (%) with the loading limit dashed;
7. Q_IP (Mvar) at the end of each report period.

Gain switches are dotted vertical lines in every panel; every axis has its own legend.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from adnmesh.results.rules import der_colors, lighter, natural_key
from adnmesh.results.series import RunData, Series

__all__ = ["plot_run", "save_plot"]

_TICK_MARGIN = 1.15
"""On the gains' log axis, a value lies at least this factor inside the outermost ticks."""

_LABEL_ROWS = 3
"""Availability labels are stacked in up to this many rows where they would overlap."""


def _rgb(color: tuple[int, int, int]) -> tuple[float, float, float]:
    return tuple(c / 255 for c in color)


def _shade(ax, run: RunData, t_end_s: float, *, labels: bool) -> None:
    spans = run.availability_spans()
    if spans:
        initial = spans[0][2]
        shaded = False
        placed: list[tuple[float, float, int]] = []      # (x0, x1, row) of the labels, axes
        t_start = run.seconds(run.t0_ns) if run.t0_ns else 0.0
        for start, end, available in spans:
            if available == initial:
                continue
            t0 = run.seconds(start)
            t1 = run.seconds(end) if end is not None else t_end_s
            ax.axvspan(t0, t1, color="0.85", zorder=0,
                       label=None if shaded or not labels else "availability changed")
            shaded = True
            if labels:
                total = len(run.der_ids) or len(initial)
                _label_span(ax, f"{len(available)} of {total} DERs available",
                            (t0 - t_start) / max(t_end_s - t_start, 1e-9), placed)
    labelled = False
    for start, end, _ in run.fault_spans():
        t0 = run.seconds(start)
        label = None if labelled or not labels else "fault"
        if end is None or end > start:
            t1 = run.seconds(end) if end is not None else t_end_s
            ax.axvspan(t0, t1, color="tab:red", alpha=0.2, zorder=0, label=label)
        else:
            ax.axvline(t0, color="tab:red", lw=1.0, label=label)
        labelled = True


def _label_span(ax, text: str, x: float, placed: list[tuple[float, float, int]]) -> None:
    """Write ``text`` at the axes fraction ``x`` (a span's start), inside the axes: right-aligned
    where it would run off the right edge, one row lower where it would overlap a label."""
    fig_width_in = ax.figure.get_size_inches()[0]
    width = len(text) * 0.55 * 8 / 72 / (0.85 * fig_width_in)      # 8 pt text, axes fraction
    x0 = min(max(x, 0.0) + 0.004, 1.0 - width - 0.004)
    rows_used = {row for a, b, row in placed if a < x0 + width and x0 < b}
    row = next((r for r in range(_LABEL_ROWS) if r not in rows_used), len(placed) % _LABEL_ROWS)
    placed.append((x0, x0 + width, row))
    ax.text(x0, 0.98 - 0.09 * row, text, transform=ax.transAxes, ha="left", va="top",
            fontsize=8, color="0.25", clip_on=True,
            bbox={"facecolor": "white", "alpha": 0.6, "edgecolor": "none", "pad": 1.0})


def plot_run(run: RunData, *, title: str | None = None, limits=None):
    """Return a matplotlib Figure of ``run`` (see the module doc); ``limits`` (the config's
    ``grid_model.limits``, e.g. :func:`~adnmesh.results.series.recorded_grid_limits`) is drawn
    in the grid panels."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

    grid = run.one("grid_v_min") is not None
    ders = bool(run.by_role("der_infeed") or run.by_role("der_setpoint"))
    q_ip = run.one("q_ip") is not None
    panels = ["power", *(["ders"] if ders else []), "p_y", "gains",
              *(["voltage", "loading"] if grid else []), *(["q_ip"] if q_ip else [])]
    heights = {"power": 2.8, "ders": 2.4, "p_y": 1.3, "gains": 1.4, "voltage": 1.5,
               "loading": 1.4, "q_ip": 1.1}
    fig = Figure(figsize=(11, 2.2 + 1.25 * sum(heights[p] for p in panels)),
                 layout="constrained")
    axes = fig.subplots(len(panels), 1, sharex=True,
                        height_ratios=[heights[p] for p in panels])
    ax = dict(zip(panels, axes))
    p_ref, p_ip, p_y = run.one("p_ref"), run.one("p_ip"), run.one("p_y")
    ends = [run.seconds(s.t_ns[-1]) for s in (p_ref, p_ip, p_y) if s is not None and s.t_ns.size]
    t_end = max(ends) if ends else 1.0

    top = ax["power"]
    _shade(top, run, t_end, labels=True)
    if p_ref is not None:
        _step(top, run, p_ref, t_end, color="black", ls="--", lw=1.2, label=p_ref.label)
    if p_ip is not None:
        top.plot(run.seconds(p_ip.t_ns), p_ip.shown(), color="tab:blue", lw=1.4,
                 label=p_ip.label)
    top.set_ylabel("active power at the IP [MW]")
    _legend(top, ncols=4)
    if ders:
        _ders_panel(ax["ders"], run, t_end)

    bottom = ax["p_y"]
    _shade(bottom, run, t_end, labels=False)
    if p_y is not None:
        bottom.plot(run.seconds(p_y.t_ns), p_y.shown(), color="tab:green", lw=1.2,
                    label="P_Y")
    bottom.set_ylabel("P_Y [p.u. of w·P_inst]")
    _gains_panel(ax["gains"], run, t_end)
    if grid:
        _voltage_panel(ax["voltage"], run, t_end, limits)
        _loading_panel(ax["loading"], run, t_end, limits)
    if q_ip:
        _q_ip_panel(ax["q_ip"], run, t_end)
    for event in (e for e in run.events if e.kind == "gain_switch"):
        for a in axes:
            a.axvline(run.seconds(event.t_ns), color="tab:purple", ls=":", lw=1.0)
    for a in axes:
        a.grid(True, which="major", alpha=0.3)
    axes[-1].set_xlabel("sim time [s]")
    top.set_xlim(0 if run.t0_ns == 0 else None, t_end)
    if title:
        n = len(run.der_ids)
        fig.suptitle(f"{title}: {n} DERs, sim time {run.seconds(run.t0_ns):g}–{t_end:g} s"
                     if n else title, fontsize=10)
    return fig


def _legend(ax, *, ncols: int, loc: str = "lower left", anchor=(0.0, 1.0), handles=None,
            labels=None):
    """A legend of ``ax`` alone, above it (lower left: at its left edge)."""
    args = () if handles is None else (handles, labels)
    return ax.legend(*args, loc=loc, bbox_to_anchor=anchor, ncols=ncols, fontsize=8,
                     frameon=False, borderaxespad=0.2)


def _step(ax, run: RunData, series: Series, t_end: float, **style) -> None:
    """``series`` (shown units) as steps held to ``t_end``."""
    values = series.shown()
    ax.step(np.append(run.seconds(series.t_ns), t_end), np.append(values, values[-1]),
            where="post", **style)


def _ders_panel(ax, run: RunData, t_end: float) -> None:
    """Every DER's infeed (solid) and set-point (dashed, lighter) in MW; one legend entry
    per DER in its colour, and one per line style."""
    from matplotlib.lines import Line2D

    _shade(ax, run, t_end, labels=False)
    by_der: dict[str, dict[str, Series]] = {}
    for role in ("der_infeed", "der_setpoint"):
        for series in run.by_role(role):
            by_der.setdefault(series.der or series.name, {})[role] = series
    colors = der_colors(by_der)
    handles = []
    for der in sorted(by_der, key=natural_key):
        color = colors[der]
        setpoint = by_der[der].get("der_setpoint")
        if setpoint is not None and setpoint.t_ns.size:
            _step(ax, run, setpoint, t_end, color=_rgb(lighter(color)), ls="--", lw=1.0)
        infeed = by_der[der].get("der_infeed")
        if infeed is not None and infeed.t_ns.size:
            ax.plot(run.seconds(infeed.t_ns), infeed.shown(), color=_rgb(color), lw=1.2)
        handles.append(Line2D([], [], color=_rgb(color), lw=2.0, label=der))
    handles += [Line2D([], [], color="0.2", lw=1.2, label="infeed"),
                Line2D([], [], color="0.6", lw=1.0, ls="--", label="set-point")]
    _legend(ax, ncols=min(len(handles), 9), handles=handles,
            labels=[h.get_label() for h in handles])
    ax.set_ylabel("DER infeed, set-point [MW]")


def _log_limits(low: float, high: float) -> tuple[float, float, list[float]]:
    """Axis limits on the 1-2-5 ticks just outside ``low`` and ``high`` (> 0), widened until
    at least four ticks lie between them, and those ticks: every value drawn lies strictly
    between two labelled ticks."""
    first, last = math.floor(math.log10(low)) - 3, math.ceil(math.log10(high)) + 3
    found = sorted(s * 10.0 ** e for e in range(first, last + 1) for s in (1.0, 2.0, 5.0))
    lo = max(i for i, t in enumerate(found) if t < low / _TICK_MARGIN)
    hi = min(i for i, t in enumerate(found) if t > high * _TICK_MARGIN)
    while hi - lo + 1 < 4:
        lo, hi = (lo - 1, hi) if (hi - lo) % 2 else (lo, hi + 1)
    return found[lo], found[hi], found[lo:hi + 1]


def _gains_panel(ax, run: RunData, t_end: float) -> None:
    """The active gains as steps on one log axis: K_P in 1/MW, K_I in 1/(MW s)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter, NullLocator

    _shade(ax, run, t_end, labels=False)
    drawn = []
    for role, color in (("kp", "tab:purple"), ("ki", "tab:orange")):
        series = run.one(role)
        if series is None or not series.values.size or not np.all(series.values > 0):
            continue
        _step(ax, run, series, t_end, color=color, lw=1.4, label=series.label)
        drawn.append(series.shown())
    ax.set_ylabel("K_P, K_I (log scale)")
    if drawn:
        values = np.concatenate(drawn)
        low, high, ticks = _log_limits(float(values.min()), float(values.max()))
        ax.set_yscale("log")
        ax.set_ylim(low, high)
        ax.yaxis.set_major_locator(FixedLocator(ticks))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_locator(NullLocator())
        ax.yaxis.set_minor_formatter(NullFormatter())
        _legend(ax, ncols=2)


def _voltage_panel(ax, run: RunData, t_end: float, limits) -> None:
    """The lowest and highest bus voltage per report period, with the configured band."""
    _shade(ax, run, t_end, labels=False)
    for role, color in (("grid_v_min", "tab:orange"), ("grid_v_max", "tab:blue")):
        series = run.one(role)
        if series is not None and series.t_ns.size:
            _step(ax, run, series, t_end, color=color, lw=1.1, label=series.name)
    if limits is not None:
        for value, which in ((limits.v_min_pu, "lowest"), (limits.v_max_pu, "highest")):
            ax.axhline(value, color="tab:red", ls="--", lw=0.9,
                       label=f"band: {which} allowed ({value:g} p.u.)")
    ax.set_ylabel("bus voltage [p.u.]")
    _legend(ax, ncols=4)
    tap = run.one("tap_pos")
    if tap is not None and tap.t_ns.size:             # the tap changer's steps, on the right
        right = ax.twinx()
        _step(right, run, tap, t_end, color="tab:cyan", lw=1.0, label=tap.name)
        right.set_ylabel("tap position")
        right.yaxis.get_major_locator().set_params(integer=True)


def _loading_panel(ax, run: RunData, t_end: float, limits) -> None:
    """The highest line and transformer loadings (%) with the limit."""
    _shade(ax, run, t_end, labels=False)
    for role, style in (("grid_line_loading", "-"), ("grid_trafo_loading", "--")):
        series = run.one(role)
        if series is not None and series.t_ns.size:
            _step(ax, run, series, t_end, ls=style, color="0.35", lw=1.0, label=series.name)
    if limits is not None:
        ax.axhline(limits.loading_max_pct, color="tab:red", ls="--", lw=0.9,
                   label=f"loading limit ({limits.loading_max_pct:g} %)")
    ax.set_ylabel("loading [%]")
    _legend(ax, ncols=3)


def _q_ip_panel(ax, run: RunData, t_end: float) -> None:
    """The reactive power at the IP (Mvar, MV -> HV positive) and, with reactive power
    control, its reference Q_ref."""
    _shade(ax, run, t_end, labels=False)
    q_ip, q_ref = run.one("q_ip"), run.one("q_ref")
    if q_ref is not None:
        _step(ax, run, q_ref, t_end, color="black", ls="--", lw=1.2, label=q_ref.label)
    if q_ip.t_ns.size:
        _step(ax, run, q_ip, t_end, color="tab:pink", lw=1.1, label=q_ip.label)
    if q_ref is not None:
        _legend(ax, ncols=2)
    ax.set_ylabel(f"Q_IP [{q_ip.display_unit}]")


def save_plot(run: RunData, out_path: str | Path, *, title: str | None = None,
              limits=None) -> Path:
    """Draw ``run`` with :func:`plot_run` and save it (format from the suffix: png, pdf, svg)."""
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    plot_run(run, title=title, limits=limits).savefig(out_path, dpi=150)
    return out_path
