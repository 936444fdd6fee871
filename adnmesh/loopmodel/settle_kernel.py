"""Compiled simulate-until-settled loop of first-order plants (numba).

:func:`adnmesh.loopmodel.step_response._simulate_until_settled` advances a bucket of candidates block by
block: after each block it takes the block's step figures, drops the candidates that have
settled (or overshot, or reached their horizon), doubles the step when every remaining
response is smooth, and sizes the next block. For first-order groups (PT1, the reference
model) :func:`settle_lanes` runs that whole loop compiled: the same kernels
(:func:`~adnmesh.loopmodel.step_kernels.advance_exact_first_order_lanes`,
:func:`~adnmesh.loopmodel.step_kernels.advance_first_order_lanes`,
:func:`~adnmesh.loopmodel.step_kernels.accumulate_lanes`) on the same blocks, the same drop, doubling and
block-size rules in the same order, so every figure is bit for bit the one of the Python loop
(``tests/test_settle_loop.py``). The Python loop cost ~0.1 ms of numpy glue per block (the
figures' masks, the copies of every buffer when candidates drop out, the step doubling), as
much as the kernels themselves for the small batches of a search.

The discretisations of every step the loop may double to (``h, 2h, 4h, ...``, as long as
``2h`` does not exceed the shortest forward path delay) come precomputed from
:func:`adnmesh.loopmodel.step_response._levels`, so the compiled loop does no matrix exponential.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from adnmesh.loopmodel.step_kernels import (accumulate_lanes, advance_exact_first_order_lanes,
                       advance_first_order_lanes)

__all__ = ["settle_lanes", "coarsen_buffer", "COARSEN_CURVATURE", "SETTLED_FRACTION",
           "MAX_BLOCK_VALUES"]

#: largest |second difference| of y (per step) at which the step may be doubled
COARSEN_CURVATURE = 1e-7
#: a response is settled once it has stayed in the smallest band for the last this fraction
#: ... of the simulated time, counted from the start: within it since 0.75 x the time
SETTLED_FRACTION = 0.75
#: samples x candidates of one block at most (the block's output array: 160 MB)
MAX_BLOCK_VALUES = 20_000_000


@numba.njit(cache=True)
def _output_gains(gains, c):  # pragma: no cover - compiled
    """``K_g C_g`` per group and candidate, (G, M), from gains (M, G) and C (G,)."""
    m_count, g_count = gains.shape
    kc = np.empty((g_count, m_count))
    for g in range(g_count):
        for m in range(m_count):
            kc[g, m] = gains[m, g] * c[g]
    return kc


@numba.njit(cache=True)
def _take_1d(a, rows):  # pragma: no cover - compiled
    out = np.empty(rows.size, a.dtype)
    for i in range(rows.size):
        out[i] = a[rows[i]]
    return out


@numba.njit(cache=True)
def _take_columns(a, rows):  # pragma: no cover - compiled
    """``a[:, rows]`` in C order."""
    out = np.empty((a.shape[0], rows.size), a.dtype)
    for r in range(a.shape[0]):
        for i in range(rows.size):
            out[r, i] = a[r, rows[i]]
    return out


@numba.njit(cache=True)
def _take_rows(a, rows):  # pragma: no cover - compiled
    """``a[rows, :]`` in C order."""
    out = np.empty((rows.size, a.shape[1]), a.dtype)
    for i in range(rows.size):
        for g in range(a.shape[1]):
            out[i, g] = a[rows[i], g]
    return out


@numba.njit(cache=True)
def coarsen_buffer(buf, k_old, old_ring, ring):  # pragma: no cover - compiled
    """A delay buffer (old_ring + 1, M) at step h as one at 2h (ring + 1, M), sample index
    ``k_old`` (even) becoming ``k_old // 2``: every second sample kept, the zero column 0."""
    k = k_old // 2
    out = np.zeros((ring + 1, buf.shape[1]))
    for j_new in range(k - ring + 2, k + 1):
        j_old = 2 * j_new
        if j_old >= 0 and j_old < k_old - old_ring + 1:
            raise ValueError("delay buffer too short to coarsen")
        col_old = j_old % old_ring if j_old >= 0 else old_ring
        if j_new >= 0:
            col_new = j_new % ring
            for m in range(buf.shape[1]):
                out[col_new, m] = buf[col_old, m]
    return out


