"""Figures of the analyses (matplotlib, Agg canvas: no display and no pyplot state).

Each function draws one result and writes it to ``path`` (format from the suffix).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from adnmesh.analysis.coupling import CouplingResult
from adnmesh.analysis.pq_region import PQRegion, binding_words, edge_words, q_range_var
from adnmesh.analysis.robustness import METRICS, RobustnessResult
from adnmesh.analysis.solution_space import REASONS, SolutionSpace
from adnmesh.analysis.uncertainty import B_RANGE, MODEL_LABELS, QUANTITY_LABELS, UncertaintyResult

__all__ = ["plot_coupling", "plot_pq_region", "plot_robustness", "plot_uncertainty",
           "plot_solution_space", "COLOURS"]

COLOURS = {"adaptive": "#1f77b4", "static": "#ff7f0e"}
_LOG_METRICS = {"rise_time_s", "settling_time_s", "gain_margin", "delay_margin_s"}


def _plain_log_ticks(ax) -> None:
    """Log y axis with plain numbers (0.5, 2, 30, not 5×10⁻¹): 1-2-5 ticks, no minor labels."""
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _covers(n_subsets: int, covers: str) -> str:
    """``"<n> subsets"`` plus what they come from (config, table), for a figure's title."""
    return f"{n_subsets} subsets" + (f" of {covers}" if covers else "")


def _save(fig: Figure, path) -> Path:
    path = Path(path)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=130)
    return path


def plot_robustness(result: RobustnessResult, path, outliers: bool = False, unit: str = "W",
                    covers: str = "") -> Path:
    """Box plots of every metric, adaptive and static side by side; ``covers`` names where the
    subsets come from (e.g. ``"simbench.yaml, paper table"``) for the title; ``unit`` the
    controlled quantity's (``W``, ``var``) in the gains' units."""
    fig = Figure(figsize=(15, 7.5), layout="constrained")
    axes = fig.subplots(2, 4).ravel()
    for ax, metric in zip(axes, METRICS):
        data, notes = [], []
        ctrls = result.controllers
        for ctrl in ctrls:
            v = np.asarray(getattr(result, ctrl)[metric.key], float)
            data.append(v[np.isfinite(v)])
            no_pair = int((~getattr(result, f"{ctrl}_batch").has_gains).sum())
            counts = {"infinite": int(np.isinf(v).sum()), "without PI pair": no_pair,
                      "unstable": int(np.isnan(v).sum()) - no_pair}
            what = [f"{n} {k}" for k, n in counts.items() if n > 0]
            if what:
                notes.append(f"{ctrl}: {', '.join(what)} (not shown)")
        boxes = ax.boxplot([d if d.size else [np.nan] for d in data], showfliers=outliers,
                           patch_artist=True, widths=0.55, medianprops={"color": "black"})
        ax.set_xticks(list(range(1, len(ctrls) + 1)), list(ctrls))
        for patch, ctrl in zip(boxes["boxes"], ctrls):
            patch.set_facecolor(COLOURS[ctrl])
            patch.set_alpha(0.75)
        label = metric.label
        if metric.key == "settling_time_s":
            label = f"settling time ({result.band_pct:g} % band) [s]"
        ax.set_title(label, fontsize=10)
        if metric.key in _LOG_METRICS and all(d.size and np.all(d > 0) for d in data):
            ax.set_yscale("log")
            _plain_log_ticks(ax)
        else:
            ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.grid(True, axis="y", alpha=0.3)
        if notes:
            ax.text(0.02, 0.98, "\n".join(notes), transform=ax.transAxes, va="top",
                    fontsize=7, color="0.35")
    info = axes[-1]
    info.axis("off")
    sb = result.static_batch
    lines = [f"{len(result.subsets)} subsets",
             "adaptive: table gains and weights per subset",
             ("static: none in the table" if sb is None else
              f"static: K_P = {sb.kp[0]:.3g} 1/{unit}, K_I = {sb.ki[0]:.3g} 1/({unit} s)"),
             "unstable: " + ", ".join(f"{c} {len(result.unstable(c))}" for c in ctrls),
             f"without a PI pair in the table: {len(result.without_gains())}",
             "reference model (PT1), exact delays",
             "outliers shown" if outliers else "outliers hidden (whiskers 1.5 IQR)"]
    info.text(0.0, 0.95, "\n".join(lines), va="top", fontsize=9)
    info.legend(handles=[Patch(color=COLOURS[c], alpha=0.75, label=c) for c in ctrls],
                loc="lower left")
    ctrl_text = " and ".join(("adaptive (table gains)" if c == "adaptive" else
                              "static (one pair)") for c in ctrls)
    fig.suptitle(f"Robustness and performance over {_covers(len(result.subsets), covers)}: "
                 f"{ctrl_text}")
    return _save(fig, path)


