"""From tuned normalised pairs to certified table entries: Find W, the back-off, the figures.

A tuning method (the paper's path, the global search, the on-demand ray) yields one normalised
pair per plant. :func:`certified_entries` turns it into a table entry for every subset of the
plant: absolute gains (``K = k_n / sum P_inst``), the weights of Find W
(:func:`~adnmesh.tuning.weights.find_weights`), the as-deployed figures (weights applied) and,
where that loop misses a constraint, both gains lowered together (:func:`back_off`). An entry
is feasible only if the as-deployed loop meets both constraints. With an uncertainty set
(``constraints.robust``) it must meet them on every member the certificate
(:func:`~adnmesh.tuning.robust_check.worst_members`) finds too; where it does not, those members
join every later check and the entry is backed off, up to :data:`ROBUST_ROUNDS` times
(docs/tuning.md#robust-tables). The table builder
(:mod:`adnmesh.tuning.build`) and the on-demand tuner (:mod:`adnmesh.tuning.ondemand`) both end
here.
"""
from __future__ import annotations

import dataclasses
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.robust_check import worst_members
from adnmesh.tuning.table import FIGURE_KEYS, TableEntry
from adnmesh.tuning.weights import find_weights

__all__ = ["PlantGroup", "certified_entries", "certify_static", "back_off", "BACK_OFF_STEPS",
           "BACK_OFF_FIRST"]

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
    robust = None
    if problem.box is not None:
        with _phase(clock, "back-off"):
            robust, scale, kp, ki, fig = _certify_over_set(problem, gains, kp, ki, scale, fig,
                                                           usable)
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
        if robust is not None:
            figures.update(robust.figures(i))
            if ok and not robust.holds[i]:
                ok, reason = False, "not certified over the uncertainty set: " + robust.why(i)
        out.append(TableEntry(s, float(kp[i]), float(ki[i]), w, ok, reason, figures))
    return out


#: certificate rounds: find the worst members, add them to the checks, back off, again
ROBUST_ROUNDS = 3


class _SetCertificate:
    """The certificate of every row: its worst members (:func:`worst_members`)."""

    def __init__(self, problem: TuningProblem, gains: np.ndarray):
        self.problem = problem
        n = gains.shape[0]
        self.worst = [None] * n        # (disk margin, member, overshoot, member, settled)
        self.holds = np.zeros(n, bool)
        #: the DER types each row's loop has
        self.types = [problem.types_in(row) for row in gains]

    def record(self, rows: np.ndarray, wc) -> None:
        p = self.problem
        ok = wc.meets(p.disk_margin_min, p.overshoot_max_pct)
        for j, r in enumerate(rows):
            self.worst[r] = (float(wc.disk_margin[j]), wc.disk_margin_at[j],
                             float(wc.overshoot_pct[j]), wc.overshoot_at[j],
                             bool(wc.settled[j]))
            self.holds[r] = bool(ok[j])

    def why(self, i: int) -> str:
        if self.worst[i] is None:
            return "not evaluated"
        dm, dm_at, over, os_at, settled = self.worst[i]
        box = self.problem.box
        if not settled:
            return "a member is unstable or does not settle"
        if dm < self.problem.disk_margin_min:
            return f"disk margin {dm:.4g} at {box.describe(dm_at, self.types[i])}"
        return f"overshoot {over:.4g} % at {box.describe(os_at, self.types[i])}"

    def figures(self, i: int) -> dict:
        if self.worst[i] is None:
            return {}
        dm, dm_at, over, os_at, settled = self.worst[i]
        box = self.problem.box
        return {"robust_disk_margin": dm if settled else None,
                "robust_disk_margin_at": box.describe(dm_at, self.types[i]) if dm_at else None,
                "robust_overshoot_pct": over if settled else None,
                "robust_overshoot_at": box.describe(os_at, self.types[i]) if os_at else None}


