"""The paper's tuning method (docs/method.md#the-papers-method), run in lock-step for many
normalised plants at once.

All gains here are *normalised* (``kp_n`` dimensionless, ``ki_n`` in 1/s; see
:mod:`adnmesh.tuning.problem`). Points the paper leaves open, defined here:

Initial values
    A 60° phase-margin PI design (MATLAB's ``pidtune`` default target): the crossover
    ``omega_c`` is the lowest frequency where the plant's phase (delays included) is -90°, and the
    PI adds 30° of lag there (``ki_n = kp_n omega_c tan 30°``) with ``|C g| = 1`` at ``omega_c``.
    The method needs the initial point to be infeasible (too aggressive); if it is feasible, both
    gains are raised by 25 % until it is not (at most 40 times).
Path search
    Start ``(kp_init, s ki_init)``. Infeasible: ``kp *= 1 - s``; feasible: remember it,
    ``ki *= 1 + s``. The stop counter ES counts moves since the last *improvement* of the best
    rise time on the path, starting at the first feasible point (before it, the path is only
    walking into the feasible set); it is reset to 0 whenever a feasible point improves the best
    rise time; the run stops when ES reaches 20, or after 5000 moves. The run's result is the
    best feasible point seen. The second run (s = 0.001) starts at the first run's result.
Start too aggressive in K_I
    For some plants (a slow CHP share with a small fast PV share) even ``0.01 ki_init`` is
    infeasible for every ``kp``: the first run then walks ``kp`` to zero without ever meeting
    the feasible set. Such a run is repeated with ``K_I,Start`` divided by 10, at most three
    times (down to ``1e-5 ki_init``). A plant whose path never becomes feasible is reported
    infeasible here; the table builder then takes the global search's pair and says so.
Area search (only if ``I_conv >= 1``)
    From the path result, K_I is raised once by the step rule, then the rectangle between that
    point, ``kp -> 0`` (down to 1 % of the path's kp, in 10 % steps) and ``ki = ki_init`` (in 5 %
    steps) is scanned; the feasible point with the lowest rise time wins, or the path result if
    none is better.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adnmesh.tuning.problem import TuningProblem

__all__ = ["initial_values", "path_search", "area_search", "PaperResult", "tune_paper", "ES_LIMIT"]

ES_LIMIT = 20
MAX_MOVES = 5000
STEPS = (0.01, 0.001)
KI_START_RETRIES = 3
#: moves of the approach to the feasible set screened at once (see :func:`_approach`), and
#: the sub-blocks in which they are checked
APPROACH_BLOCK = 32
APPROACH_SPLITS = (0, 1, 4, 12, 32)
AREA_KP_STEP = 0.10
AREA_KI_STEP = 0.05
AREA_KP_FLOOR = 0.01


@dataclass
class PaperResult:
    """Per plant (arrays of shape (P,)): the chosen normalised pair and how it was found."""

    kp: np.ndarray
    ki: np.ndarray
    rise_time_s: np.ndarray
    feasible: np.ndarray
    kp_init: np.ndarray
    ki_init: np.ndarray
    i_conv: np.ndarray
    area_searched: np.ndarray
    evaluations: int
    paths: list = field(default_factory=list)     # per plant: list of (kp, ki, feasible)


def initial_values(problem: TuningProblem, fractions: np.ndarray):
    """60° phase-margin PI per normalised plant, raised until infeasible; shape (P,) each."""
    fractions = np.atleast_2d(fractions)
    omega = np.geomspace(1e-4, 1e3, 7001)
    # loop plant: every delay of the loop (T_com, T_delay, T_meas) included
    g = fractions @ problem.plant(fractions[0]).group_responses(omega)   # (P, N)
    phase = _unwrapped_to_crossing(np.angle(g))
    below = phase <= -np.pi / 2
    if not below.any(axis=1).all():
        raise ValueError("plant phase never reaches -90 deg below 1e3 rad/s")
    idx = np.maximum(np.argmax(below, axis=1), 1)
    # interpolate the -90° crossing in log frequency
    p0, p1 = phase[np.arange(len(idx)), idx - 1], phase[np.arange(len(idx)), idx]
    lw = np.log(omega[idx - 1]) + (-np.pi / 2 - p0) / (p1 - p0) * np.log(omega[idx] / omega[idx - 1])
    wc = np.exp(lw)
    gc = np.abs(np.einsum("pg,gp->p", fractions,
                          problem.plant(fractions[0]).group_responses(wc)))
    kp = np.cos(np.pi / 6) / gc
    ki = kp * wc * np.tan(np.pi / 6)
    for _ in range(40):
        ok = problem.check(fractions, kp, ki).feasible
        if not ok.any():
            break
        kp = np.where(ok, kp * 1.25, kp)
        ki = np.where(ok, ki * 1.25, ki)
    return kp, ki


def _unwrapped_to_crossing(raw: np.ndarray) -> np.ndarray:
    """Rows of phases (rad) as :func:`numpy.unwrap` gives them, at least up to the first
    sample at or below -90°. Before a row's first jump of pi or more unwrap adds exactly 0,
    so where the raw phase reaches -90° before any jump (every PT1 plant: the phase falls
    from 0 and wraps only past -180°) the raw row is the unwrapped one there; the other rows
    are unwrapped whole. (The whole unwrap of the (887, 7001) SimBench phases took 0.26 s,
    12 % of the static design.)"""
    below = raw <= -np.pi / 2
    first = np.where(below.any(axis=1), np.argmax(below, axis=1), raw.shape[1] - 1)
    jump = np.abs(np.diff(raw, axis=1)) >= np.pi
    jumped = np.where(jump.any(axis=1), np.argmax(jump, axis=1), raw.shape[1])
    # a jump between samples j and j + 1 changes sample j + 1 onwards
    rows = np.nonzero(jumped + 1 <= first)[0]
    if rows.size == 0:
        return raw
    out = raw.copy()
    out[rows] = np.unwrap(raw[rows], axis=1)
    return out


def _approach(problem: TuningProblem, fractions, plants, kp, ki, step: float):
    """First feasible move of paths that have not met the feasible set yet, in blocks.

    Before its first feasible point a path only lowers ``kp`` by ``1 - step`` per move (``ki``
    fixed), so the next ``APPROACH_BLOCK`` moves are known in advance. They are screened at
    once on the sampled disk margin (:meth:`TuningProblem.may_meet_disk_margin`: a move that
    fails it is infeasible for certain), and the rest checked in order, in sub-blocks of
    :data:`APPROACH_SPLITS`, only for paths whose first feasible move is not yet known: the
    moves after it are never used, and each of them, being feasible, would cost a step
    response simulated until it settles. Returns, per plant in ``plants``, the number of
    infeasible moves before the first feasible one (``APPROACH_BLOCK`` if none in the block),
    the block's kp values (P, B) and the number of moves checked.
    """
    factors = (1.0 - step) ** np.arange(APPROACH_BLOCK)
    kps = kp[plants, None] * factors[None, :]
    kis = np.repeat(ki[plants, None], APPROACH_BLOCK, axis=1)
    rows = np.repeat(plants, APPROACH_BLOCK)
    may = problem.may_meet_disk_margin(fractions[rows], kps.ravel(),
                                       kis.ravel()).reshape(plants.size, APPROACH_BLOCK)
    first = np.full(plants.size, APPROACH_BLOCK)
    checked = 0
    for lo, hi in zip(APPROACH_SPLITS[:-1], APPROACH_SPLITS[1:]):
        p_idx, j = np.nonzero(may[:, lo:hi] & (first[:, None] == APPROACH_BLOCK))
        if p_idx.size == 0:
            continue
        j = j + lo
        ok = problem.check(fractions[plants[p_idx]], kps[p_idx, j], kis[p_idx, j]).feasible
        checked += p_idx.size
        np.minimum.at(first, p_idx[ok], j[ok])
    return first, kps, checked


def path_search(problem: TuningProblem, fractions, kp, ki, step: float, record: bool = False):
    """One Path Search run per plant from ``(kp, ki)``; returns (best kp, ki, rise,
    evaluations, paths). Plants that never become feasible return NaN.

    The moves are exactly those of the rule in the module docstring; the approach to the
    feasible set (``kp`` lowered with ``ki`` fixed) is evaluated in blocks (:func:`_approach`).
    """
    fractions = np.atleast_2d(fractions)
    n = fractions.shape[0]
    kp, ki = np.array(kp, float), np.array(ki, float)
    best = np.full((3, n), np.nan)            # kp, ki, rise
    es = np.zeros(n, int)
    moves = np.zeros(n, int)
    seen = np.zeros(n, bool)
    active = np.ones(n, bool)
    paths = [[] for _ in range(n)] if record else []
    evaluations = 0
    while True:
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        new = idx[~seen[idx]]
        if new.size:
            first, kps, checked = _approach(problem, fractions, new, kp, ki, step)
            evaluations += checked
            if record:
                for i, j, row in zip(new, first, kps):
                    paths[i].extend((float(k), float(ki[i]), False) for k in row[:j])
            moves[new] += first
            kp[new] = np.where(first < APPROACH_BLOCK, kps[np.arange(new.size),
                                                            np.minimum(first, APPROACH_BLOCK - 1)],
                               kps[:, -1] * (1.0 - step))
            lost = new[(first == APPROACH_BLOCK)
                       & ((kp[new] < 1e-9) | (moves[new] >= MAX_MOVES))]
            active[lost] = False
            idx = np.concatenate([idx[seen[idx]], new[first < APPROACH_BLOCK]])
            if idx.size == 0:
                continue
        chk = problem.check(fractions[idx], kp[idx], ki[idx])
        evaluations += idx.size
        moves[idx] += 1
        if record:
            for j, i in enumerate(idx):
                paths[i].append((float(kp[i]), float(ki[i]), bool(chk.feasible[j])))
        feas = chk.feasible
        better = feas & ~(chk.rise_time_s >= best[2, idx])      # NaN best counts as worse
        b = idx[better]
        best[:, b] = kp[b], ki[b], chk.rise_time_s[better]
        seen[idx[feas]] = True
        es[b] = 0
        es[idx[~better & seen[idx]]] += 1
        ki[idx[feas]] *= 1.0 + step
        kp[idx[~feas]] *= 1.0 - step
        active[idx[es[idx] >= ES_LIMIT]] = False
        active[idx[(kp[idx] < 1e-9) | (moves[idx] >= MAX_MOVES)]] = False
    return best[0], best[1], best[2], evaluations, paths


def _rectangles(kp, ki, ki_init, step: float):
    """The points of every plant's area-search rectangle
    (docs/method.md#convexity-indicator-and-area-search): (plant index, kp, ki),
    each shape (K,), plant by plant and each plant's points in meshgrid order."""
    cand_p, cand_kp, cand_ki = [], [], []
    n_kp = int(np.ceil(np.log(AREA_KP_FLOOR) / np.log(1 - AREA_KP_STEP))) + 1
    for p in range(kp.size):
        kps = kp[p] * (1 - AREA_KP_STEP) ** np.arange(n_kp)
        ki0 = ki[p] * (1 + step)
        n_ki = max(1, int(np.floor(np.log(max(ki_init[p] / ki0, 1.0))
                              / np.log(1 + AREA_KI_STEP))) + 1)
        kis = ki0 * (1 + AREA_KI_STEP) ** np.arange(n_ki)
        gk, gi = np.meshgrid(kps, kis)
        cand_p.append(np.full(gk.size, p))
        cand_kp.append(gk.ravel())
        cand_ki.append(gi.ravel())
    return np.concatenate(cand_p), np.concatenate(cand_kp), np.concatenate(cand_ki)


def area_search(problem: TuningProblem, fractions, kp, ki, ki_init, step: float, beat=None):
    """Scan the area-search rectangle (docs/method.md#convexity-indicator-and-area-search) for each
    plant; returns (kp, ki, rise) of the best
    feasible point found that is faster than ``beat`` (s, per plant; default: any), NaN where
    none, and the number of evaluations.

    Only the fastest feasible point is wanted, so no point is checked that cannot be it: the
    points are screened on the sampled disk margin (certain verdicts), the rest simulated
    until 90 % only (:meth:`TuningProblem.first_rise_s`: their rise times, a fifth of a
    check each), and then checked in order of rise time, fastest first, until a plant's first
    feasible one (which is its best) or one no faster than ``beat``. Checking every point
    gives the same points (``tests/test_paper_area.py``); most of the rectangle is slow,
    feasible loops that a check simulates until they settle.
    """
    fractions = np.atleast_2d(fractions)
    n = fractions.shape[0]
    out = np.full((3, n), np.nan)
    if n == 0:
        return out[0], out[1], out[2], 0
    beat = np.full(n, np.inf) if beat is None else np.asarray(beat, float)
    rows, kps, kis = _rectangles(np.asarray(kp, float), np.asarray(ki, float),
                                 np.asarray(ki_init, float), step)
    may = np.nonzero(problem.may_meet_disk_margin(fractions[rows], kps, kis))[0]
    rise = np.full(rows.size, np.nan)
    rise[may] = problem.first_rise_s(fractions[rows[may]], kps[may], kis[may])
    cand = np.nonzero(rise < beat[rows])[0]
    cand = cand[np.lexsort((cand, rise[cand], rows[cand]))]       # by plant, then rise
    start = np.searchsorted(rows[cand], np.arange(n))
    count = np.diff(np.append(start, cand.size))
    evaluations = rows.size
    open_ = np.nonzero(count > 0)[0]
    lo, width = 0, 1
    while open_.size:
        # each open plant's candidates of rank lo, ..., lo + width - 1 (fastest first)
        take = np.minimum(count[open_] - lo, width)
        p_idx = np.repeat(open_, take)
        rank = lo + np.arange(p_idx.size) - np.repeat(np.cumsum(take) - take, take)
        j = cand[start[p_idx] + rank]
        chk = problem.check(fractions[rows[j]], kps[j], kis[j])
        evaluations += j.size
        # the first feasible point of a plant in rise order is its fastest
        ok = np.nonzero(chk.feasible)[0]
        first = ok[np.r_[True, p_idx[ok][1:] != p_idx[ok][:-1]]] if ok.size else ok
        for k in first:
            out[:, p_idx[k]] = kps[j[k]], kis[j[k]], chk.rise_time_s[k]
        found = np.zeros(n, bool)
        found[p_idx[first]] = True
        lo += width
        width *= 2
        open_ = open_[~found[open_] & (count[open_] > lo)]
    return out[0], out[1], out[2], evaluations


def tune_paper(problem: TuningProblem, fractions, record: bool = False) -> PaperResult:
    """The paper's method for P normalised plants (shape (P, G)), in lock-step."""
    fractions = np.atleast_2d(fractions)
    kp0, ki0 = initial_values(problem, fractions)
    evaluations = 0
    kp, ki = kp0.copy(), STEPS[0] * ki0
    best_kp, best_ki, best_rise = (np.full(len(kp0), np.nan) for _ in range(3))
    min_rise = np.full(len(kp0), np.inf)
    paths = [[] for _ in kp0] if record else []
    for step in STEPS:
        bk, bi, br, ev, pth = path_search(problem, fractions, kp, ki, step, record)
        evaluations += ev
        if record:
            for acc, new in zip(paths, pth):
                acc.extend(new)
        if step == STEPS[0]:
            # paths that never met the feasible set start again with a lower K_I
            for retry in range(1, KI_START_RETRIES + 1):
                lost = np.nonzero(~np.isfinite(br))[0]
                if lost.size == 0:
                    break
                rk, ri, rr, ev, pth = path_search(problem, fractions[lost], kp0[lost],
                                                  ki[lost] * 0.1**retry, step, record)
                evaluations += ev
                bk[lost], bi[lost], br[lost] = rk, ri, rr
                if record:
                    for j, new in zip(lost, pth):
                        paths[j].extend(new)
        improved = np.isfinite(br) & ~(br >= best_rise)
        best_kp = np.where(improved, bk, best_kp)
        best_ki = np.where(improved, bi, best_ki)
        best_rise = np.where(improved, br, best_rise)
        min_rise = np.fmin(min_rise, br)
        # the second run starts at the first run's result (or where the first one ended up)
        kp = np.where(np.isfinite(best_kp), best_kp, kp0 * STEPS[0])
        ki = np.where(np.isfinite(best_ki), best_ki, ki0 * STEPS[0])
    i_conv = min_rise / (problem.average_time_s(fractions) + problem.config.t_meas_s
                         + problem.config.design_t_com_s)
    area = np.isfinite(i_conv) & (i_conv >= 1.0)
    if area.any():
        idx = np.nonzero(area)[0]
        ak, ai, ar, ev = area_search(problem, fractions[idx], best_kp[idx], best_ki[idx],
                                     ki0[idx], STEPS[-1], best_rise[idx])
        evaluations += ev
        better = np.isfinite(ar) & (ar < best_rise[idx])
        best_kp[idx[better]], best_ki[idx[better]], best_rise[idx[better]] = (
            ak[better], ai[better], ar[better])
    return PaperResult(best_kp, best_ki, best_rise, np.isfinite(best_rise), kp0, ki0, i_conv,
                       area, evaluations, paths)
