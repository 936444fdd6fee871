"""Compiled inner loop of the step-response simulation (numba).

:func:`advance` runs the method of steps of :mod:`adnmesh.loopmodel.step_response` for M candidates over a
block of samples, with delays read from precomputed (interpolating) taps; :func:`advance_exact`
is the same arithmetic for the common case of delays that are whole multiples of the step, with
the buffer columns computed in the loop (no taps, no interpolation). :func:`accumulate` is the
step-figure rule of :mod:`adnmesh.loopmodel.step_figures` (rise, settling, peak of sampled responses, on
the simulation's uniform grid or at given sample times). For first-order groups (PT1, the
reference model) :func:`advance_exact_first_order_lanes` and :func:`advance_first_order_lanes`
run the same arithmetic with the candidates as the inner loop (buffers stored sample by
sample: the columns, taps and t < 0 tests are shared, the candidates fill SIMD lanes), and
:func:`accumulate_lanes` takes their (steps, M) blocks. They are the hot loops of the step
responses (the frequency domain's are in :mod:`adnmesh.loopmodel.frequency_kernels`); everything else is
vectorised numpy. Candidates are independent, so the general kernels' outer loop runs in
parallel threads for large batches.
"""
from __future__ import annotations

import numba
import numpy as np

__all__ = ["advance", "advance_exact", "advance_first_order_lanes",
           "advance_exact_first_order_lanes", "accumulate", "accumulate_lanes", "delay_taps"]

#: below this many candidates the serial kernel wins (no thread start-up)
PARALLEL_FROM = 64
#: "no tap before": a floor position no sample has (see :func:`_tap_after`)
_NO_TAP = -(1 << 62)


def advance(steps, k0, ring, h, kp, *rest):
    """Dispatch to the parallel kernel for large batches, the serial one otherwise."""
    kernel = _advance_parallel if kp.size >= PARALLEL_FROM else _advance_serial
    kernel(steps, k0, ring, h, kp, *rest)


@numba.njit(cache=True, inline="always")
def _lag_step(phi, gl, gr, kc, x, tmp, u_l, u_r):  # pragma: no cover - compiled
    """One exact FOH step ``x <- Phi x + gl u_l + gr u_r`` of a group; returns its output."""
    n = x.size
    for a in range(n):
        acc = gl[a] * u_l + gr[a] * u_r
        for b in range(n):
            acc += phi[a, b] * x[b]
        tmp[a] = acc
    y = 0.0
    for a in range(n):
        x[a] = tmp[a]
        y += kc[a] * tmp[a]
    return y


@numba.njit(cache=True, inline="always")
def _tap_inputs(p_y, m, i, g, l0, l1, lw, r0, r1, rw):  # pragma: no cover - compiled
    """Group g's delayed input at the left and right end of step i, from the taps."""
    u_l = p_y[m, l0[i, g]] * (1.0 - lw[i, g]) + p_y[m, l1[i, g]] * lw[i, g]
    u_r = p_y[m, r0[i, g]] * (1.0 - rw[i, g]) + p_y[m, r1[i, g]] * rw[i, g]
    return u_l, u_r


@numba.njit(cache=True, inline="always")
def _exact_inputs(p_y, m, col, j, d, ring):  # pragma: no cover - compiled
    """The input delayed by exactly d steps at the left and right end of step j (column
    ``col``); 0 before t = 0, and the left limit 0 at t = 0 itself for the right end."""
    c_l = col - d
    if c_l < 0:
        c_l += ring
    c_r = c_l + 1 if c_l + 1 < ring else 0
    u_l = p_y[m, c_l] if j - d >= 0 else 0.0
    u_r = p_y[m, c_r] if j + 1 - d > 0 else 0.0
    return u_l, u_r


@numba.njit(cache=True, inline="always")
def _pi(kp, ki, half_h, y_meas, xi, e_prev):  # pragma: no cover - compiled
    """The PI on the measured output: trapezoidal integral; returns (P_Y, integral, error)."""
    e = 1.0 - y_meas
    xi += half_h * (e_prev + e)
    return kp * e + ki * xi, xi, e


