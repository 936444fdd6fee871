"""The static controller: one (K_P, K_I) feasible for every subset (w = 1), best worst case.

Absolute gains meet subset A as normalised gains ``K * sum_A P_inst``, so a pair that suits the
largest subsets is slow on the smallest. The search runs along rays ``K_I = rho K_P``
(``rho`` log-spaced over 0.01 ... 10 1/s): on each ray the largest gain scale feasible for all
subsets is found by bisection in log K_P (assuming feasibility is monotone in the scale along a
ray — the result is re-checked on every subset, so a wrong assumption can only cost optimality,
never feasibility), then the ray with the best worst-case rise time wins.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .problem import TuningProblem

__all__ = ["StaticResult", "static_controller"]

RATIOS = np.geomspace(0.01, 10.0, 13)
BISECTIONS = 14


@dataclass
class StaticResult:
    """The static pair (1/W, 1/(W s)) and its worst case over the plants."""

    kp: float
    ki: float
    worst_rise_time_s: float
    worst_plant: int
    feasible: bool


def _all_feasible(problem, fractions, totals, kp, ki):
    """Per ray: feasible on every plant, and the worst rise time (inf if infeasible)."""
    n_rays, n_plants = kp.size, fractions.shape[0]
    rows = np.tile(np.arange(n_plants), n_rays)
    kpn = np.repeat(kp, n_plants) * totals[rows]
    kin = np.repeat(ki, n_plants) * totals[rows]
    chk = problem.check(fractions[rows], kpn, kin)
    feas = chk.feasible.reshape(n_rays, n_plants)
    rise = np.where(feas, chk.rise_time_s.reshape(n_rays, n_plants), np.inf)
    ok = feas.all(axis=1)
    worst = np.where(ok, rise.max(axis=1), np.inf)
    return ok, worst, np.argmax(rise, axis=1)


def static_controller(problem: TuningProblem, fractions, totals, kp_hint: float) -> StaticResult:
    """Search the static pair for plants ``fractions`` (P, G) with powers ``totals`` (P,) in W.

    ``kp_hint`` (1/W) sets the bisection bracket: [kp_hint / 1e4, kp_hint * 10].
    """
    fractions = np.atleast_2d(fractions)
    totals = np.asarray(totals, float)
    lo = np.full(RATIOS.size, np.log(kp_hint / 1e4))
    hi = np.full(RATIOS.size, np.log(kp_hint * 10.0))
    best_worst = np.full(RATIOS.size, np.inf)
    best_kp = np.full(RATIOS.size, np.nan)
    best_plant = np.zeros(RATIOS.size, int)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        ok, worst, plant = _all_feasible(problem, fractions, totals, np.exp(mid),
                                         RATIOS * np.exp(mid))
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
        better = ok & (worst <= best_worst)
        best_worst = np.where(better, worst, best_worst)
        best_kp = np.where(better, np.exp(mid), best_kp)
        best_plant = np.where(better, plant, best_plant)
    if not np.isfinite(best_worst).any():
        return StaticResult(float("nan"), float("nan"), float("inf"), -1, False)
    r = int(np.argmin(best_worst))
    return StaticResult(float(best_kp[r]), float(best_kp[r] * RATIOS[r]), float(best_worst[r]),
                        int(best_plant[r]), True)
