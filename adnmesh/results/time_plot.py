"""The paper-style time plot of a recorded run (``adnmesh plot``).

Top panel: P_ref (dashed steps) and the measured P_IP in MW over sim time; every time span in
which the set of available DERs differs from the first one is shaded grey and labelled with the
number available, faults are shaded
red (an instant fault is a red line). Second panel: the controller output P_Y. Third panel: the
active gains, K_P in 1/W (left axis) and K_I in 1/(W s) (right axis), both log scale, as steps;
gain switches are dotted vertical lines in every panel. With a grid model (``measurement/grid``
records) a fourth panel: the lowest and
highest bus voltage (p.u., left) and the highest line and transformer loading (%, right) per
report period, with the band of the config's ``grid_model.limits`` dotted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adnmesh.results.series import RunData

__all__ = ["plot_run", "save_plot"]


def _shade(ax, run: RunData, t_end_s: float, *, labels: bool) -> None:
    spans = run.availability_spans()
    if spans:
        initial = spans[0][2]
        shaded = False
        for start, end, available in spans:
            if available == initial:
                continue
            t0 = run.seconds(start)
            t1 = run.seconds(end) if end is not None else t_end_s
            ax.axvspan(t0, t1, color="0.85", zorder=0,
                       label=None if shaded or not labels else "availability changed")
            if not labels:
                continue
            ax.annotate(f"{len(available)} of {len(run.der_ids) or len(initial)} DERs available",
                        xy=(t0, 1.0), xycoords=("data", "axes fraction"),
                        xytext=(3, -3), textcoords="offset points", va="top", fontsize=8,
                        color="0.3")
            shaded = True
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


def plot_run(run: RunData, *, title: str | None = None):
    """Return a matplotlib Figure of ``run`` (see the module doc)."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

    grid = run.one("grid_v_min") is not None
    fig = Figure(figsize=(10, 10 if grid else 8), layout="constrained")
    axes = fig.subplots(4 if grid else 3, 1, sharex=True,
                        height_ratios=(3, 1.6, 1.6, 2) if grid else (3, 1.6, 1.6))
    top, bottom, gain_ax = axes[0], axes[1], axes[2]
    p_ref, p_ip, p_y = run.one("p_ref"), run.one("p_ip"), run.one("p_y")
    ends = [run.seconds(s.t_ns[-1]) for s in (p_ref, p_ip, p_y) if s is not None and s.t_ns.size]
    t_end = max(ends) if ends else 1.0

    _shade(top, run, t_end, labels=True)
    if p_ref is not None:
        t = np.append(run.seconds(p_ref.t_ns), t_end)
        top.step(t, np.append(p_ref.values, p_ref.values[-1]) / 1e6, where="post",
                 color="black", ls="--", lw=1.2, label="P_ref")
    if p_ip is not None:
        top.plot(run.seconds(p_ip.t_ns), p_ip.values / 1e6, color="tab:blue", lw=1.4,
                 label="P_IP")
    top.set_ylabel("active power at the IP [MW]")
    top.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=4, fontsize=8, frameon=False)
    top.grid(True, alpha=0.3)

    _shade(bottom, run, t_end, labels=False)
    if p_y is not None:
        bottom.plot(run.seconds(p_y.t_ns), p_y.values, color="tab:green", lw=1.2, label="P_Y")
    bottom.set_ylabel("controller output P_Y [-]")
    bottom.grid(True, alpha=0.3)
    _gains_panel(gain_ax, run, t_end)
    for event in (e for e in run.events if e.kind == "gain_switch"):
        for ax in axes:
            ax.axvline(run.seconds(event.t_ns), color="tab:purple", ls=":", lw=1.0)
    axes[-1].set_xlabel("sim time [s]")
    if grid:
        _grid_panel(axes[3], run, t_end)
    top.set_xlim(0 if run.t0_ns == 0 else None, t_end)
    if title:
        n = len(run.der_ids)
        fig.suptitle(f"{title}: {n} DERs, sim time {run.seconds(run.t0_ns):g}–{t_end:g} s"
                     if n else title, fontsize=10)
    return fig


def _gains_panel(ax, run: RunData, t_end: float) -> None:
    """The active gains as steps on one log axis: K_P in 1/W, K_I in 1/(W s)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    _shade(ax, run, t_end, labels=False)
    ax.grid(True, which="major", alpha=0.3)
    drawn = False
    for role, color, unit in (("kp", "tab:purple", "1/W"), ("ki", "tab:orange", "1/(W s)")):
        series = run.one(role)
        if series is None or not series.values.size or not np.all(series.values > 0):
            continue
        t = np.append(run.seconds(series.t_ns), t_end)
        name = "K_P" if role == "kp" else "K_I"
        ax.step(t, np.append(series.values, series.values[-1]), where="post", color=color,
                lw=1.4, label=f"{name} [{unit}]")
        drawn = True
    ax.set_ylabel("K_P, K_I (log scale)")
    if drawn:
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.0e}".replace("e-0", "e-")))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=2, fontsize=8,
                  frameon=False)


def _grid_panel(ax, run: RunData, t_end: float) -> None:
    """Bus voltage extremes (left) and the highest loadings (right), per report period."""
    for role, label in (("grid_v_min", "lowest bus voltage"), ("grid_v_max", "highest")):
        series = run.one(role)
        ax.step(run.seconds(series.t_ns), series.values, where="post", lw=1.0, label=label)
    ax.set_ylabel("bus voltage [p.u.]")
    ax.grid(True, alpha=0.3)
    loading = ax.twinx()
    for role, style in (("grid_line_loading", "-"), ("grid_trafo_loading", "--")):
        series = run.one(role)
        if series is not None:
            loading.step(run.seconds(series.t_ns), series.values, where="post", ls=style,
                         color="0.4", lw=1.0, label=series.name)
    loading.set_ylabel("loading [%]")
    handles = [h for a in (ax, loading) for h in a.get_legend_handles_labels()[0]]
    labels = [lab for a in (ax, loading) for lab in a.get_legend_handles_labels()[1]]
    ax.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=4, fontsize=8,
              frameon=False)


def save_plot(run: RunData, out_path: str | Path, *, title: str | None = None) -> Path:
    """Draw ``run`` with :func:`plot_run` and save it (format from the suffix: png, pdf, svg)."""
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    plot_run(run, title=title).savefig(out_path, dpi=150)
    return out_path
