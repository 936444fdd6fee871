"""What a hierarchy's run leaves for a person: its recording, its figure and its step lines
(``adnmesh cascade --run``, docs/hierarchy.md)."""

from __future__ import annotations

import math
import os
import secrets
import time
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from adnmesh.recording.writer import Recorder
from adnmesh.results.design_check import ders_shown, design_lines
from adnmesh.study.hierarchy import HierarchyResult, level_series, recorded
from adnmesh.wire.keys import Keys
from adnmesh.wire.schemas import message_schemas

__all__ = ["plot_run", "step_lines", "switch_lines", "write_recording"]

SWITCH_WINDOW_S = 10.0
"""The window after an upper gain switch in which its largest deviation is taken, s."""


def write_recording(result: HierarchyResult, path: Path, hierarchy) -> Path:
    """Every level's messages in one MCAP file at ``path`` (topics ``adn/<grid>/...``; log
    time the delivery, publish time the sending, ns of sim time), and each level's alone
    beside it (``<stem>.<grid>.mcap``: a recording of one grid, as ``adnmesh up`` writes, for
    ``inspect`` and ``replay``); all of them name one ``run_id``, so that ``adnmesh merge``
    refuses level files of two runs."""
    levels = [hierarchy.name, *(a.id for a in hierarchy.adns)]
    run_id = (f"{hierarchy.name}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}-"
              f"{secrets.token_hex(3)}")
    common = {"run_id": run_id, "clock": "sim", "hierarchy": str(hierarchy.path),
              "hierarchy_sha256": hierarchy.sha256, "duration_s": f"{result.end_s:g}",
              "levels": " ".join(levels)}
    rows = recorded(result.run)
    files = [(path, None), *((path.with_name(f"{path.stem}.{g}.mcap"), g) for g in levels)]
    for target, grid in files:
        metadata = common | {"grid": grid or hierarchy.name}
        with Recorder(target, metadata=metadata, schemas=message_schemas()) as recorder:
            for key, kind, payload, t_send, t_deliver in rows:
                if grid is None or key.split("/", 2)[1] == grid:
                    recorder.write(key, kind, payload, log_time_ns=t_deliver,
                                   publish_time_ns=t_send)
    return path


def plot_run(result: HierarchyResult, levels, path: Path) -> Path:
    """Two panels: the upper P_IP (the HV grid's exchange with the level above, or without an
    HV grid the sum of the ADNs' exchanges) against the upper reference (MW), and each ADN's
    exchange with the offset the level above asked of it (MW)."""
    upper, adns, _ = levels
    keys = Keys(upper.config.grid)
    fig = Figure(figsize=(9.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2, sharex=None)
    t, p = level_series(result.run, keys.of("p_ip"), "p_ip_w")
    t_ref, ref = level_series(result.run, keys.of("p_ref"), "p_ref_w")
    what = ("the HV grid's exchange" if upper.config.grid_model is not None else
            "sum of the exchanges")
    top.plot(t / 1e9, p / 1e6, lw=1.4, label=f"{what} (upper P_IP)")
    top.step(np.append(t_ref, t[-1]) / 1e9, np.append(ref, ref[-1]) / 1e6, where="post",
             color="k", lw=0.9, ls="--", label="upper P_ref")
    top.set_ylabel("MW")
    top.set_title(f"{upper.config.grid}: the upper loop")
    for i, (adn, level) in enumerate(adns.items()):
        t_a, p_a = level_series(result.run, Keys(level.config.grid).of("p_ip"), "p_ip_w")
        t_o, o = level_series(result.run, keys.of("adn_offset", adn), "offset_w")
        bottom.plot(t_a / 1e9, p_a / 1e6, color=f"C{i}", lw=1.2, label=f"{adn}: exchange")
        if t_o.size:
            bottom.step(t_o / 1e9, (o + p_a[0]) / 1e6, where="post", color=f"C{i}", lw=0.8,
                        ls=":", label=f"{adn}: operating point + offset")
    bottom.set_xlabel("sim time, s")
    bottom.set_ylabel("MW")
    bottom.set_title("the ADNs")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.savefig(path, dpi=110)
    return path


def _seconds(value: float) -> str:
    return f"{value:.3g} s" if math.isfinite(value) else "not reached"


def step_lines(result: HierarchyResult) -> list[str]:
    """One line per upper step: rise, settling and overshoot beside what its entry was
    certified for on the cascade; then a line for each step over that design
    (:func:`~adnmesh.results.design_check.design_lines`)."""
    lines = []
    for step, check in zip(result.steps, result.checks):
        f = step.figures
        designed = {c.name: c.design for c in check.figures}
        said = "" if not designed else (
            f" (certified: rise {designed['rise']:.3g} s, settling {designed['settling']:.3g} s, "
            f"overshoot {designed['overshoot']:.3g} %)")
        lines.append(f"  step {step.step_w / 1e6:+.3f} MW at {step.t_s:g} s, entry "
                     f"{check.entry}{ders_shown(check.ders)}: rise {_seconds(f.rise_time_s)}, "
                     f"settling ({f.band_pct:g} %) {_seconds(f.settling_time_s)}, overshoot "
                     f"{f.overshoot_pct:.3g} %{said}")
    return (lines or ["  no step of the upper reference in the run"]) + \
        design_lines(result.checks)


def switch_lines(result: HierarchyResult, grid: str) -> list[str]:
    """One line per gain switch of the upper CPFC (an ADN leaving or returning): the ADNs it
    uses from then on and the largest deviation of the sum of the exchanges from the upper
    reference in the :data:`SWITCH_WINDOW_S` after it (or to the next step, switch or
    availability change)."""
    import msgspec

    keys = Keys(grid)
    t, p = level_series(result.run, keys.of("p_ip"), "p_ip_w")
    t_ref, ref = level_series(result.run, keys.of("p_ref"), "p_ref_w")
    lines = []
    for payload in result.run.payloads(keys.of("p_y")):
        if b'"switch"' not in payload:
            continue
        body = msgspec.json.decode(payload)
        at = body["t_send_ns"]
        later = [int(x) for x in (*t_ref, *result.window_ends_ns) if x > at]
        end = min([at + int(SWITCH_WINDOW_S * 1e9), *later])
        inside = (t >= at) & (t < end)
        reference = ref[np.searchsorted(t_ref, t[inside], side="right") - 1]
        deviation = float(np.max(np.abs(p[inside] - reference))) if inside.any() else math.nan
        used = [a for a, w in body.get("w", {}).items() if w]
        before = body["switch"].get("kp_before")
        gains = f", gains x{body['kp'] / before:.3g}" if before and body["kp"] != before else ""
        lines.append(f"  switch at {at / 1e9:g} s to {', '.join(used) or 'no ADN'}{gains}: largest "
                     f"deviation {deviation / 1e3:.3g} kW in the {(end - at) / 1e9:.3g} s after"
                     f" (handover {body['switch'].get('handover_s') or 0:.3g} s)")
    return lines