def plot_uncertainty(results: list[UncertaintyResult], path, covers: str = "") -> Path:
    """Ranges of b without failure per model and quantity, one panel per controller
    (``covers``: where the subsets come from, for the title)."""
    fig = Figure(figsize=(6.5 * len(results), 5.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(results), sharex=True, sharey=True))
    lo_edge, hi_edge = B_RANGE
    colours = {"stability": "#2ca02c", "rise_time": "#1f77b4", "settling_time": "#9467bd"}
    for ax, res in zip(axes, results):
        labels, pos, y = [], [], 0.0
        for ml in res.models:
            for q, (down, up) in ml.limits.items():
                labels.append(f"{MODEL_LABELS[ml.model]}  {QUANTITY_LABELS[q]}")
                pos.append(y)
                y += 1
                if "no subsets" in (down.status, up.status):
                    continue
                if "at nominal" in (down.status, up.status):
                    ax.plot([1.0], [pos[-1]], "x", color="red", ms=9, mew=2)
                    ax.text(1.08, pos[-1] + 0.18, "fails at b = 1", fontsize=7, color="red")
                    continue
                b_lo = down.b if down.status == "found" else lo_edge
                b_hi = up.b if up.status == "found" else hi_edge
                ax.plot([b_lo, b_hi], [pos[-1]] * 2, lw=6, color=colours[q],
                        solid_capstyle="butt", alpha=0.85)
                for b, lim, ha in ((b_lo, down, "right"), (b_hi, up, "left")):
                    ax.text(b * (0.93 if ha == "right" else 1.07), pos[-1], lim.text(), ha=ha,
                            va="center", fontsize=7)
            y += 0.5
        ax.axvline(1.0, color="0.3", ls="--", lw=1)
        ax.set_xscale("log")
        ax.set_xlim(lo_edge / 3, hi_edge * 3)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.set_yticks(pos, labels, fontsize=8)
        ax.set_xlabel("b  (T_unc = b · T)")
        n = len(res.names) - len(res.excluded) - len(res.without_gains)
        ax.set_title(f"{res.controller} controller: b without failure ({n} subsets)",
                     fontsize=10)
        ax.grid(True, axis="x", which="both", alpha=0.25)
    axes[0].invert_yaxis()              # shared: first model on top in every panel
    where = f" of {covers}" if covers else ""
    fig.suptitle(f"Model uncertainty{where}: stability and doubling limits per controller "
                 "(reference: nominal PT1 of each subset)", fontsize=10)
    return _save(fig, path)


_REASON_COLOURS = {"unstable": "#7f7f7f", "disk margin": "#f4a582", "overshoot": "#fddbc7",
                   "": "#4dac26"}