@numba.njit(cache=True, inline="always")
def _exact_measured(y_hist, m, nxt, j, n_meas, ring):  # pragma: no cover - compiled
    """The output delayed by exactly ``n_meas`` steps at sample j + 1 (column ``nxt``)."""
    c_m = nxt - n_meas
    if c_m < 0:
        c_m += ring
    return y_hist[m, c_m] if j + 1 - n_meas >= 0 else 0.0


def _advance(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist, x_int, err,
            l0, l1, lw, r0, r1, rw, m0, m1, mw, out):  # pragma: no cover - compiled
    """Advance every candidate ``steps`` samples; writes ``out[m, i]`` = y at sample k0+i+1.

    Shapes: kc (M, G, n), phi (G, n, n), gl/gr (G, n), x (M, G, n), p_y/y_hist (M, ring+1),
    x_int/err (M,), taps l0.. (steps, G) and m0.. (steps,); state arrays are updated in place.
    """
    m_count, g_count, n = x.shape
    half_h = 0.5 * h
    for m in numba.prange(m_count):
        xm = x[m].copy()
        tmp = np.empty(n)
        xi = x_int[m]
        e_prev = err[m]
        for i in range(steps):
            y = 0.0
            for g in range(g_count):
                u_l, u_r = _tap_inputs(p_y, m, i, g, l0, l1, lw, r0, r1, rw)
                y += _lag_step(phi[g], gl[g], gr[g], kc[m, g], xm[g], tmp, u_l, u_r)
            col = (k0 + i + 1) % ring
            y_hist[m, col] = y
            y_meas = y_hist[m, m0[i]] * (1.0 - mw[i]) + y_hist[m, m1[i]] * mw[i]
            p_y[m, col], xi, e_prev = _pi(kp[m], ki[m], half_h, y_meas, xi, e_prev)
            out[m, i] = y
        x[m] = xm
        x_int[m] = xi
        err[m] = e_prev


_advance_parallel = numba.njit(cache=True, parallel=True)(_advance)
_advance_serial = numba.njit(cache=True, parallel=False)(_advance)


@numba.njit(cache=True)
def advance_first_order_lanes(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist,
                              x_int, err, n_in, f_in, n_meas, f_meas,
                              out):  # pragma: no cover - compiled
    """:func:`advance` for groups of first order (one state each) with the candidates as the
    inner loop (see :func:`advance_exact_first_order_lanes`: the same layouts, bit for bit the
    same results). The delay taps (:func:`delay_taps`'s, element by element) are computed here,
    once per step and group for all candidates: delays ``n_in + f_in`` (G,) and
    ``n_meas + f_meas`` steps."""
    g_count, m_count = x.shape
    half_h = 0.5 * h
    y = np.empty(m_count)
    # each tap's floor position and column at the step before (_NO_TAP: none yet)
    l_j0 = np.full(g_count, _NO_TAP, np.int64)
    l_col = np.zeros(g_count, np.int64)
    r_j0 = np.full(g_count, _NO_TAP, np.int64)
    r_col = np.zeros(g_count, np.int64)
    m_j0, m_col = _NO_TAP, 0
    for i in range(steps):
        for m in range(m_count):
            y[m] = 0.0
        for g in range(g_count):
            a0, a1, wa, l_j0[g], l_col[g] = _tap_after(k0 + i, n_in[g], f_in[g], ring, False,
                                                       l_j0[g], l_col[g])
            b0, b1, wb, r_j0[g], r_col[g] = _tap_after(k0 + 1 + i, n_in[g], f_in[g], ring,
                                                       True, r_j0[g], r_col[g])
            pg, glg, grg = phi[g], gl[g], gr[g]
            for m in range(m_count):
                u_l = p_y[a0, m] * (1.0 - wa) + p_y[a1, m] * wa
                u_r = p_y[b0, m] * (1.0 - wb) + p_y[b1, m] * wb
                acc = glg * u_l + grg * u_r
                acc += pg * x[g, m]
                x[g, m] = acc
                y_g = 0.0
                y_g += kc[g, m] * acc
                y[m] += y_g
        col = (k0 + i + 1) % ring
        c0, c1, wm, m_j0, m_col = _tap_after(k0 + 1 + i, n_meas, f_meas, ring, False, m_j0,
                                             m_col)
        for m in range(m_count):
            y_hist[col, m] = y[m]
            e = 1.0 - (y_hist[c0, m] * (1.0 - wm) + y_hist[c1, m] * wm)
            xi = x_int[m] + half_h * (err[m] + e)
            x_int[m] = xi
            p_y[col, m] = kp[m] * e + ki[m] * xi
            err[m] = e
            out[i, m] = y[m]


