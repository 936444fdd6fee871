"""Compiled inner loop of the step-response simulation (numba).

One function, :func:`advance`, runs the method of steps of :mod:`adnmesh.stepresp` for M
candidates over a block of samples. It is the only hot loop of the numerics: everything else is
vectorised numpy. Candidates are independent, so the outer loop runs in parallel threads; the
arithmetic is exactly the one documented in :mod:`adnmesh.stepresp`.
"""
from __future__ import annotations

import numba
import numpy as np

__all__ = ["advance"]

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
