"""Said when over: each step of P_ref against what its table entry was certified for
(docs/method.md#said-when-over).

The CPFC says, with the first ``P_Y`` of every table entry it uses, what that entry was
certified for (its ``p_y`` message's ``design``: the step response of the entry's as-deployed
loop and the overshoot limit it was certified against). So a recording knows it without the
table. A step's entry is the one in use when it is applied (a switch made because the DERs
move the other way, docs/method.md#directional-availability, comes one sample before the step;
any other switch ends the step's window).

A step is **over its design** if

- its overshoot exceeds the overshoot limit the entry was certified against
  (``constraints.overshoot_max_pct``: every entry is certified below it);
- its rise time or settling time exceeds the entry's design figure by more than
  :data:`FIGURE_TOLERANCE` (a slower response than designed, beyond what sampling and the
  grid explain); a response that did not rise (settle) within a window longer than that
  counts too.

One rule for every output: ``adnmesh up``'s summary and ``--summary-json``, ``adnmesh
inspect`` (text and ``--json``) take :func:`design_checks` of the summary's steps, and the
recorder's Foxglove log says the same of each step once its window has closed
(:class:`adnmesh.results.design_watch.OverDesignWatch`, an event of kind ``over_design``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["FIGURE_TOLERANCE", "DesignCheck", "FigureCheck", "design_checks", "design_lines",
           "ders_shown", "entry_at"]

FIGURE_TOLERANCE = 0.10
"""A rise or settling time more than this fraction above its design figure is over the design
(the reference run's steps with the wind turbines are 7-9 % slower than designed: the detailed
models and the grid; those of the CHPs and PVs alone 66-81 %)."""


@dataclass(frozen=True)
class FigureCheck:
    """One figure of a step against its entry.

    ``measured`` is None where the figure does not exist (no 90 % crossing; not settled within
    the window, then ``window_s`` stands for it); ``limit`` is what it may reach (overshoot:
    the certified limit; times: the design figure times ``1 +`` :data:`FIGURE_TOLERANCE`).
    """

    name: str
    measured: float | None
    design: float
    limit: float
    over: bool


@dataclass(frozen=True)
class DesignCheck:
    """A step of P_ref against the entry in use: ``entry`` (its number, None if the recording
    names none with certified figures, e.g. the static controller's), its DERs if known, and
    one :class:`FigureCheck` per figure (overshoot, rise, settling); ``over`` names those over
    the design."""

    t_s: float
    step_w: float
    entry: int | None
    ders: tuple[str, ...] = ()
    figures: tuple[FigureCheck, ...] = ()
    over: tuple[str, ...] = ()


def entry_at(entries, t_ns: int) -> dict | None:
    """The entry in use at ``t_ns``: the last of ``entries`` (dicts with ``t_ns``, ``entry``,
    ``design`` or None, ``ders``; in time order) announced at or before it."""
    found = None
    for announced in entries:
        if announced["t_ns"] > t_ns:
            break
        found = announced
    return found


def design_checks(steps, entries) -> tuple[DesignCheck, ...]:
    """Every step (:class:`~adnmesh.loopmodel.step_figures.ReferenceStep`, times from the run's
    start) against its entry (``entries`` as for :func:`entry_at`)."""
    out = []
    for step in steps:
        announced = entry_at(entries, int(round(step.t_s * 1e9)))
        design = None if announced is None else announced.get("design")
        if step.figures is None or design is None:
            out.append(DesignCheck(step.t_s, step.step_w,
                                   None if announced is None else announced.get("entry"),
                                   tuple(announced.get("ders", ())) if announced else ()))
            continue
        figures = _figures(step, design)
        out.append(DesignCheck(step.t_s, step.step_w, announced.get("entry"),
                               tuple(announced.get("ders", ())), figures,
                               tuple(f.name for f in figures if f.over)))
    return tuple(out)


def _figures(step, design: dict) -> tuple[FigureCheck, ...]:
    f, window = step.figures, step.window_s
    limit = float(design["overshoot_max_pct"])
    checks = [FigureCheck("overshoot", f.overshoot_pct, float(design["overshoot_pct"]), limit,
                          bool(f.overshoot_pct > limit))]
    for name, measured, key in (("rise", f.rise_time_s, "rise_time_s"),
                                ("settling", f.settling_time_s, "settling_time_s")):
        designed = float(design[key])
        most = designed * (1 + FIGURE_TOLERANCE)
        exists = math.isfinite(measured)
        over = measured > most if exists else window > most
        checks.append(FigureCheck(name, float(measured) if exists else None, designed, most,
                                  bool(over)))
    return tuple(checks)


def design_lines(checks, unit: str = "W") -> list[str]:
    """One line per step over its design, with the design figures beside the measured ones
    (``unit``: the step's, ``W`` or ``var``)."""
    lines = []
    for check in checks:
        if not check.over:
            continue
        parts = []
        for f in check.figures:
            if not f.over:
                continue
            if f.name == "overshoot":
                parts.append(f"overshoot {f.measured:.3f} % > the {f.limit:g} % it was "
                             f"certified for (designed {f.design:.3f} %)")
            elif f.measured is None:
                parts.append(f"{'no rise' if f.name == 'rise' else 'not settled'} in the "
                             f"window against {f.design:.3f} s designed")
            else:
                parts.append(f"{f.name} {f.measured:.3f} s against {f.design:.3f} s designed "
                             f"({100 * (f.measured / f.design - 1):+.0f} %, more than "
                             f"+{100 * FIGURE_TOLERANCE:g} %)")
        lines.append(f"  step at {check.t_s:g} s ({check.step_w / 1e6:+.3f} M{unit}) OVER THE "
                     f"DESIGN of entry {check.entry}{ders_shown(check.ders)}: " + "; ".join(parts))
    return lines


def ders_shown(ders) -> str:
    """`` (A, B, ...)``: at most six DER ids and how many there are (empty for none)."""
    if not ders:
        return ""
    shown = ", ".join(ders[:6]) + (f", ... ({len(ders)})" if len(ders) > 6 else "")
    return f" ({shown})"