@numba.njit(cache=True)
def settle_lanes(kp, ki, gains, t_min, t_max, bands, stop_above, until_rise, chunk,
                 levels):  # pragma: no cover - compiled
    """Simulate M first-order loops until each has settled; their step figures.

    Parameters
    ----------
    kp, ki : (M,) float
        PI gains, 1/W and 1/(W s).
    gains : (M, G) float
        Group gains, W.
    t_min, t_max : (M,) float
        Shortest and longest horizon per candidate, s.
    bands : (3,) float
        Settling bands (fractions): the configured one, 2 %, and the settled test's.
    stop_above : float
        A candidate whose response exceeds this is finished at once (``inf``: never).
    until_rise : bool
        A candidate is finished once it has reached 90 %.
    chunk : int
        Samples of the first block.
    levels : tuple of arrays
        The discretisations per step the loop may use (``step_response._levels``), in this
        order:

        hs : (L,) float
            The steps, s: ``hs[0]`` first, each the double of the one before.
        phi, gl, gr, c : (L, G) float
            Per step, each group's FOH discretisation (one state).
        n_in, f_in : (L, G) int, float
            Per step, each forward path delay in whole steps and the fraction left.
        n_meas, f_meas : (L,) int, float
            Per step, the measurement delay likewise.
        ring : (L,) int
            Per step, the delay buffers' ring length.
        exact : (L,) bool
            Per step, whether every delay is a whole number of steps.

    Returns
    -------
    overshoot_pct, rise_time_s, settling_time_s, settling_time_2pct_s, peak, peak_time_s,
    horizon_s : (M,) float
        As :func:`adnmesh.loopmodel.step_response._simulate_until_settled` returns them.
    """
    hs, phi, gl, gr, c, n_in, f_in, n_meas, f_meas, ring, exact = levels
    m0 = kp.size
    g_count = gains.shape[1]
    r_os = np.full(m0, np.nan)
    r_tr = np.full(m0, np.nan)
    r_ts = np.full(m0, np.nan)
    r_ts2 = np.full(m0, np.nan)
    r_pk = np.full(m0, np.nan)
    r_tp = np.full(m0, np.nan)
    r_hor = np.full(m0, np.nan)
    lev = 0
    h = hs[0]
    rg = ring[0]
    kp_a, ki_a, gains_a = kp.copy(), ki.copy(), gains.copy()
    kc = _output_gains(gains_a, c[0])
    p_y = np.zeros((rg + 1, m0))
    y_hist = np.zeros((rg + 1, m0))
    for m in range(m0):
        p_y[0, m] = kp_a[m]                  # right limit of P_Y at t = 0
    x = np.zeros((g_count, m0))
    x_int = np.zeros(m0)
    err = np.ones(m0)
    t10 = np.full(m0, np.nan)
    t90 = np.full(m0, np.nan)
    peak = np.full(m0, -np.inf)
    peak_t = np.zeros(m0)
    settle = np.zeros((bands.size, m0))
    last = np.zeros(m0)
    alive = np.arange(m0)
    tmin_a, tmax_a = t_min.copy(), t_max.copy()
    uniform = np.empty(0)
    # sample index (not the constant 0 to numba's typing: the kernels would be compiled
    # for a literal first argument too)
    k = chunk - chunk
    n = m0
    while n > 0:
        t0 = k * h
        out = np.empty((chunk, n))
        if exact[lev]:
            advance_exact_first_order_lanes(chunk, k, rg, h, kp_a, ki_a, kc, phi[lev],
                                            gl[lev], gr[lev], x, p_y, y_hist, x_int, err,
                                            n_in[lev], n_meas[lev], out)
        else:
            advance_first_order_lanes(chunk, k, rg, h, kp_a, ki_a, kc, phi[lev], gl[lev],
                                      gr[lev], x, p_y, y_hist, x_int, err, n_in[lev],
                                      f_in[lev], n_meas[lev], f_meas[lev], out)
        k += chunk
        curvature = np.empty(n)
        accumulate_lanes(t0, h, uniform, out, last, t10, t90, peak, peak_t, bands, settle,
                         curvature)
        elapsed = k * h
        keep = np.empty(n, np.int64)
        n_keep = 0
        for i in range(n):
            settled = (settle[2, i] <= SETTLED_FRACTION * elapsed) and (elapsed >= tmin_a[i])
            over = peak[i] > stop_above
            if until_rise:
                over = over or np.isfinite(t90[i])
            if not (settled or over or elapsed >= tmax_a[i]):
                keep[n_keep] = i
                n_keep += 1
                continue
            j = alive[i]
            v = 100.0 * (peak[i] - 1.0)
            r_os[j] = 0.0 if v < 0.0 else v             # np.maximum(0, v): NaN stays NaN
            r_tr[j] = t90[i] - t10[i]
            if settled:
                r_ts[j], r_ts2[j] = settle[0, i], settle[1, i]
            elif over:
                r_ts[j], r_ts2[j] = np.nan, np.nan
            else:
                r_ts[j], r_ts2[j] = np.inf, np.inf
            r_pk[j], r_tp[j], r_hor[j] = peak[i], peak_t[i], elapsed
        if n_keep < n:
            rows = keep[:n_keep]
            alive = _take_1d(alive, rows)
            tmin_a, tmax_a = _take_1d(tmin_a, rows), _take_1d(tmax_a, rows)
            kp_a, ki_a = _take_1d(kp_a, rows), _take_1d(ki_a, rows)
            gains_a = _take_rows(gains_a, rows)
            x_int, err = _take_1d(x_int, rows), _take_1d(err, rows)
            p_y, y_hist = _take_columns(p_y, rows), _take_columns(y_hist, rows)
            x, kc = _take_columns(x, rows), _take_columns(kc, rows)
            t10, t90 = _take_1d(t10, rows), _take_1d(t90, rows)
            peak, peak_t = _take_1d(peak, rows), _take_1d(peak_t, rows)
            last = _take_1d(last, rows)
            settle = _take_columns(settle, rows)
            curvature = _take_1d(curvature, rows)
            n = n_keep
        if n == 0:
            break
        # smooth responses (second differences far below the error target) need no fine
        # step: doubling h multiplies the hold error by ~4
        smooth = True
        for i in range(n):
            if not curvature[i] < COARSEN_CURVATURE:
                smooth = False
                break
        if chunk > 2 and lev + 1 < hs.size and smooth:
            if k % 2:
                raise ValueError("coarsen at an even sample index")
            old_ring = rg
            lev += 1
            h = hs[lev]
            rg = ring[lev]
            p_y = coarsen_buffer(p_y, k, old_ring, rg)
            y_hist = coarsen_buffer(y_hist, k, old_ring, rg)
            k = k // 2
            kc = _output_gains(gains_a, c[lev])
        chunk = min(max(int(math.ceil(0.5 * elapsed / h)), chunk // 2), MAX_BLOCK_VALUES // n)
        chunk += (k + chunk) % 2              # end every block on an even sample index
    return r_os, r_tr, r_ts, r_ts2, r_pk, r_tp, r_hor