def advance_exact(steps, k0, ring, h, kp, *rest):
    """:func:`advance` for whole-step delays ``n_in`` (G,) and ``n_meas`` (ints, in steps)."""
    kernel = _exact_parallel if kp.size >= PARALLEL_FROM else _exact_serial
    kernel(steps, k0, ring, h, kp, *rest)


def _advance_exact(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist, x_int, err,
                   n_in, n_meas, out):  # pragma: no cover - compiled
    """Same as :func:`_advance` with delays of exactly ``n_in[g]`` and ``n_meas`` steps.

    Sample ``j - n`` of a buffer is column ``(j - n) % ring``, or the zero column ``ring``
    before t = 0; for the right end of an interval, position 0 reads the left limit (0) of the
    step at t = 0, as in :meth:`adnmesh.loopmodel.step_response._Simulator._taps`.
    """
    m_count, g_count, n = x.shape
    half_h = 0.5 * h
    for m in numba.prange(m_count):
        xm = x[m].copy()
        tmp = np.empty(n)
        xi = x_int[m]
        e_prev = err[m]
        col = k0 % ring                     # column of sample j = k0 + i
        for i in range(steps):
            j = k0 + i
            nxt = col + 1 if col + 1 < ring else 0
            y = 0.0
            for g in range(g_count):
                u_l, u_r = _exact_inputs(p_y, m, col, j, n_in[g], ring)
                y += _lag_step(phi[g], gl[g], gr[g], kc[m, g], xm[g], tmp, u_l, u_r)
            y_hist[m, nxt] = y
            y_meas = _exact_measured(y_hist, m, nxt, j, n_meas, ring)
            p_y[m, nxt], xi, e_prev = _pi(kp[m], ki[m], half_h, y_meas, xi, e_prev)
            out[m, i] = y
            col = nxt
        x[m] = xm
        x_int[m] = xi
        err[m] = e_prev


_exact_parallel = numba.njit(cache=True, parallel=True)(_advance_exact)
_exact_serial = numba.njit(cache=True, parallel=False)(_advance_exact)


@numba.njit(cache=True)
def advance_exact_first_order_lanes(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist,
                                    x_int, err, n_in, n_meas, out):  # pragma: no cover
    """:func:`advance_exact` for groups of first order (one state each: the state update
    ``x <- phi x + gl u_l + gr u_r`` and output ``kc x`` of :func:`_lag_step` written out)
    with the candidates as the inner loop (lanes): ``kc``, ``x`` (G, M), ``phi``, ``gl``,
    ``gr`` (G,), ``p_y``, ``y_hist`` (ring + 1, M), ``out`` (steps, M), the rest as there.
    Every candidate's arithmetic is the same operations in the same order (bit for bit the
    same results); the ring columns and the t < 0 tests are shared by all candidates, so the
    inner loops run over contiguous rows, in SIMD lanes (1.9-2.3 ns per candidate-step
    against 8.4-8.6 candidate by candidate, 40 and 120 candidates)."""
    g_count, m_count = x.shape
    half_h = 0.5 * h
    col = k0 % ring
    y = np.empty(m_count)
    for i in range(steps):
        j = k0 + i
        nxt = col + 1 if col + 1 < ring else 0
        for m in range(m_count):
            y[m] = 0.0
        for g in range(g_count):
            d = n_in[g]
            c_l = col - d
            if c_l < 0:
                c_l += ring
            c_r = c_l + 1 if c_l + 1 < ring else 0
            # before t = 0 the input is 0 (the right end at t = 0: its left limit, 0): read
            # from the constant-0 column `ring`
            src_l = c_l if j - d >= 0 else ring
            src_r = c_r if j + 1 - d > 0 else ring
            pg, glg, grg = phi[g], gl[g], gr[g]
            for m in range(m_count):
                acc = glg * p_y[src_l, m] + grg * p_y[src_r, m]
                acc += pg * x[g, m]
                x[g, m] = acc
                y_g = 0.0
                y_g += kc[g, m] * acc
                y[m] += y_g
        c_m = nxt - n_meas
        if c_m < 0:
            c_m += ring
        src_m = c_m if j + 1 - n_meas >= 0 else ring
        for m in range(m_count):
            y_hist[nxt, m] = y[m]
            e = 1.0 - y_hist[src_m, m]
            xi = x_int[m] + half_h * (err[m] + e)
            x_int[m] = xi
            p_y[nxt, m] = kp[m] * e + ki[m] * xi
            err[m] = e
            out[i, m] = y[m]
        col = nxt


