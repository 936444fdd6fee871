"""Compiled frequency-domain pass of the constraint check (numba).

A constraint check samples the loop ``L(j omega)`` of every candidate on the certified grid of
:mod:`adnmesh.loopmodel.stability` (hundreds of frequencies) and needs from it only a few numbers per
candidate: the sampled peak of ``2 |S - 1/2| = |1 - L| / |1 + L|`` with its neighbours (the
disk margin's bound and the bracket that :func:`adnmesh.loopmodel.margins.peak` refines), and, for the
candidates that pass that screen, the winding of ``F = 1 + L`` with the grid intervals whose
Lipschitz test fails (refined by :func:`adnmesh.loopmodel.stability._refine`). :func:`grid_pass` computes
them in one pass over the grid without the (M, N) complex arrays numpy would build for each
step (``L``, ``F``, ``|F|``, the quotients, their angles): the same formulas, so the same
values to rounding (``tests/test_freq_kernels.py`` compares it with the numpy path).
"""
from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["grid_pass", "first_above", "last_at_least", "refine_peaks", "GOLDEN_STEP"]


@numba.njit(cache=True)
def grid_pass(kp, ki, gains, resp, omega, screen_min, rho, drho, winding_too):  # pragma: no cover
    """One pass over the common grid for M candidates.

    Parameters
    ----------
    kp, ki : (M,) float
        PI gains, 1/W and 1/(W s).
    gains : (M, G) float
        Group gains, W.
    resp : (G, N) complex
        Group responses with the loop's delays, :meth:`adnmesh.loopmodel.plant.Plant.group_responses`.
    omega : (N,) float
        The grid, rad/s, increasing.
    screen_min : float
        Candidates whose sampled bound ``2 / max q`` is below this get no winding (``keep``
        False).
    rho, drho : (G, N - 1) float
        Per grid interval, bounds of ``|H_g|`` and of ``|dH_g/domega| + theta_g |H_g|``
        (:func:`adnmesh.loopmodel.stability._group_bounds`, the delays' share included); not read
        without ``winding_too``.
    winding_too : bool
        False: the peaks alone (no candidate is kept).

    Returns
    -------
    q_peak, q_prev, q_next : (M,) float
        Largest ``q`` on the grid and ``q`` at the samples before and after it (NaN past an
        end).
    k_peak : (M,) int
        Its index (the first one on a tie, as ``argmax``).
    keep : (M,) bool
        ``2 / q_peak >= screen_min``.
    winding : (M,) float
        ``arg F(omega_0) + pi/2 - arg F(omega_N-1)`` plus the wrapped change of ``arg F`` over
        every interval that passed the Lipschitz test (kept candidates; else 0): the
        :func:`adnmesh.loopmodel.stability.nyquist_stability` sum before the failed intervals' share.
    bad : (M, N - 1) bool
        Intervals of kept candidates that failed the test (their arg change is not in
        ``winding``).
    """
    m_n, g_n = gains.shape
    n = omega.size
    q_peak = np.empty(m_n)
    q_prev = np.empty(m_n)
    q_next = np.empty(m_n)
    k_peak = np.empty(m_n, np.int64)
    keep = np.zeros(m_n, np.bool_)
    winding = np.zeros(m_n)
    bad = np.zeros((m_n, max(n - 1, 0)), np.bool_)
    f_re = np.empty(n)
    f_im = np.empty(n)
    q2 = np.empty(n)
    # per interval: its width and width / lo, width / lo^2 (the Lipschitz bound's factors;
    # a rounding here only moves an interval between passing and bisection, both certified)
    width = np.empty(max(n - 1, 0))
    width_lo = np.empty(max(n - 1, 0))
    width_lo2 = np.empty(max(n - 1, 0))
    for k in range(n - 1):
        width[k] = omega[k + 1] - omega[k]
        width_lo[k] = width[k] / omega[k]
        width_lo2[k] = width_lo[k] / omega[k]
    for m in range(m_n):
        best = -1.0
        kbest = 0
        for k in range(n):
            acc_re = 0.0
            acc_im = 0.0
            for g in range(g_n):
                acc_re += gains[m, g] * resp[g, k].real
                acc_im += gains[m, g] * resp[g, k].imag
            c_im = -ki[m] / omega[k]
            l_re = kp[m] * acc_re - c_im * acc_im
            l_im = kp[m] * acc_im + c_im * acc_re
            f_re[k] = 1.0 + l_re
            f_im[k] = l_im
            # q^2 = |1 - L|^2 / |1 + L|^2: same order as q, no square roots in the loop
            q2[k] = ((1.0 - l_re) ** 2 + l_im * l_im) / ((1.0 + l_re) ** 2 + l_im * l_im)
            if q2[k] > best:
                best = q2[k]
                kbest = k
        q_peak[m] = math.sqrt(best)
        k_peak[m] = kbest
        q_prev[m] = math.sqrt(q2[kbest - 1]) if kbest > 0 else np.nan
        q_next[m] = math.sqrt(q2[kbest + 1]) if kbest < n - 1 else np.nan
        if not (winding_too and 2.0 / q_peak[m] >= screen_min):
            continue
        keep[m] = True
        # sum of the wrapped arg changes over the intervals that pass the Lipschitz test (each
        # below pi/2): they telescope to arg F at the ends, plus 2 pi per crossing of the
        # negative real axis, minus the plain arg differences of the failed intervals
        crossings = 0
        failed = 0.0
        kp_m, ki_m = kp[m], ki[m]
        for k in range(n - 1):
            s1 = 0.0
            s2 = 0.0
            for g in range(g_n):
                s1 += gains[m, g] * rho[g, k]
                s2 += gains[m, g] * drho[g, k]
            # (omega[k + 1] - lo) (ki / lo^2 s1 + (kp + ki / lo) s2)
            step = ki_m * width_lo2[k] * s1 + (kp_m * width[k] + ki_m * width_lo[k]) * s2
            if step * step < 0.998001 * (f_re[k] ** 2 + f_im[k] ** 2):
                below_a = math.copysign(1.0, f_im[k]) < 0.0
                below_b = math.copysign(1.0, f_im[k + 1]) < 0.0
                if below_a != below_b and f_re[k] < 0.0:
                    crossings += 1 if below_b else -1
            else:
                bad[m, k] = True
                failed += (math.atan2(f_im[k + 1], f_re[k + 1])
                           - math.atan2(f_im[k], f_re[k]))
        winding[m] = np.pi / 2.0 + 2.0 * np.pi * crossings - failed
    return q_peak, q_prev, q_next, k_peak, keep, winding, bad