def _certify_over_set(problem, gains, kp, ki, scale, fig, usable):
    """Certify the rows over the uncertainty set; where one fails, add the members it failed
    on to every later check and back it off (both gains together), up to
    :data:`ROBUST_ROUNDS` times. Returns (certificate, scale, kp, ki, figures)."""
    cert = _SetCertificate(problem, gains)
    todo = np.nonzero(usable & np.isfinite(scale) & _meets(problem, fig))[0]
    for round_ in range(ROBUST_ROUNDS + 1):
        if todo.size == 0:
            break
        wc = worst_members(problem, gains[todo], kp[todo], ki[todo])
        cert.record(todo, wc)
        bad = todo[~cert.holds[todo]]
        if bad.size == 0 or round_ == ROBUST_ROUNDS:
            break
        problem.add_members(m for r in bad for m in (cert.worst[r][1], cert.worst[r][3])
                            if m is not None)
        factor = back_off(problem, gains[bad], kp[bad], ki[bad])
        far = ~np.isfinite(factor)
        if far.any():
            factor[far] = _far_back_off(problem, gains[bad[far]], kp[bad[far]], ki[bad[far]])
        found = np.isfinite(factor)
        bad = bad[found]
        if bad.size == 0:
            break
        scale[bad] *= factor[found]
        kp, ki = kp.copy(), ki.copy()
        kp[bad] *= factor[found]
        ki[bad] *= factor[found]
        fig = _replace_rows(fig, bad, problem.figures(gains[bad], kp[bad], ki[bad]))
        todo = bad
    return cert, scale, kp, ki, fig


def certify_static(problem: TuningProblem, powers: np.ndarray, kp: float, ki: float,
                   t_max_s) -> tuple[float, float, dict, str | None]:
    """The static pair (1/W, 1/(W s)) certified over the uncertainty set on every plant it is
    checked on (``powers`` (P, G), W): the members it fails on join the checks and both gains
    are lowered together (the same factor on every plant) until it holds, up to
    :data:`ROBUST_ROUNDS` times. Returns (K_P, K_I, the certificate's figures, why it is not
    certified or None)."""
    ones = np.ones(powers.shape[0])
    rows = np.arange(powers.shape[0])
    why = None
    for round_ in range(ROBUST_ROUNDS + 1):
        wc = worst_members(problem, powers, kp * ones, ki * ones)
        cert = _SetCertificate(problem, powers)
        cert.record(rows, wc)
        # the lowest disk margin of all plants, and the highest overshoot
        figures = cert.figures(int(np.argmin(wc.disk_margin)))
        figures.update({k: v for k, v in cert.figures(int(np.argmax(wc.overshoot_pct))).items()
                        if k.startswith("robust_overshoot")})
        if cert.holds.all():
            return kp, ki, figures, None
        bad = np.nonzero(~cert.holds)[0]
        why = f"plant {int(bad[0])}: {cert.why(int(bad[0]))}"
        if round_ == ROBUST_ROUNDS:
            break
        problem.add_members(m for r in bad for m in (wc.disk_margin_at[r], wc.overshoot_at[r])
                            if m is not None)
        tot = powers.sum(axis=1)
        f = powers / tot[:, None]
        factors = np.concatenate([0.99 ** np.arange(1, BACK_OFF_STEPS + 1), FAR_FACTORS])
        for factor in factors:
            chk = problem.check(f, kp * factor * tot, ki * factor * tot, t_max_s=t_max_s)
            if chk.feasible.all():
                kp, ki = kp * factor, ki * factor
                break
        else:
            break
    return kp, ki, figures, why


#: beyond the 1 % steps: factors down to this, then bisection to 1 % of the factor
FAR_FACTORS = np.geomspace(0.6, 1e-3, 24)
FAR_BISECTIONS = 6


def _far_back_off(problem, gains, kp, ki) -> np.ndarray:
    """A gain scale for rows the 1 % steps of :func:`back_off` did not help (a member of the
    set far from the ones the search checked): the largest of :data:`FAR_FACTORS` that meets
    every check, then bisected (geometrically) towards the one above it; NaN if none does."""
    n, k = kp.size, FAR_FACTORS.size
    rows = np.repeat(np.arange(n), k)
    f = np.tile(FAR_FACTORS, n)
    ok = problem.check(gains[rows], kp[rows] * f, ki[rows] * f).feasible.reshape(n, k)
    hit = ok.any(axis=1)
    out = np.full(n, np.nan)
    if not hit.any():
        return out
    j = np.argmax(ok, axis=1)
    lo = FAR_FACTORS[j]                                       # feasible
    hi = np.where(j > 0, FAR_FACTORS[np.maximum(j - 1, 0)], 0.99 ** 50)   # not
    idx = np.nonzero(hit)[0]
    lo, hi = lo[idx], hi[idx]
    for _ in range(FAR_BISECTIONS):
        mid = np.sqrt(lo * hi)
        good = problem.check(gains[idx], kp[idx] * mid, ki[idx] * mid).feasible
        lo, hi = np.where(good, mid, lo), np.where(good, hi, mid)
    out[idx] = lo
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