@numba.njit(cache=True)
def delay_taps(first, steps, n, f, ring, right_end):  # pragma: no cover - compiled
    """Ring columns and weights of a signal delayed by ``n[g] + f[g]`` steps, for the samples
    ``j = first, ..., first + steps - 1``: see :meth:`adnmesh.loopmodel.step_response._Simulator._taps`
    (the same operations, element by element; one call costs ~2 us where the numpy version's
    temporaries cost ~36 us, and a long run calls it three times per block)."""
    g_count = n.size
    c0 = np.empty((steps, g_count), np.int64)
    c1 = np.empty((steps, g_count), np.int64)
    w = np.empty((steps, g_count))
    for i in range(steps):
        for g in range(g_count):
            c0[i, g], c1[i, g], w[i, g] = _tap(first + i, n[g], f[g], ring, right_end)
    return c0, c1, w


@numba.njit(cache=True, inline="always")
def _tap(j, n, f, ring, right_end):  # pragma: no cover - compiled
    """Ring columns and weight of sample j of a signal delayed by ``n + f`` steps (one
    element of :func:`delay_taps`)."""
    c0, c1, w, _, _ = _tap_after(j, n, f, ring, right_end, _NO_TAP, 0)
    return c0, c1, w


@numba.njit(cache=True, inline="always")
def _tap_after(j, n, f, ring, right_end, j0_before, col_before):  # pragma: no cover
    """:func:`_tap`, given the tap of sample j - 1 (its ``floor`` position ``j0_before`` and
    ``j0_before % ring``): the columns then follow by one step without a division (the
    same values). Returns (c0, c1, w, j0, j0 % ring)."""
    pos = float(j - n) - f
    j0 = int(np.floor(pos + 1e-9))
    zero = pos < -1e-9
    if right_end:
        zero = zero or abs(pos) < 1e-9
    if j0 == j0_before + 1:
        col = col_before + 1 if col_before + 1 < ring else 0
    else:
        col = j0 % ring
    c1 = col + 1 if col + 1 < ring else 0
    c0 = ring if (zero or j0 < 0) else col
    return c0, ring if zero else c1, 0.0 if zero else pos - j0, j0, col


@numba.njit(cache=True)
def _time_at(i, frac, t0, h, times):  # pragma: no cover - compiled
    """Time of the position ``i + frac`` between samples i and i + 1 (0 = ``last``).

    Uniform block (``times`` empty): ``t0 + h (i + frac)``. Sampled times: linear between
    ``times[i]`` and ``times[i + 1]``. The two agree (to rounding) on a uniform grid.
    ``frac == 0`` is the time of sample i itself: it never reads ``times[i + 1]``, which does not
    exist for the last sample (numba does not check bounds; a read past the end gave a peak at
    the last sample a time of NaN or garbage).
    """
    if times.size == 0:
        return t0 + h * (i + frac)
    if frac == 0.0:
        return times[i]
    return times[i] + (times[i + 1] - times[i]) * frac