def plot_solution_space(space: SolutionSpace, path, covers: str = "", unit: str = "W") -> Path:
    """Feasibility classes and rise time over the (K_P, K_I) plane, search path on top
    (``covers``: the config and table, for the title). Markers that can coincide (table entry,
    path result, grid optimum) differ in shape, colour and fill, the larger drawn first;
    ``unit``: the controlled quantity's (``W``, ``var``) in the gains' axes."""
    fig = Figure(figsize=(13, 5.5), layout="constrained")
    ax_f, ax_r = fig.subplots(1, 2, sharex=True, sharey=True)
    codes = np.zeros(space.reason.shape, int)
    for i, r in enumerate(REASONS):
        codes[space.reason == r] = i
    cmap = ListedColormap([_REASON_COLOURS[r] for r in REASONS])
    ax_f.pcolormesh(space.kp, space.ki, codes, cmap=cmap,
                    norm=BoundaryNorm(np.arange(len(REASONS) + 1) - 0.5, len(REASONS)),
                    shading="nearest")
    counts = space.counts()
    ax_f.legend(handles=[Patch(color=_REASON_COLOURS[r],
                               label=f"{r or 'feasible'} ({counts[r or 'feasible']})")
                         for r in REASONS], loc="lower left", fontsize=8)
    rise = np.where(space.feasible, space.rise_time_s, np.nan)
    ax_r.pcolormesh(space.kp, space.ki, np.where(space.feasible, np.nan, 0.0),
                    cmap=ListedColormap(["#dddddd"]), shading="nearest")
    if np.isfinite(rise).any():
        lo, hi = np.nanmin(rise), np.nanmax(rise)
        mesh = ax_r.pcolormesh(space.kp, space.ki, rise, cmap="viridis_r", shading="nearest",
                               norm=LogNorm(lo, max(hi, lo * 1.01)))
        fig.colorbar(mesh, ax=ax_r, label="rise time 10–90 % [s] (feasible points)")
    c = space.constraints or {}
    ax_f.set_title(f"feasibility (α ≥ {c.get('disk_margin_min', float('nan')):g}, "
                   f"overshoot < {c.get('overshoot_max_pct', float('nan')):g} %)", fontsize=10)
    ax_r.set_title("rise time where feasible (grey: infeasible)", fontsize=10)
    best = space.best()
    for ax in (ax_f, ax_r):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"K_P [1/{unit}]")
        if space.table_point is not None:
            ax.plot(*space.table_point, "*", ms=18, color="gold", mec="black", zorder=5,
                    label="table entry")
        if space.path:
            p = np.array([(k, i) for k, i, _ in space.path])
            ok = np.array([f for _, _, f in space.path], bool)
            ax.plot(p[:, 0], p[:, 1], "-", color="black", lw=0.8, label="paper search path")
            ax.plot(p[ok, 0], p[ok, 1], "o", ms=2.5, color="white", mec="black", mew=0.5)
            ax.plot(p[~ok, 0], p[~ok, 1], "x", ms=3, color="black", mew=0.6)
            ax.plot(*p[0], "s", ms=7, color="black", zorder=5, label="path start")
            if ok.any():
                ax.plot(*p[ok][-1], "^", ms=8, color="red", mec="black", zorder=6,
                        label="path result (last feasible point)")
        if best is not None:
            ax.plot(best[0], best[1], "o", ms=13, mfc="none", mec="magenta", mew=2.0,
                    zorder=7, label=f"grid optimum ({best[2]:.3g} s)")
    ax_f.set_ylabel(f"K_I [1/({unit} s)]")
    handles, labels = ax_r.get_legend_handles_labels()
    if handles:
        ax_r.legend(handles, labels, loc="lower left", fontsize=8)
    note = "" if space.path else "  (no search path: adnmesh.tuning.paper_path unavailable)"
    where = f" ({covers})" if covers else ""
    fig.suptitle(f"Solution space of the subset {{{space.name}}}{where}: "
                 f"{space.p_inst_w / 1e6:.4g} MW, weights 1{note}", fontsize=11)
    return _save(fig, path)


def plot_coupling(result: CouplingResult, path, covers: str = "") -> Path:
    """|M(jω)| of the coupled P-Q loop against the small-gain bound 1, and the cross
    transfers Q_ref → P_IP and P_ref → Q_IP (:mod:`adnmesh.analysis.coupling`)."""
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    ax_m, ax_x = fig.subplots(1, 2)
    ax_m.loglog(result.omega, np.abs(result.m), color="tab:purple", label="|M(jω)|")
    ax_m.axhline(1.0, color="tab:red", ls="--", lw=1, label="small-gain bound 1")
    ax_m.plot(result.mu_omega, result.mu, "o", color="black",
              label=f"max {result.mu:.3g} at {result.mu_omega:.3g} rad/s")
    ax_m.set_xlabel("ω [rad/s]")
    ax_m.set_ylabel("|M(jω)|")
    ax_m.set_title("coupling of the two loops" + (" (stable)" if result.stable else
                                                   " (NOT shown stable)"), fontsize=10)
    ax_m.legend(fontsize=8, loc="lower left")
    ax_x.loglog(result.omega, result.q_into_p, color="tab:blue", label="Q_ref → P_IP [W/var]")
    ax_x.loglog(result.omega, result.p_into_q, color="tab:orange", label="P_ref → Q_IP [var/W]")
    ax_x.set_xlabel("ω [rad/s]")
    ax_x.set_title("cross transfers (the other loop open)", fontsize=10)
    ax_x.legend(fontsize=8, loc="lower left")
    for ax in (ax_m, ax_x):
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("P and Q loops together: the coupled 2×2 loop, exact delays"
                 + (f"\n{covers}" if covers else ""), fontsize=10)
    return _save(fig, path)


