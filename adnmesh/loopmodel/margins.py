"""Disk margin and classical (allmargin-style) margins of the exact delayed loop.

Conventions follow MATLAB (which the paper used) and python-control:

- disk margin, balanced (skew 0): ``alpha = 1 / max_omega |S - 1/2|``, ``S = 1/(1 + L)``; the
  disk-based gain margin is ``[(2 - alpha)/(2 + alpha), (2 + alpha)/(2 - alpha)]`` (absolute) and
  the phase margin ``2 atan(alpha/2)``. Only meaningful for a stable closed loop; unstable
  candidates get ``alpha = 0``.
- classical margins at *all* crossovers: gain margin ``-1/Re L`` at every phase crossover on the
  negative real axis, phase margin ``mod(arg L, 360 deg) - 180 deg`` at every gain crossover,
  delay margin ``mod(PM, 2 pi)/omega_c``. The scalar figures are the gain margin nearest 0 dB,
  the phase margin smallest in magnitude and the smallest delay margin.

Peaks and crossings are located on the certified grid of :mod:`adnmesh.loopmodel.stability` and refined
on the exact response (:func:`peak`: parabolic steps for the peak; :func:`crossing`: regula
falsi for crossings) to ~1e-7 (peak) and ~1e-13 (crossings) relative frequency.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.frequency_kernels import GOLDEN_STEP, refine_peaks
from adnmesh.loopmodel.frequency_response import as_candidates, loop_points
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.stability import NyquistData

__all__ = ["DiskMargin", "ClassicalMargins", "disk_margin", "disk_margin_at",
           "classical_margins", "crossing", "peak"]

_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class DiskMargin:
    """Balanced disk margin per candidate (arrays of shape (M,)).

    Attributes
    ----------
    alpha : ndarray
        Disk margin alpha (dimensionless); 0 where the closed loop is unstable.
    omega : ndarray
        Critical frequency, rad/s (NaN where unstable).
    """

    alpha: np.ndarray
    omega: np.ndarray

    @property
    def gain_margin(self) -> np.ndarray:
        """Disk-based gain margin interval, absolute, shape (M, 2)."""
        a = self.alpha
        with np.errstate(divide="ignore"):
            upper = np.where(a < 2.0, (2.0 + a) / (2.0 - a), np.inf)
        return np.stack([(2.0 - a) / (2.0 + a), upper], axis=-1)

    @property
    def phase_margin_deg(self) -> np.ndarray:
        """Disk-based phase margin ``2 atan(alpha/2)``, degrees."""
        return np.degrees(2.0 * np.arctan(self.alpha / 2.0))


@dataclass(frozen=True)
class ClassicalMargins:
    """Classical margins per candidate.

    Attributes
    ----------
    gain_margin : ndarray, shape (M,)
        Gain margin nearest 0 dB, absolute ratio (inf if no phase crossover).
    gain_margin_omega : ndarray, shape (M,)
        Its phase-crossover frequency, rad/s.
    phase_margin_deg : ndarray, shape (M,)
        Phase margin smallest in magnitude, degrees (inf if no gain crossover).
    phase_margin_omega : ndarray, shape (M,)
        Its gain-crossover frequency, rad/s.
    delay_margin_s : ndarray, shape (M,)
        Smallest delay margin over all gain crossovers, s.
    all_gain_margins, all_phase_margins_deg, all_delay_margins_s : list of ndarray
        Every crossover's figure, per candidate, ordered by frequency.
    """

    gain_margin: np.ndarray
    gain_margin_omega: np.ndarray
    phase_margin_deg: np.ndarray
    phase_margin_omega: np.ndarray
    delay_margin_s: np.ndarray
    all_gain_margins: list
    all_phase_margins_deg: list
    all_delay_margins_s: list


#: peak of |S - 1/2| located to this in ln(omega) (its value, flat there, then to ~1e-12)
PEAK_XTOL = 1e-7


def disk_margin(plant: Plant, kp, ki, nyq: NyquistData) -> DiskMargin:
    """Balanced disk margin of M candidates.

    The peak of ``2 |S - 1/2|`` is taken from the certified grid of ``nyq`` and refined on
    the exact response by :func:`peak`'s rule, compiled with the loop evaluated inside
    (:func:`adnmesh.loopmodel.frequency_kernels.refine_peaks`; the grid's end points, where no bracket
    exists, by a golden section over their grid interval).

    Parameters
    ----------
    plant : Plant
    kp, ki : array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    nyq : NyquistData
        Result of :func:`adnmesh.loopmodel.stability.nyquist_stability` for the same candidates.
    """
    loop = nyq.loop
    q = np.abs(1.0 - loop) / np.abs(1.0 + loop)            # = 2 |S - 1/2|
    k = np.argmax(q, axis=1)
    rows = np.arange(q.shape[0])
    n = nyq.omega.size
    q_prev = np.where(k > 0, q[rows, np.maximum(k - 1, 0)], np.nan)
    q_next = np.where(k < n - 1, q[rows, np.minimum(k + 1, n - 1)], np.nan)
    return disk_margin_at(plant, kp, ki, nyq.omega, k, q_prev, q[rows, k], q_next, nyq.stable)


@functools.lru_cache(maxsize=256)
def _dynamics(actuators: tuple, t_ict_s: float):
    """Per group the numerator (n0, n1, 0) and denominator (d0, d1, d2) of ``H_g`` and the
    delays (T_delay, T_com + T_meas) in s, for :func:`adnmesh.loopmodel.frequency_kernels.refine_peaks`;
    shape (G, 3), (G, 3), (G, 2) (never written)."""
    num, den = np.zeros((len(actuators), 3)), np.zeros((len(actuators), 3))
    for g, act in enumerate(actuators):
        num[g, :act.numerator.size] = act.numerator
        den[g, :act.denominator.size] = act.denominator
    delays = np.array([[a.t_delay_s, t_ict_s] for a in actuators], dtype=float)
    return num, den, delays


def disk_margin_at(plant: Plant, kp, ki, omega, k, q_prev, q_peak, q_next,
                   stable) -> DiskMargin:
    """:func:`disk_margin` from the sampled peak alone: per candidate the index ``k`` of the
    largest ``q = 2 |S - 1/2|`` on the grid ``omega`` (rad/s, shape (N,)), ``q`` there and at
    the samples before and after it (NaN past an end), and the stability verdict; arrays of
    shape (M,) (e.g. from :func:`adnmesh.loopmodel.frequency_kernels.grid_pass`)."""
    kp, ki, gains = as_candidates(plant, kp, ki)
    k = np.asarray(k)
    n = omega.size
    logw = np.log(omega)

    def value(x, i):
        lw = loop_points(plant, kp[i], ki[i], gains[i], np.exp(x))
        return np.abs(1.0 - lw) / np.abs(1.0 + lw)

    best, where = np.array(q_peak, dtype=float), logw[k].copy()
    inner = np.nonzero((k > 0) & (k < n - 1))[0]
    if inner.size:
        kin = k[inner]
        # peak()'s rule, compiled with the loop evaluated inside (refine_peaks)
        num, den, delays = _dynamics(plant.actuators, float(plant.t_com_s + plant.t_meas_s))
        x, f = refine_peaks(np.ascontiguousarray(kp[inner], dtype=float),
                            np.ascontiguousarray(ki[inner], dtype=float),
                            np.ascontiguousarray(gains[inner], dtype=float), num, den, delays,
                            logw[kin - 1], logw[kin], logw[kin + 1],
                            np.ascontiguousarray(q_prev[inner], dtype=float), best[inner],
                            np.ascontiguousarray(q_next[inner], dtype=float), PEAK_XTOL, 60)
        best[inner], where[inner] = f, x
    edge = np.nonzero((k == 0) | (k == n - 1))[0]
    if edge.size:
        lo = logw[np.maximum(k[edge] - 1, 0)]
        hi = logw[np.minimum(k[edge] + 1, n - 1)]
        x, f = _golden(lambda x: value(x, edge), lo, hi)
        better = f > best[edge]
        best[edge] = np.where(better, f, best[edge])
        where[edge] = np.where(better, x, where[edge])
    alpha = np.where(stable, 2.0 / best, 0.0)
    return DiskMargin(alpha, np.where(stable, np.exp(where), np.nan))


def peak(fun, x0, x1, x2, f0, f1, f2, xtol: float = PEAK_XTOL, iterations: int = 60):
    """Maxima of ``fun`` bracketed by ``x0 < x1 < x2`` with ``f1 >= f0, f2``, vectorised.

    Successive parabolic interpolation with golden-section steps (Brent's rule for a
    maximum): the vertex of the parabola through the three points where it falls inside the
    bracket (a step below ``xtol`` made ``xtol`` long), else a golden step into the larger
    half; a golden step also whenever the bracket has not halved in three steps. A maximum
    is done when its bracket is below ``3 xtol`` (a small parabolic step alone does not
    prove the maximum: the parabola may fit badly). ``fun(x, idx)`` gives the
    values at ``x`` of the maxima ``idx``. Returns ``(x, f)``: the best point met and its
    value (never below ``f1``). 7 evaluations for one SimBench loop where a golden section
    needed 26; the value is scipy's ``optimize.elementwise.find_minimum``'s to 1e-11
    (``tests/test_margins.py``).
    """
    x0, x1, x2 = (np.array(v, dtype=float) for v in (x0, x1, x2))
    f0, f1, f2 = (np.array(v, dtype=float) for v in (f0, f1, f2))
    stall = np.zeros(x1.size, int)
    open_ = np.nonzero(x2 - x0 > xtol)[0]
    for _ in range(iterations):
        if open_.size == 0:
            break
        a, b, c, fa, fb, fc = (v[open_] for v in (x0, x1, x2, f0, f1, f2))
        r, s = (b - a) * (fb - fc), (b - c) * (fb - fa)
        den = r - s
        v = b - 0.5 * ((b - a) * r - (b - c) * s) / np.where(den != 0.0, den, 1.0)
        parabola = (den != 0.0) & (v > a) & (v < c) & (stall[open_] < 3)
        # a step below xtol is made xtol long (towards the vertex), so the bracket shrinks
        nudge = np.where(v >= b, xtol, -xtol)
        v = np.where(np.abs(v - b) < xtol, b + nudge, v)
        parabola &= (v > a) & (v < c)
        wide_right = (c - b) > (b - a)
        golden = np.where(wide_right, b + GOLDEN_STEP * (c - b), b - GOLDEN_STEP * (b - a))
        v = np.where(parabola, v, golden)
        fv = fun(v, open_)
        up = fv > fb                   # v is the new middle; the old middle bounds its side
        left = v < b
        x0[open_] = np.where(up, np.where(left, a, b), np.where(left, v, a))
        f0[open_] = np.where(up, np.where(left, fa, fb), np.where(left, fv, fa))
        x2[open_] = np.where(up, np.where(left, b, c), np.where(left, c, v))
        f2[open_] = np.where(up, np.where(left, fb, fc), np.where(left, fc, fv))
        x1[open_] = np.where(up, v, b)
        f1[open_] = np.where(up, fv, fb)
        width = x2[open_] - x0[open_]
        stall[open_] = np.where(width <= 0.5 * (c - a), 0, stall[open_] + 1)
        open_ = open_[width > 3.0 * xtol]
    return x1, f1


def _golden(fun, lo, hi, iterations: int = 24):
    """Golden-section search for maxima of ``fun`` on ``[lo, hi]`` (vectorised): the best of
    its two last points ``(x, f)`` (24 steps narrow the bracket by ~1e-5)."""
    x1 = hi - _GOLDEN * (hi - lo)
    x2 = lo + _GOLDEN * (hi - lo)
    f1, f2 = fun(x1), fun(x2)
    for _ in range(iterations):
        left = f1 > f2                       # maximum lies in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x2n = np.where(left, x1, lo + _GOLDEN * (hi - lo))
        x1n = np.where(left, hi - _GOLDEN * (hi - lo), x2)
        fn = fun(np.where(left, x1n, x2n))
        f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
        x1, x2 = x1n, x2n
    return np.where(f1 > f2, x1, x2), np.maximum(f1, f2)


#: crossing located to this in ln(omega), i.e. this relative frequency
CROSSING_XTOL = 1e-13


def crossing(fun, lo, hi, xtol: float = CROSSING_XTOL, iterations: int = 100) -> np.ndarray:
    """Sign changes of ``fun`` in brackets ``[lo, hi]`` (arrays, one per crossing), vectorised.

    The Anderson-Bjoerck variant of regula falsi: superlinear (7-10 evaluations of ``fun``
    for a smooth function, where a bisection to the same ``xtol`` takes 40), the root always
    bracketed, a bisection step wherever the secant is degenerate or the bracket has not
    halved in two steps (a function flat on one side). A crossing is done when its
    bracket or its last step is below ``xtol``; only the open ones are evaluated again.
    ``fun(x, idx)`` gives the values at abscissae ``x`` of the crossings ``idx`` (indices into
    ``lo``); ``fun`` at ``lo`` and at ``hi`` must not have the same sign. scipy's
    ``optimize.elementwise.find_root`` finds the same roots (tested) at 1.5-4x the cost for the
    crossings of a few loops: its per-iteration overhead (``benchmarks/bench_numerics.py
    --crossings``).
    """
    a = np.array(lo, dtype=float)
    b = np.array(hi, dtype=float)
    every = np.arange(a.size)
    fa, fb = fun(a, every), fun(b, every)
    stall = np.zeros(a.size, int)          # steps since the bracket last halved
    open_ = np.nonzero((np.abs(b - a) > xtol) & (fb != 0.0) & (fa != 0.0))[0]
    b = np.where(fa == 0.0, a, b)
    for _ in range(iterations):
        if open_.size == 0:
            break
        ai, bi, fai, fbi = a[open_], b[open_], fa[open_], fb[open_]
        denom = fbi - fai
        c = bi - fbi * (bi - ai) / np.where(denom != 0.0, denom, 1.0)
        converged = (denom != 0.0) & (np.abs(c - bi) <= xtol)   # secant step: b is the root
        if converged.any():
            keep = ~converged
            open_, ai, bi, fai, fbi, c = (v[keep] for v in (open_, ai, bi, fai, fbi, c))
            if open_.size == 0:
                break
        inside = (c > np.minimum(ai, bi)) & (c < np.maximum(ai, bi)) & (stall[open_] < 2)
        c = np.where(inside, c, 0.5 * (ai + bi))        # bisect: degenerate secant or a stall
        fc = fun(c, open_)
        flip = np.sign(fc) != np.sign(fbi)           # root between b and c: a takes b's place
        m = 1.0 - fc / np.where(fbi != 0.0, fbi, 1.0)
        new_a = np.where(flip, bi, ai)
        fa[open_] = np.where(flip, fbi, fai * np.where(m > 0.0, m, 0.5))
        a[open_] = new_a
        b[open_], fb[open_] = c, fc
        halved = np.abs(new_a - c) <= 0.5 * np.abs(bi - ai)
        stall[open_] = np.where(halved, 0, stall[open_] + 1)
        done = (fc == 0.0) | (np.abs(new_a - c) <= xtol)
        open_ = open_[~done]
    return b


def classical_margins(plant: Plant, kp, ki, nyq: NyquistData) -> ClassicalMargins:
    """Gain, phase and delay margins at every crossover (like MATLAB ``allmargin``).

    Parameters
    ----------
    plant : Plant
    kp, ki : array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    nyq : NyquistData
        Result of :func:`adnmesh.loopmodel.stability.nyquist_stability` for the same candidates.
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    m = kp.size
    loop = nyq.loop
    logw = np.log(nyq.omega)

    # phase crossovers: Im L changes sign where Re L < 0
    im = loop.imag
    pm_, pk_ = np.nonzero((np.sign(im[:, :-1]) != np.sign(im[:, 1:]))
                          & ((loop.real[:, :-1] < 0) | (loop.real[:, 1:] < 0)))
    kpp, kip, gp = kp[pm_], ki[pm_], gains[pm_]
    w_pc = np.exp(crossing(lambda x, i: loop_points(plant, kpp[i], kip[i], gp[i], np.exp(x)).imag,
                          logw[pk_], logw[pk_ + 1])) if pm_.size else np.zeros(0)
    re_pc = loop_points(plant, kpp, kip, gp, w_pc).real if pm_.size else np.zeros(0)
    keep = re_pc < 0
    pm_, w_pc, gm_all = pm_[keep], w_pc[keep], -1.0 / re_pc[keep]

    # gain crossovers: |L| - 1 changes sign
    mag = np.abs(loop) - 1.0
    gm_, gk_ = np.nonzero(np.sign(mag[:, :-1]) != np.sign(mag[:, 1:]))
    kpg, kig, gg = kp[gm_], ki[gm_], gains[gm_]
    w_gc = np.exp(crossing(lambda x, i: np.abs(loop_points(plant, kpg[i], kig[i], gg[i],
                                                           np.exp(x))) - 1.0,
                          logw[gk_], logw[gk_ + 1])) if gm_.size else np.zeros(0)
    l_gc = loop_points(plant, kpg, kig, gg, w_gc) if gm_.size else np.zeros(0, complex)
    pm_all = np.remainder(np.angle(l_gc, deg=True), 360.0) - 180.0
    dm_all = np.remainder(np.radians(pm_all), 2.0 * np.pi) / np.where(w_gc > 0, w_gc, 1.0)

    gain_margin = np.full(m, np.inf)
    gain_margin_omega = np.full(m, np.nan)
    phase_margin = np.full(m, np.inf)
    phase_margin_omega = np.full(m, np.nan)
    delay_margin = np.full(m, np.inf)
    all_gm, all_pm, all_dm = [], [], []
    gm_split = np.split(np.arange(pm_.size), np.searchsorted(pm_, np.arange(1, m)))
    pm_split = np.split(np.arange(gm_.size), np.searchsorted(gm_, np.arange(1, m)))
    for i in range(m):
        g, p = gm_split[i], pm_split[i]
        all_gm.append(gm_all[g])
        all_pm.append(pm_all[p])
        all_dm.append(dm_all[p])
        if g.size:
            j = g[np.argmin(np.abs(np.log(gm_all[g])))]
            gain_margin[i], gain_margin_omega[i] = gm_all[j], w_pc[j]
        if p.size:
            j = p[np.argmin(np.abs(pm_all[p]))]
            phase_margin[i], phase_margin_omega[i] = pm_all[j], w_gc[j]
            delay_margin[i] = dm_all[p].min()
    return ClassicalMargins(gain_margin, gain_margin_omega, phase_margin, phase_margin_omega,
                            delay_margin, all_gm, all_pm, all_dm)
