"""The year study's figures, as PNG (matplotlib, Agg; docs/study.md#figures).

- ``duration.png``: duration curves of the controllable range and the linear range, up and
  down (MW over the share of the year at least that large), the service size marked;
- ``heatmap_rise.png`` and ``heatmap_range.png``: day × time of day of the entry's rise time
  and of the linear range both ways (the smaller of up and down);
- ``limits.png``: the extreme voltages and the largest loading per interval with their
  limits, the intervals the guard would act in marked;
- ``contribution.png``: per DER, the range lost without it and the share of its intervals
  whose service it alone made.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_figures"]


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from adnmesh.files import write_atomic
    FigureCanvasAgg(fig)
    return write_atomic(path, lambda fh: fig.savefig(fh, format="png", dpi=110))


def _duration(result, config):
    from matplotlib.figure import Figure

    col = result.columns
    fig = Figure(figsize=(8, 4.6), layout="constrained")
    ax = fig.add_subplot()
    n = len(result)
    share = (np.arange(1, n + 1) / n) * 100 if n else np.zeros(0)
    for key, label, style in (("range_up_w", "range up", "-"), ("range_down_w", "range down", "-"),
                              ("linear_up_w", "linear range up", "--"),
                              ("linear_down_w", "linear range down", "--")):
        ax.plot(share, np.sort(col[key])[::-1] * 1e-6, style, label=label)
    ax.axhline(config.study.service_w * 1e-6, color="k", lw=0.8, ls=":",
               label=f"service {config.study.service_w * 1e-6:g} MW")
    ax.set_xlabel("share of the intervals at least this large [%]")
    ax.set_ylabel("MW")
    ax.set_title(f"Controllable range of {config.grid}: duration curves\n"
                 f"({n} intervals; service ±{config.study.service_w * 1e-6:g} MW within "
                 f"{config.study.service_s:g} s: {np.mean(col['service']) * 100:.1f} %)")
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def _grid(result, values: np.ndarray):
    """``values`` per interval as days × intervals of a day (NaN where none)."""
    times = result.columns["time"].astype("datetime64[m]")
    per_day = max(int(round(86400 / result.step_s)), 1)
    day0 = times[0].astype("datetime64[D]")
    day = (times.astype("datetime64[D]") - day0).astype(int)
    slot = ((times - times.astype("datetime64[D]")).astype(int) * 60 // int(result.step_s))
    grid = np.full((day.max() + 1, per_day), np.nan)
    grid[day, np.clip(slot, 0, per_day - 1)] = values
    return grid, day0


def _heatmap(result, values, title, label, cmap):
    from matplotlib.figure import Figure

    grid, day0 = _grid(result, values)
    fig = Figure(figsize=(9, 4.6), layout="constrained")
    ax = fig.add_subplot()
    image = ax.imshow(grid.T, aspect="auto", origin="lower", cmap=cmap, interpolation="nearest",
                      extent=(0, grid.shape[0], 0, 24))
    fig.colorbar(image, ax=ax, label=label)
    ax.set_xlabel(f"day from {day0}")
    ax.set_ylabel("time of day [h]")
    ax.set_yticks(range(0, 25, 6))
    ax.set_title(title)
    return fig


def _limits(result, config):
    from matplotlib.figure import Figure

    col = result.columns
    lim = config.grid_model.limits
    days = (col["time"].astype("datetime64[m]") - col["time"][0].astype("datetime64[m]")
            ).astype(float) / 1440.0
    fig = Figure(figsize=(9, 5.4), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(days, col["vm_max_pu"], lw=0.5, label="highest voltage")
    top.plot(days, col["vm_min_pu"], lw=0.5, label="lowest voltage")
    for level in (lim.v_min_pu, lim.v_max_pu):
        top.axhline(level, color="r", lw=0.8, ls="--")
    top.set_ylabel("p.u.")
    top.legend(loc="upper right")
    top.set_title(f"Grid limits over the intervals: limited (guard acts) "
                  f"{np.mean(col['limited']) * 100:.2f} %, violated "
                  f"{np.mean(col['violated']) * 100:.2f} %")
    bottom.plot(days, np.fmax(col["line_max_pct"], col["trafo_max_pct"]), lw=0.5,
                label="largest loading")
    bottom.axhline(lim.loading_max_pct, color="r", lw=0.8, ls="--")
    limited = np.flatnonzero(col["limited"])
    if limited.size:
        for ax in (top, bottom):
            ax.plot(days[limited], np.full(limited.size, ax.get_ylim()[0]), "|", color="C3",
                    label="limited" if ax is bottom else None)
    bottom.set_ylabel("%")
    bottom.set_xlabel("days")
    bottom.legend(loc="upper right")
    return fig


def _contribution(result):
    from matplotlib.figure import Figure

    from adnmesh.study.outputs import der_rows
    rows = der_rows(result)
    names = [r["der"] for r in rows]
    x = np.arange(len(names))
    fig = Figure(figsize=(max(6, 0.6 * len(names) + 3), 5), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.bar(x - 0.2, [r["range_up_lost_mw"] for r in rows], 0.4, label="range up lost")
    top.bar(x + 0.2, [r["range_down_lost_mw"] for r in rows], 0.4, label="range down lost")
    top.set_ylabel("MW (mean over its intervals)")
    top.legend()
    top.set_title("What the year loses without each DER (intervals it is available in)")
    bottom.bar(x, [r["service_lost_share"] * 100 for r in rows], 0.6, color="C2")
    bottom.set_ylabel("service lost [%]")
    bottom.set_xticks(x, names, rotation=45 if len(names) > 12 else 0)
    return fig


def write_figures(result, config, out_dir: Path) -> list[Path]:
    """Write the figures into ``out_dir``; return their paths."""
    if len(result) == 0:
        return []
    col = result.columns
    both = np.fmin(col["linear_up_w"], col["linear_down_w"]) * 1e-6
    figures = {
        "duration.png": _duration(result, config),
        "heatmap_rise.png": _heatmap(result, col["rise_s"], "Rise time of the entry in use",
                                     "rise time 10-90 % [s]", "viridis_r"),
        "heatmap_range.png": _heatmap(result, both, "Linear range both ways (the smaller of "
                                      "up and down)", "MW", "viridis"),
        "limits.png": _limits(result, config),
        "contribution.png": _contribution(result),
    }
    return [_save(fig, Path(out_dir) / name) for name, fig in figures.items()]
