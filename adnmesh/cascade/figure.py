"""The picture of an upper table: each entry's step on the exact cascade beside the loop its
equivalent models predicted.

One panel per entry shown (the entry for all ADNs, then each ADN alone): the upper reference
step's response of the exact cascade under the entry's certified gains (solid), each ADN's
share of it (thin), and the loop of the equivalent models under the same gains (dashed), with
the overshoot band of the constraint.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from adnmesh.cascade.nested_step import simulate
from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.step_response import simulate_step

__all__ = ["plot_entries"]


def plot_entries(panels: list[tuple[str, Cascade, Plant, float, float, float]],
                 overshoot_max_pct: float, path: Path) -> Path:
    """Write the PNG of ``panels``: (title, exact cascade, equivalent plant, kp, ki, horizon s)."""
    cols = min(3, len(panels))
    rows = -(-len(panels) // cols)
    fig = Figure(figsize=(4.6 * cols, 3.2 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (title, cascade, plant, kp, ki, horizon) in enumerate(panels):
        ax = fig.add_subplot(rows, cols, i + 1)
        exact = simulate(cascade, (kp, ki), horizon)
        t_eq, y_eq = simulate_step(plant, kp, ki, horizon)
        ax.axhspan(1.0, 1.0 + overshoot_max_pct / 100, color="0.85", lw=0)
        ax.plot(exact.t_s, exact.y, color="C0", lw=1.8, label="exact cascade")
        ax.plot(t_eq, y_eq[0], color="C1", lw=1.2, ls="--", label="equivalent models")
        for k, (share, adn) in enumerate(zip(exact.y_adn, cascade.adns)):
            ax.plot(exact.t_s, share, color=f"C{2 + k % 8}", lw=0.8,
                    label=f"{adn.name}'s share")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("time after the upper reference step, s")
        ax.set_ylabel("infeed change / step")
        ax.set_xlim(0, horizon)
        ax.set_ylim(0, max(1.15, float(np.max(exact.y)) * 1.05))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.savefig(path, dpi=110)
    return path