_BINDING_STYLE = {"v_max": ("^", "tab:red"), "v_min": ("v", "tab:purple"),
                  "loading": ("s", "tab:orange")}


def plot_pq_region(region: PQRegion, path, operating_point: tuple[float, float] | None = None,
                   covers: str = "") -> Path:
    """The feasible P-Q region at the interconnection point (:mod:`adnmesh.analysis.pq_region`)
    beside the region under DER capability alone; support points where a grid limit binds
    marked by kind, with the elements named; ``operating_point`` (P_IP W, Q_IP var) with the
    region's Q range there; ``covers``: the config and grid, for the title. Axes in MW and
    Mvar."""
    fig = Figure(figsize=(8.5, 8.0), layout="constrained")
    ax = fig.add_subplot()
    bare = region.without_limits
    if bare is not None:
        _polygon(ax, bare.vertices, dict(fc="0.92", ec="0.35", ls="--", lw=1.2,
                                         label="DER capability only"))
    limits = region.limits
    label = "with grid limits" + ("" if limits is None else
                                   f" (v in [{limits.v_min_pu:g}, {limits.v_max_pu:g}] p.u., "
                                   f"loading ≤ {limits.loading_max_pct:g} %)")
    _polygon(ax, region.vertices, dict(fc="tab:blue", alpha=0.35, ec="tab:blue", lw=1.5,
                                       label=label))
    binding = region.binding_limits()
    for kind, elements in binding.items():
        marker, colour = _BINDING_STYLE.get(kind, ("o", "black"))
        at = np.array([[s.p_ip_w, s.q_ip_var] for s in region.support
                       if any(b.startswith(kind + " ") for b in s.binding)]) / 1e6
        ax.plot(at[:, 0], at[:, 1], marker, ls="none", color=colour, mec="black", mew=0.5,
                ms=6, zorder=5, label=f"{binding_words({kind: elements})} binds")
    if operating_point is not None:
        p, q = operating_point
        span = q_range_var(region, p)
        if span is not None:
            ax.plot([p / 1e6] * 2, np.array(span) / 1e6, color="black", lw=1.5,
                    marker="_", ms=12, zorder=4,
                    label=f"Q range at the operating P: {span[0] / 1e6:.3f} to "
                          f"{span[1] / 1e6:.3f} Mvar")
        ax.plot(p / 1e6, q / 1e6, "X", ms=11, color="gold", mec="black", zorder=6,
                label=f"operating point (DERs at their schedules): {p / 1e6:.3f} MW, "
                      f"{q / 1e6:.3f} Mvar")
    ax.set_xlabel("P_IP [MW] (MV → HV positive)")
    ax.set_ylabel("Q_IP [Mvar] (MV → HV positive)")
    ax.grid(True, alpha=0.3)
    ax.margins(0.06)
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", fontsize=8)
    lo, hi = region.p_span_w()
    qlo, qhi = region.q_span_var()
    lines = [f"P_IP {lo / 1e6:.3f} to {hi / 1e6:.3f} MW, Q_IP {qlo / 1e6:.3f} to "
             f"{qhi / 1e6:.3f} Mvar; {len(region.support)} support points, edges within "
             f"{region.boundary_error_w / 1e3:.2g} kW (kvar)", edge_words(region),
             *region.notes]
    fig.suptitle("Feasible P-Q region at the interconnection point"
                 + (f"\n{covers}" if covers else ""), fontsize=11)
    ax.set_title("\n".join(lines), fontsize=8)
    return _save(fig, path)


def _polygon(ax, vertices: np.ndarray, style: dict) -> None:
    """A region's polygon in MW and Mvar (a segment or a point as a line or a marker)."""
    from matplotlib.patches import Polygon

    xy = np.asarray(vertices, float) / 1e6
    if len(xy) >= 3:
        ax.add_patch(Polygon(xy, closed=True, **style))
        ax.autoscale_view()
    else:
        ax.plot(xy[:, 0], xy[:, 1], "o-", color=style.get("ec", "black"),
                label=style.get("label"))
