"""Figure of the detailed DER models' step responses beside the reference PT1 (matplotlib Agg).

One panel per distinct (type, T_delay, T_rise) of the config (responses are normalised to the
step, so DERs that differ only in P_inst look the same): the detailed model's answers to steps
up (solid) and down (dotted; where they coincide with the steps up, the model is symmetric) of
two sizes, and the reference PT1's, dashed black; rise times in the legend. And the re-entry
transients of :mod:`adnmesh.dermodels.handover` (:func:`plot_handover`).
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from adnmesh.dermodels.responses import BASE_FRACTION, DerModelReport

__all__ = ["plot_der_models", "plot_handover", "distinct_reports"]

_COLOURS = {("up", 0): "#1f77b4", ("down", 0): "#d62728", ("up", 1): "#17becf",
            ("down", 1): "#ff7f0e"}


def distinct_reports(reports) -> list[tuple[DerModelReport, list[str]]]:
    """One report per distinct (type, T_delay, T_rise), with the ids of the DERs it stands for."""
    groups: dict[tuple, tuple[DerModelReport, list[str]]] = {}
    for r in reports:
        key = (r.der_type, r.t_delay_s, r.t_rise_s)
        groups.setdefault(key, (r, []))[1].append(r.der_id)
    return list(groups.values())


def plot_der_models(reports, path) -> Path:
    """Draw the step responses of ``reports`` (from :func:`der_model_report`) to ``path``."""
    groups = distinct_reports(reports)
    fig = Figure(figsize=(5.2 * len(groups), 4.4), layout="constrained")
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    for ax, (report, ids) in zip(axes, groups):
        sizes = sorted({r.step_fraction for r in report.responses})
        for resp in report.responses:
            colour = _COLOURS[(resp.direction, sizes.index(resp.step_fraction) % 2)]
            ax.plot(resp.t_s, resp.normalised, color=colour,
                    lw=1.6 if resp.direction == "up" else 2.4,
                    ls="-" if resp.direction == "up" else ":",
                    label=f"{resp.label}: t_r {resp.rise_time_s:.3g} s")
        ref = report.reference[0]
        ax.plot(ref.t_s, ref.normalised, "k--", lw=1.2,
                label=f"reference PT1: t_r {ref.rise_time_s:.3g} s")
        for level in (0.1, 0.9):
            ax.axhline(level, color="0.8", lw=0.6, zorder=0)
        ax.set_title(f"{report.model_name}\n{', '.join(ids)}", fontsize=9)
        ax.set_xlabel("time after the setpoint step [s]")
        ax.set_ylabel("(P - P_0) / (P_1 - P_0)")
        ax.set_ylim(-0.05, 1.1)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"DER models: setpoint steps from {100 * BASE_FRACTION:g} % of P_inst "
                 f"(T_delay, T_rise as in the config)", fontsize=10)
    path = Path(path)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=130)
    return path


def plot_handover(panels, path) -> Path:
    """Draw the re-entry transients (:mod:`adnmesh.dermodels.handover`): one panel per kind of
    returning DER (``panels``: ``(title, [HandoverResponse, ...])``), the two DERs' total
    infeed change while the share moves from each other kind, at once (dotted) and over the
    handover (solid)."""
    fig = Figure(figsize=(5.2 * len(panels), 4.4), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"]
    for ax, (title, responses) in zip(axes, panels):
        givers = list(dict.fromkeys(r.giver for r in responses))
        for r in responses:
            colour = colours[givers.index(r.giver) % len(colours)]
            how = "at once" if r.handover_s <= 0 else f"over {r.handover_s:.3g} s"
            ax.plot(r.t_s[1:], 100 * r.deviation[1:], color=colour,
                    ls=":" if r.handover_s <= 0 else "-", lw=1.4 if r.handover_s > 0 else 2.0,
                    label=f"from {r.giver}, {how}: {100 * r.largest:.3g} %")
        ax.axhline(0.0, color="0.6", lw=0.6, zorder=0)
        ax.set_title(title, fontsize=9)
        ax.set_xscale("log")
        ax.set_xlabel("time after the switch [s] (log)")
        ax.set_ylabel("change of the two infeeds' sum [% of the share]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.suptitle("Re-entry transient, open loop: a returning DER takes 10 % of the smaller "
                 "P_inst from another (the CPFC's loop corrects what is left)", fontsize=10)
    path = Path(path)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=130)
    return path
