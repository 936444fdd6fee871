"""From tuned normalised pairs to certified table entries: Find W, the back-off, the figures.

A tuning method (the paper's path, the global search, the on-demand ray) yields one normalised
pair per plant. :func:`certified_entries` turns it into a table entry for every subset of the
plant: absolute gains (``K = k_n / sum P_inst``), the weights of Find W
(:func:`~adnmesh.tuning.weights.find_weights`), the as-deployed figures (weights applied) and,
where that loop misses a constraint, both gains lowered together (:func:`back_off`). An entry
is feasible only if the as-deployed loop meets both constraints. The table builder
(:mod:`adnmesh.tuning.build`) and the on-demand tuner (:mod:`adnmesh.tuning.ondemand`) both end
here.
"""
from __future__ import annotations

import dataclasses
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.table import FIGURE_KEYS, TableEntry
from adnmesh.tuning.weights import find_weights

__all__ = ["PlantGroup", "certified_entries", "back_off", "BACK_OFF_STEPS", "BACK_OFF_FIRST"]

#: 1 % steps by which both gains are lowered at most (:func:`back_off`)
BACK_OFF_STEPS = 50
#: back-off steps checked for every entry before the rest
BACK_OFF_FIRST = 2


@dataclass(frozen=True)
class PlantGroup:
    """One normalised plant and the subsets that share it."""

    fractions: np.ndarray
    subsets: tuple[tuple[str, ...], ...]


def _phase(clock, name: str):
    """``clock.phase(name)`` (a context timing a phase), or nothing without a clock."""
    return nullcontext() if clock is None else clock.phase(name)


def certified_entries(problem: TuningProblem, groups: list[PlantGroup], kp_n, ki_n, feasible,
                      reasons, global_rise, design_rise, tuned_by,
                      clock=None) -> list[TableEntry]:
    """Table entries (absolute gains, weights, as-deployed figures) for tuned plant groups.

    ``design_rise`` is the tuning method's rise time on the unweighted plant, ``global_rise``
    the global optimum's on the same plant: the two are comparable, the as-deployed figures
    (weights applied) are what the runtime gets. ``tuned_by`` (per group) names the method
    that found the pair. ``clock`` (optional, with a ``phase(name)`` context) times the
    phases "find W", "back-off" and "as-deployed figures".
    """
    rows = []                          # (subset, K_P, K_I, global rise, design rise, tuned by)
    out: list[TableEntry] = []
    for g, grp in enumerate(groups):
        for s in grp.subsets:
            total = float(problem.group_power(s).sum())
            if feasible[g]:
                rows.append((s, kp_n[g] / total, ki_n[g] / total, global_rise[g],
                             design_rise[g], tuned_by[g]))
            else:
                out.append(TableEntry(s, float("nan"), float("nan"), {d: 1.0 for d in s}, False,
                                      reasons[g], {"global_rise_time_s": None}))
    if not rows:
        return out
    with _phase(clock, "find W"):
        weights = find_weights(problem, [(r[0], r[1], r[2]) for r in rows])
    gains = np.array([problem.group_power(r[0], w) for r, w in zip(rows, weights)])
    kp = np.array([r[1] for r in rows])
    ki = np.array([r[2] for r in rows])
    usable = gains.sum(axis=1) > 0
    gains[~usable] = 1.0                     # placeholder; such rows are reported infeasible
    with _phase(clock, "as-deployed figures"):
        fig = problem.figures(gains, kp, ki)
    # the figures are the full check of the unscaled gains: back off only where they fail
    scale = np.ones(kp.size)
    bad = np.nonzero(~_meets(problem, fig))[0]
    if bad.size:
        with _phase(clock, "back-off"):
            scale[bad] = back_off(problem, gains[bad], kp[bad], ki[bad])
        kp, ki = kp * np.nan_to_num(scale, nan=1.0), ki * np.nan_to_num(scale, nan=1.0)
        with _phase(clock, "as-deployed figures"):
            again = problem.figures(gains[bad], kp[bad], ki[bad])
        fig = _replace_rows(fig, bad, again)
    for i, ((s, _, _, grise, drise, by), w) in enumerate(zip(rows, weights)):
        row = fig.row(i)
        figures = {k: row[k] for k in FIGURE_KEYS}
        figures["settling_time_2pct_s"] = row["settling_time_2pct_s"]
        figures["global_rise_time_s"] = None if not np.isfinite(grise) else float(grise)
        figures["design_rise_time_s"] = float(drise)
        figures["tuned_by"] = by
        figures["gain_back_off"] = float(scale[i]) if np.isfinite(scale[i]) else None
        ok = bool(usable[i] and np.isfinite(scale[i]) and row["stable"]
                  and row["disk_margin"] >= problem.disk_margin_min
                  and row["overshoot_pct"] is not None
                  and row["overshoot_pct"] < problem.overshoot_max_pct)
        reason = None if ok else ("every weight reduced to 0" if not usable[i]
                                  else "as-deployed loop violates a constraint")
        out.append(TableEntry(s, float(kp[i]), float(ki[i]), w, ok, reason, figures))
    return out


def _meets(problem: TuningProblem, fig) -> np.ndarray:
    """Both constraints met by full figures, as :meth:`TuningProblem.check` decides them."""
    return (fig.stable & (fig.disk_margin >= problem.disk_margin_min)
            & (fig.overshoot_pct < problem.overshoot_max_pct)
            & np.isfinite(fig.rise_time_s) & np.isfinite(fig.settling_time_s))


def _replace_rows(fig, rows: np.ndarray, new):
    """``fig`` (LoopFigures) with the candidates ``rows`` taken from ``new``."""
    out = {}
    for f in dataclasses.fields(fig):
        old = getattr(fig, f.name)
        if isinstance(old, np.ndarray):
            old = old.copy()
            old[rows] = getattr(new, f.name)
        else:                                                  # per-candidate lists
            old = list(old)
            for i, r in enumerate(rows):
                old[r] = getattr(new, f.name)[i]
        out[f.name] = old
    return type(fig)(**out)


def back_off(problem: TuningProblem, gains, kp, ki) -> np.ndarray:
    """Gain scale per entry so that the as-deployed loop (W applied) meets both constraints.

    Find W changes the plant the gains were tuned for; where the weighted loop then misses a
    constraint (typically alpha a few 1e-4 below the limit), both gains are lowered together
    in 1 % steps (at most :data:`BACK_OFF_STEPS`). 1.0 where nothing was needed, NaN where
    those steps did not help.
    """
    scale = np.ones(kp.size)
    bad = np.nonzero(~problem.check(gains, kp, ki).feasible)[0]
    factors = 0.99 ** np.arange(1, BACK_OFF_STEPS + 1)
    # the first steps for every entry at once (most need one or two), the rest only for
    # the entries they did not help; the answer is each entry's first feasible step
    for steps in (slice(0, BACK_OFF_FIRST), slice(BACK_OFF_FIRST, BACK_OFF_STEPS)):
        if bad.size == 0:
            break
        f_k = factors[steps]
        rows = np.repeat(bad, f_k.size)
        f = np.tile(f_k, bad.size)
        ok = problem.check(gains[rows], kp[rows] * f, ki[rows] * f).feasible.reshape(bad.size, -1)
        hit = ok.any(axis=1)
        scale[bad[hit]] = f_k[np.argmax(ok[hit], axis=1)]
        bad = bad[~hit]
    scale[bad] = np.nan
    return scale