@numba.njit(cache=True, inline="always")
def _low_bound(m, k, a, frac, rho, beta_term, grid):  # pragma: no cover - compiled
    """``grid[k] a[m] (frac[m] . rho[:, k]) + frac[m] . beta_term[:, k]``."""
    s_rho = 0.0
    s_beta = 0.0
    for g in range(frac.shape[1]):
        s_rho += frac[m, g] * rho[g, k]
        s_beta += frac[m, g] * beta_term[g, k]
    return grid[k] * a[m] * s_rho + s_beta


@numba.njit(cache=True)
def first_above(a, frac, rho, beta_term, grid, level):  # pragma: no cover - compiled
    """Per candidate, the first grid index where ``grid a (frac . rho) + frac . beta_term``
    exceeds ``level`` (the grid's size if none): the low-frequency certificate's bound of
    :func:`adnmesh.loopmodel.stability._low_frequency_limit`. The bound is nondecreasing along the grid
    (nonnegative terms, each nondecreasing, on a grid 12 % apart), so a bisection finds
    that index (the one a scan would). ``a`` (M,), ``frac`` (M, G), ``rho`` and
    ``beta_term`` (G, K), ``grid`` (K,)."""
    m_n = frac.shape[0]
    k_n = grid.size
    out = np.empty(m_n, np.int64)
    for m in range(m_n):
        lo, hi = 0, k_n               # the index is in [lo, hi]; bound(hi) > level if hi < K
        while lo < hi:
            mid = (lo + hi) // 2
            if _low_bound(m, mid, a, frac, rho, beta_term, grid) > level:
                hi = mid
            else:
                lo = mid + 1
        out[m] = lo
    return out


@numba.njit(cache=True, inline="always")
def _envelope(m, k, kp, ki, gains, rho, lo):  # pragma: no cover - compiled
    """``(kp[m] + ki[m] / lo[k]) gains[m] . rho[:, k]``."""
    s = 0.0
    for g in range(gains.shape[1]):
        s += gains[m, g] * rho[g, k]
    return (kp[m] + ki[m] / lo[k]) * s