@numba.njit(cache=True)
def _vertex(ym, yc, yp, j, t0, h, times):  # pragma: no cover - compiled
    """Peak value and time of the parabola through samples j - 1, j, j + 1 if it is concave,
    else sample j itself.

    Uniform block: offset ``0.5 (ym - yp) / (ym - 2 yc + yp)`` steps, peak
    ``yc - 0.25 (ym - yp) offset``. Sampled times: the same parabola written for spacings
    ``d1 = t_j - t_(j-1)``, ``d2 = t_(j+1) - t_j`` (slopes ``s1``, ``s2``, curvature
    ``a = (s2 - s1) / (d1 + d2)``, slope at ``t_j`` ``b = s1 + a d1``; vertex at
    ``t_j - b / (2a)``, value ``yc - b^2 / (4a)``), which is the uniform formula when d1 = d2.
    """
    if times.size == 0:
        den = ym - 2.0 * yc + yp
        off = 0.0
        if den < 0.0:
            off = 0.5 * (ym - yp) / den
        return yc - 0.25 * (ym - yp) * off, t0 + h * (j + off)
    d1 = times[j] - times[j - 1]
    d2 = times[j + 1] - times[j]
    s1 = (yc - ym) / d1
    a = ((yp - yc) / d2 - s1) / (d1 + d2)
    if not a < 0.0:
        return yc, times[j]
    b = s1 + a * d1
    return yc - b * b / (4.0 * a), times[j] - b / (2.0 * a)


def _accumulate(t0, h, times, chunk, last, t10, t90, peak, peak_t, bands, settle, curvature):
    """Step figures of one block of samples per candidate, updated in place: THE rule of
    :mod:`adnmesh.loopmodel.step_figures` (every step figure in adnmesh comes from here).

    ``chunk`` (M, n), n >= 1, holds y after ``last`` (M,). Sample positions: 0 is ``last``,
    k + 1 is ``chunk[:, k]``. Their times: ``t0 + h * position`` when ``times`` is empty (the
    uniform grid of the simulation), else ``times`` (n + 1,), shared by all rows, increasing.
    Per row: first crossings of 10 % and 90 % from below, linearly interpolated (none if the
    row is already at or above the level at position 0); the block's largest sample if higher
    than ``peak`` (the first of equal ones), refined by the parabola through it and its
    neighbours when both are in the block and it is concave; for each band the last exit
    (interpolated) from ``|y - 1| <= band``, ``inf`` if the block ends outside, unchanged if the
    block is inside throughout. ``curvature[m]`` receives the block's largest
    ``|y[k] - 2 y[k-1] + y[k-2]|``. Only the conversion of positions to times depends on
    ``times`` (:func:`_time_at`, :func:`_vertex`).
    """  # pragma: no cover - compiled
    m_count, n = chunk.shape
    for m in numba.prange(m_count):
        prev = last[m]
        for store, level in ((t10, 0.1), (t90, 0.9)):
            if not np.isnan(store[m]):
                continue
            if prev >= level:
                continue                    # first sample already above: no crossing here
            for k in range(n):
                if chunk[m, k] >= level:
                    y0 = prev if k == 0 else chunk[m, k - 1]
                    store[m] = _time_at(k, (level - y0) / (chunk[m, k] - y0), t0, h, times)
                    break
        # peak of the block (sample 0 = prev)
        j = 0
        yc = prev
        for k in range(n):
            if chunk[m, k] > yc:
                yc = chunk[m, k]
                j = k + 1
        if yc > peak[m]:
            if 0 < j < n:
                ym = prev if j == 1 else chunk[m, j - 2]
                peak[m], peak_t[m] = _vertex(ym, yc, chunk[m, j], j, t0, h, times)
            else:
                peak[m], peak_t[m] = yc, _time_at(j, 0.0, t0, h, times)
        for b in range(bands.size):
            band = bands[b]
            # last sample (0 = prev, k + 1 = chunk[k]) outside the band
            last_out = -1
            for k in range(n - 1, -1, -1):
                if abs(chunk[m, k] - 1.0) > band:
                    last_out = k + 1
                    break
            if last_out < 0 and abs(prev - 1.0) > band:
                last_out = 0
            if last_out < 0:
                continue
            if last_out == n:
                settle[b, m] = np.inf
                continue
            y0 = prev if last_out == 0 else chunk[m, last_out - 1]
            y1 = chunk[m, last_out]
            target = 1.0 + band if y0 > 1.0 else 1.0 - band
            settle[b, m] = _time_at(last_out, (target - y0) / (y1 - y0), t0, h, times)
        c = 0.0
        for k in range(2, n):
            d = abs(chunk[m, k] - 2.0 * chunk[m, k - 1] + chunk[m, k - 2])
            if d > c:
                c = d
        curvature[m] = c
        last[m] = chunk[m, n - 1]


