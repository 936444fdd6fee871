"""Summary figures of a recorded run: how P_IP followed each step of P_ref.

The step figures are those of ``adnmesh up``'s summary, by the same function
(:func:`adnmesh.loopmodel.step_figures.reference_step_figures`) on the same windows: a step's
window ends at the next step or at the next event that ends a window by the one rule both apply,
:class:`adnmesh.results.rules.StepWindowEnds` (a gain switch, an availability change: a DER's
heartbeat flag or SI, a fault's start or end), else at the run's end (the ``clock/start``
message's ``end_ns``; the last P_IP sample if the recording has none). Times are send (sampling) times;
see :mod:`adnmesh.loopmodel.step_figures` for the definitions
(docs/method.md#figures-of-merit, MATLAB ``stepinfo``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.step_figures import ReferenceStep, reference_step_figures
from adnmesh.results import rules
from adnmesh.results.series import RunData

__all__ = ["RunFigures", "run_end_ns", "run_figures", "step_table", "window_ends"]


@dataclass(frozen=True)
class RunFigures:
    """Summary of a run: step responses, tracking error and event counts.

    ``availability_changes`` does not count the initial state; ``faults`` counts fault events
    (a start and an end are two); ``mode_changes`` counts DER mode changes (e.g. to watchdog).

    ``rms_error_w`` and ``max_error_w`` are over every P_IP sample, against the P_ref in force
    at its send time (None without both series).
    """

    steps: tuple[ReferenceStep, ...]
    band_pct: float
    rms_error_w: float | None
    max_error_w: float | None
    gain_switches: int
    availability_changes: int
    faults: int
    mode_changes: int


def window_ends(run: RunData) -> list[int]:
    """Instants (ns) other than P_ref steps that end a step's window: those of the run's events
    by the rule of :class:`~adnmesh.results.rules.StepWindowEnds`, and the steps of Q_ref
    (reactive power control: what follows them is their response)."""
    ends = rules.window_ends(run.events)
    q_ref = run.one("q_ref")
    if q_ref is None or q_ref.t_ns.size < 2:
        return ends
    return sorted([*ends, *(int(t) for t in q_ref.t_ns[1:])])


def run_end_ns(run: RunData) -> int | None:
    """End of the run, ns: the ``end_ns`` of its start message, else the last P_IP sample
    (:meth:`RunData.end_ns`)."""
    return run.end_ns()


def run_figures(run: RunData, *, band_pct: float = 5.0) -> RunFigures:
    """Compute the :class:`RunFigures` of ``run`` (settling band ``band_pct`` %)."""
    p_ref, p_ip = run.one("p_ref"), run.one("p_ip")
    steps: tuple[ReferenceStep, ...] = ()
    rms = worst = None
    if p_ref is not None and p_ip is not None and p_ip.values.size:
        steps = reference_step_figures(p_ip.t_ns, p_ip.values, p_ref.t_ns, p_ref.values,
                                       window_ends(run), run_end_ns(run), band_pct=band_pct,
                                       origin_ns=run.t0_ns, offset_w=_offsets(run, p_ref))
        index = np.searchsorted(p_ref.t_ns, p_ip.t_ns, side="right") - 1
        valid = index >= 0
        if valid.any():
            error = p_ip.values[valid] - p_ref.values[index[valid]]
            rms, worst = float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error)))
    kinds = [e.kind for e in run.events]
    return RunFigures(steps=steps, band_pct=band_pct, rms_error_w=rms, max_error_w=worst,
                      gain_switches=kinds.count("gain_switch"),
                      availability_changes=max(0, kinds.count("availability") - 1),
                      faults=len(run.fault_spans()), mode_changes=kinds.count("der_mode"))


def _offsets(run: RunData, p_ref):
    """The level above's offset in each P_ref record (an ADN of a hierarchy: the ``offset_w``
    its p_ref messages carry, the same instants), zeros where a record has none; None without
    any."""
    offset = run.one("p_ref_offset")
    if offset is None or not offset.values.size:
        return None
    where = np.searchsorted(offset.t_ns, p_ref.t_ns)
    inside = where < offset.t_ns.size
    hit = np.zeros(p_ref.t_ns.size, bool)
    hit[inside] = offset.t_ns[where[inside]] == p_ref.t_ns[inside]
    out = np.zeros(p_ref.t_ns.size)
    out[hit] = offset.values[where[hit]]
    return out


def step_table(steps, band_pct: float, title: str = "P_IP after each P_ref step",
               checks=(), unit: str = "W"):
    """Rich table of :class:`~adnmesh.loopmodel.step_figures.ReferenceStep` records (``adnmesh up``'s
    summary and ``adnmesh inspect`` print the same one).

    A dash is a figure that does not exist (no 90 % crossing, too few samples); a settling time
    ``> w`` means not settled within the window of ``w`` s. With ``checks`` (one
    :class:`~adnmesh.results.design_check.DesignCheck` per step), if any has certified
    figures, two more columns: what the step's table entry was designed for (rise, settling,
    overshoot) and which figures are over it (docs/method.md#said-when-over). ``unit``: ``W``
    (P) or ``var`` (Q).
    """
    from rich.table import Table

    table = Table(title=f"{title} (rise 10-90 %, settling band {band_pct:g} %)",
                  title_justify="left")
    columns = ["t [s]", f"step [M{unit}]", "rise [s]", "settling [s]", "overshoot [%]",
               f"steady error [k{unit}]", "window [s]"]
    checks = checks if any(c.figures for c in checks) else ()   # none said: as before
    if checks:
        columns += ["designed: rise / settling / overshoot (entry)", "over the design"]
    for column in columns:
        table.add_column(column, justify="right")
    for i, s in enumerate(steps):
        f = s.figures
        row = [f"{s.t_s:.2f}", f"{s.step_w / 1e6:+.3f}",
               _num(None if f is None else f.rise_time_s, ".3f"),
               _settling(f, s.window_s),
               _num(None if f is None else f.overshoot_pct, ".3f"),
               _num(None if s.steady_error_w is None else s.steady_error_w / 1e3, ".2f"),
               f"{s.window_s:.2f}"]
        if checks:
            row += _design_cells(checks[i] if i < len(checks) else None)
        table.add_row(*row)
    if not steps:
        table.add_row("", "no steps", *[""] * (len(columns) - 2))
    return table


def _design_cells(check) -> list[str]:
    if check is None or not check.figures:
        return ["-", "-" if check is None or check.entry is None else
                f"no certified figures (entry {check.entry})"]
    by_name = {f.name: f for f in check.figures}
    designed = (f"{by_name['rise'].design:.3f} / {by_name['settling'].design:.3f} / "
                f"{by_name['overshoot'].design:.3f} (e{check.entry})")
    return [designed, "OVER: " + ", ".join(check.over) if check.over else "no"]


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None or not np.isfinite(value) else format(value, fmt)


def _settling(figures, window_s: float) -> str:
    if figures is not None and figures.settling_time_s == np.inf:
        return f"> {window_s:.2f}"
    return _num(None if figures is None else figures.settling_time_s, ".3f")
