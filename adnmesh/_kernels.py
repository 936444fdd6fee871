"""Compiled inner loop of the step-response simulation (numba).

:func:`advance` runs the method of steps of :mod:`adnmesh.stepresp` for M candidates over a
block of samples, with delays read from precomputed (interpolating) taps; :func:`advance_exact`
is the same arithmetic for the common case of delays that are whole multiples of the step, with
the buffer columns computed in the loop (no taps, no interpolation). They are the only hot loops
of the numerics: everything else is vectorised numpy. Candidates are independent, so the outer
loop runs in parallel threads for large batches.
"""
from __future__ import annotations

import numba
import numpy as np

__all__ = ["advance", "advance_exact"]

#: below this many candidates the serial kernel wins (no thread start-up)
PARALLEL_FROM = 64


def advance(steps, k0, ring, h, kp, *rest):
    """Dispatch to the parallel kernel for large batches, the serial one otherwise."""
    kernel = _advance_parallel if kp.size >= PARALLEL_FROM else _advance_serial
    kernel(steps, k0, ring, h, kp, *rest)


def _advance(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist, x_int, err,
            l0, l1, lw, r0, r1, rw, m0, m1, mw, out):  # pragma: no cover - compiled
    """Advance every candidate ``steps`` samples; writes ``out[m, i]`` = y at sample k0+i+1.

    Shapes: kc (M, G, n), phi (G, n, n), gl/gr (G, n), x (M, G, n), p_y/y_hist (M, ring+1),
    x_int/err (M,), taps l0.. (steps, G) and m0.. (steps,); state arrays are updated in place.
    """
    m_count, g_count, n = x.shape
    half_h = 0.5 * h
    for m in numba.prange(m_count):  # noqa: PLR1702
        xm = x[m].copy()
        tmp = np.empty(n)
        xi = x_int[m]
        e_prev = err[m]
        for i in range(steps):
            y = 0.0
            for g in range(g_count):
                u_l = p_y[m, l0[i, g]] * (1.0 - lw[i, g]) + p_y[m, l1[i, g]] * lw[i, g]
                u_r = p_y[m, r0[i, g]] * (1.0 - rw[i, g]) + p_y[m, r1[i, g]] * rw[i, g]
                for a in range(n):
                    acc = gl[g, a] * u_l + gr[g, a] * u_r
                    for b in range(n):
                        acc += phi[g, a, b] * xm[g, b]
                    tmp[a] = acc
                for a in range(n):
                    xm[g, a] = tmp[a]
                    y += kc[m, g, a] * tmp[a]
            col = (k0 + i + 1) % ring
            y_hist[m, col] = y
            y_meas = y_hist[m, m0[i]] * (1.0 - mw[i]) + y_hist[m, m1[i]] * mw[i]
            e = 1.0 - y_meas
            xi += half_h * (e_prev + e)
            e_prev = e
            p_y[m, col] = kp[m] * e + ki[m] * xi
            out[m, i] = y
        x[m] = xm
        x_int[m] = xi
        err[m] = e_prev


_advance_parallel = numba.njit(cache=True, parallel=True)(_advance)
_advance_serial = numba.njit(cache=True, parallel=False)(_advance)


def advance_exact(steps, k0, ring, h, kp, *rest):
    """:func:`advance` for whole-step delays ``n_in`` (G,) and ``n_meas`` (ints, in steps)."""
    kernel = _exact_parallel if kp.size >= PARALLEL_FROM else _exact_serial
    kernel(steps, k0, ring, h, kp, *rest)


def _advance_exact(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, p_y, y_hist, x_int, err,
                   n_in, n_meas, out):  # pragma: no cover - compiled
    """Same as :func:`_advance` with delays of exactly ``n_in[g]`` and ``n_meas`` steps.

    Sample ``j - n`` of a buffer is column ``(j - n) % ring``, or the zero column ``ring``
    before t = 0; for the right end of an interval, position 0 reads the left limit (0) of the
    step at t = 0, as in :meth:`adnmesh.stepresp._Simulator._taps`.
    """
    m_count, g_count, n = x.shape
    half_h = 0.5 * h
    for m in numba.prange(m_count):  # noqa: PLR1702
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
                d = n_in[g]
                c_l = col - d
                if c_l < 0:
                    c_l += ring
                c_r = c_l + 1 if c_l + 1 < ring else 0
                u_l = p_y[m, c_l] if j - d >= 0 else 0.0
                u_r = p_y[m, c_r] if j + 1 - d > 0 else 0.0
                for a in range(n):
                    acc = gl[g, a] * u_l + gr[g, a] * u_r
                    for b in range(n):
                        acc += phi[g, a, b] * xm[g, b]
                    tmp[a] = acc
                for a in range(n):
                    xm[g, a] = tmp[a]
                    y += kc[m, g, a] * tmp[a]
            y_hist[m, nxt] = y
            c_m = nxt - n_meas
            if c_m < 0:
                c_m += ring
            y_meas = y_hist[m, c_m] if j + 1 - n_meas >= 0 else 0.0
            e = 1.0 - y_meas
            xi += half_h * (e_prev + e)
            e_prev = e
            p_y[m, nxt] = kp[m] * e + ki[m] * xi
            out[m, i] = y
            col = nxt
        x[m] = xm
        x_int[m] = xi
        err[m] = e_prev


_exact_parallel = numba.njit(cache=True, parallel=True)(_advance_exact)
_exact_serial = numba.njit(cache=True, parallel=False)(_advance_exact)
