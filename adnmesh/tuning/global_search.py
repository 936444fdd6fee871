"""Global search: the feasible normalised pair with minimum rise time (dense grid + edge tracing).

1. A log-spaced grid of ``(kp_n, ki_n)`` around the initial (too aggressive) design — ``kp_n``
   from 1e-2 to 1.2 x ``kp_init``, ``ki_n`` from 1e-3 to 1.2 x ``ki_init`` — is screened for the
   disk margin for every plant in one vectorised batch; step responses are then simulated
   column by column from the top, only until the column's highest feasible point is found
   (:func:`_column_tops`).
2. Rise time falls as K_I grows, so the optimum lies on the upper edge of the feasible set, which
   for these loops is a narrow wedge whose tip a compass search misses. For every grid column
   (fixed ``kp_n``) the edge is located by bisection in ``ki_n`` between the column's highest
   feasible grid point and the infeasible point above it.
3. Around the best point, an 11 x 9 grid spanning ±1 column and ±2 row spacings is checked and
   every column's edge traced the same way (the feasible set can be a band in ki_n, so each
   zoom column needs its own feasible starting point); the zoom is repeated with the spacings
   divided by 5 (three zooms: final column spacing ~0.2 % in kp_n, edge located to ~0.01 %).

4. From the best point, the paper's path rule with the fine step (0.1 %) walks the edge to the
   local optimum (the tip of the feasible wedge).

Columns that cannot beat a plant's best point are dropped: rise time falls as K_I grows along
a column, so the rise time of any point (feasible or not) bounds that of every pair below it.
The bound comes free from the infeasible points a check simulates (overshoot) and, for an
edge whose upper end is short of the disk margin (not simulated by the check), from
simulating that end until it reaches 90 % (:meth:`TuningProblem.first_rise_s`, a fifth of
a check's cost). On SimBench this drops about two thirds of the edge bisections; the result
is the same (tested against the search without bounds).

All plants run in lock-step. It certifies the paper method (its rise time is stored beside every
table entry) and is the on-demand tuner (one subset in about a second).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.tuning.paper import STEPS, path_search
from adnmesh.tuning.problem import Check, TuningProblem

__all__ = ["GlobalResult", "tune_global", "GRID_KP", "GRID_KI"]

GRID_KP = 24
GRID_KI = 32
KP_RANGE = (1e-2, 1.2)
KI_RANGE = (1e-3, 1.2)
#: an edge is located to this width in log ki_n (0.01 %), with at most 10 bisections: 10 of
#: the grid's and the first zoom's row spacing, 8 and 6 of the next zooms' (5x closer each
#: time). Before, every level bisected 10 times, the last zoom to 5e-6. With 4e-4 (4
#: bisections in the last zoom) the global optimum was 0.11 % slower than the paper's path
#: on one wt-chp plant.
EDGE_TOL = 1e-4
MAX_BISECTIONS = 10
ZOOMS = 3
ZOOM_COLUMNS = 11
ZOOM_ROWS = 9
#: a rise time bounds a column's pairs below it to within this fraction (the bounding
#: simulation may run on a slightly different step than the pairs' own checks)
RISE_SLACK = 1e-3


@dataclass
class GlobalResult:
    """Per plant (shape (P,)): best normalised pair, its rise time, feasibility."""

    kp: np.ndarray
    ki: np.ndarray
    rise_time_s: np.ndarray
    feasible: np.ndarray
    evaluations: int


class _Best:
    """Running best (log kp, log ki, rise) per plant."""

    def __init__(self, n: int):
        self.lkp = np.full(n, np.nan)
        self.lki = np.full(n, np.nan)
        self.rise = np.full(n, np.inf)

    def offer(self, plant, lkp, lki, rise) -> None:
        """Keep, per plant, the lowest rise time among the offers and the current best."""
        if plant.size == 0:
            return
        order = np.lexsort((rise, plant))                 # by plant, then rise
        first = np.r_[True, plant[order][1:] != plant[order][:-1]]
        sel = order[first]
        p = plant[sel]
        better = rise[sel] < self.rise[p]
        p, sel = p[better], sel[better]
        self.lkp[p], self.lki[p], self.rise[p] = lkp[sel], lki[sel], rise[sel]


def _bisections(interval: float) -> int:
    """Bisections that narrow ``interval`` (log ki_n) to :data:`EDGE_TOL` (at most
    :data:`MAX_BISECTIONS`)."""
    return int(np.clip(np.ceil(np.log2(interval / EDGE_TOL)), 1, MAX_BISECTIONS))


def _raise_bound(bound, c: Check, ok) -> np.ndarray:
    """Column bounds raised by the rise times of infeasible points just simulated: every pair
    below them on their column is slower."""
    seen = ~ok & np.isfinite(c.simulated_rise_s)
    return np.where(seen, np.fmax(bound, c.simulated_rise_s * (1.0 - RISE_SLACK)), bound)


def _edge(problem, fractions, plant, lkp, lo, hi, best: _Best, bound, bisections: int) -> int:
    """Bisect ``log ki`` between feasible ``lo`` and infeasible ``hi`` per column.

    ``bound`` (per column) is a lower bound of the rise time of every pair below ``hi``
    (-inf if none is known); where none is known and the plant has a best point, the rise
    time of ``hi`` itself is simulated (until 90 % only). A column whose bound is not below
    its plant's best rise time is dropped: none of its pairs can beat it.
    """
    bound = bound.copy()
    evaluations = _first_rise_bound(problem, fractions, plant, lkp, hi, best, bound,
                                    ~np.isfinite(bound))
    for _ in range(bisections):
        keep = ~(bound >= best.rise[plant])
        plant, lkp, lo, hi, bound = plant[keep], lkp[keep], lo[keep], hi[keep], bound[keep]
        if plant.size == 0:
            break
        mid = 0.5 * (lo + hi)
        c = problem.check(fractions[plant], np.exp(lkp), np.exp(mid))
        evaluations += plant.size
        ok = c.feasible
        best.offer(plant[ok], lkp[ok], mid[ok], c.rise_time_s[ok])
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
        bound = _raise_bound(bound, c, ok)
    return evaluations


def _first_rise_bound(problem, fractions, plant, lkp, hi, best: _Best, bound, rows) -> int:
    """Raise ``bound`` (in place) by the rise time of ``hi`` where ``rows`` and the plant
    has a best point to compare it with; returns the simulations made. (Doing this for
    every upper end the bisection meets drops 27 % of the edge checks on SimBench, but
    costs as much as it saves.)"""
    need = rows & np.isfinite(best.rise[plant])
    if not need.any():
        return 0
    rise = problem.first_rise_s(fractions[plant[need]], np.exp(lkp[need]), np.exp(hi[need]))
    bound[need] = np.fmax(bound[need], np.where(np.isfinite(rise), rise * (1.0 - RISE_SLACK),
                                                -np.inf))
    return int(need.sum())


def _column_tops(problem, fractions, plant, lkp, lki, best: _Best):
    """Highest feasible row of every column of per-plant grids, simulating top-down.

    ``plant`` (A,) indexes ``fractions``; ``lkp``, ``lki`` (A, R, C) are log gains with ``ki``
    rising along R. The disk margin is screened for the whole grid at once on its sampled
    upper bound (:meth:`TuningProblem.may_meet_disk_margin`: certifying the whole grid would
    be wasted on the points below the tops); then, row by row from the top, only the points
    that pass of columns whose edge is still unknown are checked (and simulated if they meet
    the disk margin). Points below a column's highest feasible one are never simulated: they are
    slower (rise time falls as K_I grows along a column), so they cannot be the optimum, and
    they are the most expensive to simulate. Nor are the points of a column below an
    infeasible simulated point no faster than the plant's best so far (they are slower still).
    Returns (top row per column, -1 where none is feasible or the column was dropped; the
    column's rise-time bound, the rise time of its lowest infeasible simulated point times
    ``1 - RISE_SLACK``, or -inf; evaluations: screened points plus checks).
    """
    a_n, r_n, c_n = lkp.shape
    rows = np.repeat(plant, r_n * c_n)
    candidate = problem.may_meet_disk_margin(fractions[rows], np.exp(lkp.ravel()),
                                             np.exp(lki.ravel())).reshape(a_n, r_n, c_n)
    evaluations = rows.size
    top = np.full((a_n, c_n), -1)
    bound = np.full((a_n, c_n), -np.inf)
    dropped = np.zeros((a_n, c_n), bool)
    for r in range(r_n - 1, -1, -1):
        dropped |= (top < 0) & (bound >= best.rise[plant][:, None])
        a_idx, col = np.nonzero(candidate[:, r, :] & (top < 0) & ~dropped)
        if a_idx.size == 0:
            continue
        c = problem.check(fractions[plant[a_idx]], np.exp(lkp[a_idx, r, col]),
                          np.exp(lki[a_idx, r, col]))
        evaluations += a_idx.size
        ok = c.feasible
        best.offer(plant[a_idx[ok]], lkp[a_idx[ok], r, col[ok]], lki[a_idx[ok], r, col[ok]],
                   c.rise_time_s[ok])
        top[a_idx[ok], col[ok]] = r
        bound[a_idx, col] = _raise_bound(bound[a_idx, col], c, ok)
    return top, bound, evaluations


def tune_global(problem: TuningProblem, fractions, kp_init, ki_init,
                grid: tuple[int, int] = (GRID_KP, GRID_KI)) -> GlobalResult:
    """Global search for P plants (fractions shape (P, G); initial designs shape (P,))."""
    fractions = np.atleast_2d(fractions)
    n = fractions.shape[0]
    ukp = np.linspace(np.log(KP_RANGE[0]), np.log(KP_RANGE[1]), grid[0])
    uki = np.linspace(np.log(KI_RANGE[0]), np.log(KI_RANGE[1]), grid[1])
    lkp = np.log(kp_init)[:, None, None] + ukp[None, None, :]          # (P, 1, nkp)
    lki = np.log(ki_init)[:, None, None] + uki[None, :, None]          # (P, nki, 1)
    lkp, lki = np.broadcast_arrays(lkp, lki)                            # (P, nki, nkp)
    best = _Best(n)
    # edge of every grid column: highest feasible point and the infeasible one above it
    top, bound, evaluations = _column_tops(problem, fractions, np.arange(n), lkp, lki, best)
    has = (top >= 0) & (top < grid[1] - 1)
    p_idx, col = np.nonzero(has)
    j = top[p_idx, col]
    evaluations += _edge(problem, fractions, p_idx, lkp[p_idx, 0, col],
                         lki[p_idx, j, 0], lki[p_idx, j + 1, 0], best, bound[p_idx, col],
                         _bisections(uki[1] - uki[0]))

    sp_kp, sp_ki = ukp[1] - ukp[0], uki[1] - uki[0]
    col_off = np.linspace(-1.0, 1.0, ZOOM_COLUMNS)
    row_off = np.linspace(-2.0, 2.0, ZOOM_ROWS)
    for _ in range(ZOOMS):
        alive = np.nonzero(np.isfinite(best.rise))[0]
        if alive.size == 0:
            break
        # a small grid around the best point (the feasible set may be a band in ki, not an
        # interval from 0), then the edge above each column's highest feasible point
        zk = best.lkp[alive, None, None] + col_off[None, None, :] * sp_kp      # (A, 1, C)
        zi = best.lki[alive, None, None] + row_off[None, :, None] * sp_ki      # (A, R, 1)
        zk, zi = np.broadcast_arrays(zk, zi)
        top, bound, ev = _column_tops(problem, fractions, alive, zk, zi, best)
        evaluations += ev
        has = (top >= 0) & (top < zk.shape[1] - 1)
        a_idx, col = np.nonzero(has)
        j = top[a_idx, col]
        evaluations += _edge(problem, fractions, alive[a_idx], zk[a_idx, 0, col],
                             zi[a_idx, j, 0], zi[a_idx, j + 1, 0], best, bound[a_idx, col],
                             _bisections((row_off[1] - row_off[0]) * sp_ki))
        sp_kp /= 5.0
        sp_ki /= 5.0
    # local refinement: walk the edge from the best point with the paper's fine path rule
    alive = np.nonzero(np.isfinite(best.rise))[0]
    if alive.size:
        kp, ki, rise, ev, _ = path_search(problem, fractions[alive], np.exp(best.lkp[alive]),
                                          np.exp(best.lki[alive]), STEPS[-1])
        evaluations += ev
        ok = np.isfinite(rise)
        best.offer(alive[ok], np.log(kp[ok]), np.log(ki[ok]), rise[ok])
    feasible = np.isfinite(best.rise)
    return GlobalResult(np.where(feasible, np.exp(best.lkp), np.nan),
                        np.where(feasible, np.exp(best.lki), np.nan),
                        np.where(feasible, best.rise, np.nan), feasible, evaluations)