@numba.njit(cache=True)
def last_at_least(kp, ki, gains, rho, lo, level, monotone):  # pragma: no cover - compiled
    """Per candidate, the last interval index where ``(kp + ki / lo) gains . rho >= level``
    (-1 if none): the envelope of :func:`adnmesh.loopmodel.stability._high_frequency_limit`. With
    ``monotone`` (every ``rho`` row nonincreasing, e.g. constant numerators: then each factor
    is, and so is every rounded product and sum) by bisection, else scanned from the top (a
    numerator's bound may grow with the frequency). ``kp``, ``ki`` (M,), ``gains`` (M, G),
    ``rho`` (G, K), ``lo`` (K,)."""
    m_n = gains.shape[0]
    k_n = lo.size
    out = np.empty(m_n, np.int64)
    for m in range(m_n):
        if monotone:
            a, b = -1, k_n - 1        # the index is in [a, b]; env(a) >= level if a >= 0
            while a < b:
                mid = (a + b + 1) // 2
                if _envelope(m, mid, kp, ki, gains, rho, lo) >= level:
                    a = mid
                else:
                    b = mid - 1
            out[m] = a
            continue
        idx = -1
        for k in range(k_n - 1, -1, -1):
            if _envelope(m, k, kp, ki, gains, rho, lo) >= level:
                idx = k
                break
        out[m] = idx
    return out


#: a golden step into an interval (0.382): of :func:`refine_peaks` and of the uncompiled rule
#: it follows, :func:`adnmesh.loopmodel.margins.peak`
GOLDEN_STEP = 1.0 - (math.sqrt(5.0) - 1.0) / 2.0


@numba.njit(cache=True, inline="always")
def _q_at(x, kp, ki, gains, num, den, delays):  # pragma: no cover - compiled
    """``|1 - L| / |1 + L|`` at ``omega = exp(x)`` (the formulas of
    :meth:`adnmesh.loopmodel.plant.Actuator.response` and :func:`adnmesh.loopmodel.frequency_response.loop_points`)."""
    w = math.exp(x)
    s = complex(0.0, w)
    acc = 0j
    for g in range(gains.size):
        if den[g, 2] == 0.0 and num[g, 1] == 0.0:           # pt1
            r = np.exp(-s * delays[g, 0]) / (den[g, 0] + den[g, 1] * s)
        else:
            r = (num[g, 0] + num[g, 1] * s) / (den[g, 0] + s * (den[g, 1] + s * den[g, 2])) \
                * np.exp(-s * delays[g, 0])
        acc += gains[g] * (r * np.exp(-1j * w * delays[g, 1]))
    lw = complex(kp, -ki / w) * acc
    return abs(1.0 - lw) / abs(1.0 + lw)


@numba.njit(cache=True)
def refine_peaks(kp, ki, gains, num, den, delays, x0, x1, x2, f0, f1, f2, xtol,
                 iterations):  # pragma: no cover - compiled
    """:func:`adnmesh.loopmodel.margins.peak` for the peaks of ``q = 2 |S - 1/2|`` in ``ln omega``,
    candidate by candidate with the loop evaluated here: the same rule (Brent's successive
    parabolic interpolation with golden steps), the same steps.

    ``kp``, ``ki`` (M,); ``gains`` (M, G), W; per group ``num`` (n0, n1, 0) and ``den``
    (d0, d1, d2) in ascending powers of s, ``delays`` (T_delay, T_com + T_meas), s; brackets
    ``x0 < x1 < x2`` (ln rad/s) with their values ``f``, each (M,). Returns (x, f), (M,).
    """
    m_n = kp.size
    x_out = np.empty(m_n)
    f_out = np.empty(m_n)
    for m in range(m_n):
        a, b, c = x0[m], x1[m], x2[m]
        fa, fb, fc = f0[m], f1[m], f2[m]
        stall = 0
        if c - a > xtol:
            for _ in range(iterations):
                r = (b - a) * (fb - fc)
                s = (b - c) * (fb - fa)
                dn = r - s
                v = b - 0.5 * ((b - a) * r - (b - c) * s) / (dn if dn != 0.0 else 1.0)
                parabola = (dn != 0.0) and (v > a) and (v < c) and (stall < 3)
                nudge = xtol if v >= b else -xtol
                if abs(v - b) < xtol:
                    v = b + nudge
                parabola = parabola and (v > a) and (v < c)
                if not parabola:
                    v = b + GOLDEN_STEP * (c - b) if (c - b) > (b - a) \
                        else b - GOLDEN_STEP * (b - a)
                fv = _q_at(v, kp[m], ki[m], gains[m], num, den, delays)
                width_before = c - a
                if fv > fb:                     # v is the new middle
                    if v < b:
                        c, fc = b, fb
                    else:
                        a, fa = b, fb
                    b, fb = v, fv
                elif v < b:
                    a, fa = v, fv
                else:
                    c, fc = v, fv
                width = c - a
                stall = 0 if width <= 0.5 * width_before else stall + 1
                if not width > 3.0 * xtol:
                    break
        x_out[m] = b
        f_out[m] = fb
    return x_out, f_out