accumulate = numba.njit(cache=True, parallel=False)(_accumulate)


@numba.njit(cache=True)
def accumulate_lanes(t0, h, times, chunk, last, t10, t90, peak, peak_t, bands, settle,
                     curvature):  # pragma: no cover - compiled
    """:func:`accumulate` for a block stored sample by sample, ``chunk`` (n, M) (the output of
    a lanes simulation): the same rule and the same arithmetic, so the same figures bit for
    bit (``tests/test_stepfigures.py``); the peak, band and curvature scans run with the
    candidates as the inner loop, over contiguous rows."""
    n, m_count = chunk.shape
    # first crossings of 10 % and 90 % (most candidates have them already: a short scan)
    for store, level in ((t10, 0.1), (t90, 0.9)):
        for m in range(m_count):
            if not np.isnan(store[m]) or last[m] >= level:
                continue
            for k in range(n):
                if chunk[k, m] >= level:
                    y0 = last[m] if k == 0 else chunk[k - 1, m]
                    store[m] = _time_at(k, (level - y0) / (chunk[k, m] - y0), t0, h, times)
                    break
    # the block's largest sample (the first of equal ones; position 0 is `last`)
    y_top = last.copy()
    j_top = np.zeros(m_count, np.int64)
    for k in range(n):
        for m in range(m_count):
            if chunk[k, m] > y_top[m]:
                y_top[m] = chunk[k, m]
                j_top[m] = k + 1
    for m in range(m_count):
        j, yc = j_top[m], y_top[m]
        if yc > peak[m]:
            if 0 < j < n:
                ym = last[m] if j == 1 else chunk[j - 2, m]
                peak[m], peak_t[m] = _vertex(ym, yc, chunk[j, m], j, t0, h, times)
            else:
                peak[m], peak_t[m] = yc, _time_at(j, 0.0, t0, h, times)
    # per band the last sample outside it, scanning back until every candidate has one
    for b in range(bands.size):
        band = bands[b]
        last_out = np.full(m_count, -1, np.int64)
        open_count = m_count
        for k in range(n - 1, -1, -1):
            for m in range(m_count):
                if last_out[m] < 0 and abs(chunk[k, m] - 1.0) > band:
                    last_out[m] = k + 1
                    open_count -= 1
            if open_count == 0:
                break
        for m in range(m_count):
            lo = last_out[m]
            if lo < 0 and abs(last[m] - 1.0) > band:
                lo = 0
            if lo < 0:
                continue
            if lo == n:
                settle[b, m] = np.inf
                continue
            y0 = last[m] if lo == 0 else chunk[lo - 1, m]
            y1 = chunk[lo, m]
            target = 1.0 + band if y0 > 1.0 else 1.0 - band
            settle[b, m] = _time_at(lo, (target - y0) / (y1 - y0), t0, h, times)
    for m in range(m_count):
        curvature[m] = 0.0
    for k in range(2, n):
        for m in range(m_count):
            d = abs(chunk[k, m] - 2.0 * chunk[k - 1, m] + chunk[k - 2, m])
            if d > curvature[m]:
                curvature[m] = d
    for m in range(m_count):
        last[m] = chunk[n - 1, m]
