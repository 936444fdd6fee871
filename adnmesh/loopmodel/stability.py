"""Certified closed-loop stability of the delayed PI loop by a Nyquist winding argument.

The argument
------------
``L(s) = C(s) exp(-s T_com) G_A(s) exp(-s T_meas)`` with ``C = K_P + K_I/s`` has one open-loop
pole at ``s = 0`` and otherwise only stable poles (``-1/tau_i``); ``|L(s)| -> 0`` as
``|s| -> inf`` in the closed right half-plane (strictly proper actuators), so the
characteristic function ``F = 1 + L`` is of retarded type and the Nyquist criterion holds:
the number of closed-loop poles in the open right half-plane is ``Z = -N`` where N is the net
number of counter-clockwise turns of ``F`` around 0 along the D-contour (indented to the right
of ``s = 0``). By conjugate symmetry and because the indentation turns ``arg F`` by ``-pi``,

    Z = 1/2 - W/pi,      W = change of arg F(j omega) for omega from 0+ to +inf.

W is computed exactly, not approximately, from samples, because every piece is certified:

1. ``(0, omega_lo]``: writing ``L = -j (K_I K / omega) h(omega)`` with ``h(0) = 1``, an explicit
   bound ``|h - 1| <= 1/2`` (polynomial in omega, see ``_low_frequency_limit``) gives
   ``Im F < 0`` there, so arg F moves inside ``(-pi, 0)`` from ``-pi/2`` to ``arg F(omega_lo)``.
2. ``[omega_hi, inf)``: an envelope ``|L| < 1`` holds, so ``Re F > 0`` and arg F moves inside
   ``(-pi/2, pi/2)`` to 0.
3. On each grid interval ``[a, b]`` a Lipschitz bound ``|dL/domega| <= Lip`` (from bounds on
   ``|C|, |C'|, |H_g|, |H_g'|`` and the delays) with ``(b - a) Lip < |F(a)|`` keeps ``F`` inside a
   disk around ``F(a)`` that excludes 0: the arg changes by less than ``pi/2`` and the wrapped
   difference of the two samples is the true change. Intervals that fail the test are bisected
   (up to ``2**16`` pieces).

In :func:`adnmesh.loopmodel.evaluation.evaluate` (every constraint check and figure) the samples, the
Lipschitz test and the winding come from one compiled pass per candidate
(:func:`adnmesh.loopmodel.frequency_kernels.grid_pass`, then :func:`winding_verdict`): the wrapped arg
changes of the intervals that pass telescope to ``arg F`` at the grid's ends plus ``2 pi`` per
crossing of the negative real axis, so no angle is taken in the loop.
:func:`nyquist_stability` is the same argument on numpy arrays, the reference the tests hold
the pass to (``tests/test_freq_kernels.py``: the same verdicts).

Failure modes: a loop with a closed-loop pole on or extremely close to the imaginary axis
makes ``|F|`` vanish and the refinement cannot certify it; such candidates are reported with
``certified = False`` and treated as unstable. Negative gains or actuators with complex
denominator roots are outside the argument and rejected.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.frequency_kernels import first_above, last_at_least
from adnmesh.loopmodel.frequency_response import as_candidates, log_grid, loop_at, loop_response
from adnmesh.loopmodel.plant import Plant

__all__ = ["NyquistData", "nyquist_stability", "certified_grid", "certified_omega",
           "interval_bounds", "winding_verdict"]

_PER_DECADE = 100
_MAX_REFINE_EXP = 16
#: grids of the low- and high-frequency certificates, rad/s
_LOW_GRID = np.geomspace(1e-12, 1e3, 15 * 20 + 1)
_HIGH_GRID = np.geomspace(1e-4, 1e7, 11 * 20 + 1)


@dataclass(frozen=True)
class NyquistData:
    """Frequency response on the certified grid and the stability verdict.

    Attributes
    ----------
    omega : ndarray, shape (N,)
        Common grid, rad/s.
    loop : ndarray, complex, shape (M, N)
        ``L(j omega)``.
    stable : ndarray of bool, shape (M,)
        Closed loop stable (and certified).
    unstable_poles : ndarray of int, shape (M,)
        Number of closed-loop poles in the open right half-plane (-1 where uncertified).
    certified : ndarray of bool, shape (M,)
        False where the winding could not be certified (near-marginal loops).
    """

    omega: np.ndarray
    loop: np.ndarray
    stable: np.ndarray
    unstable_poles: np.ndarray
    certified: np.ndarray


def _poly_abs(coeffs: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """``sum_i |c_i| omega^i`` — an upper bound of ``|c(j omega)|``, nondecreasing in omega."""
    return np.polynomial.polynomial.polyval(omega, np.abs(coeffs))


def _group_bounds(plant: Plant, lo: np.ndarray, hi: np.ndarray):
    """Bounds on ``[lo, hi]`` per group: ``|H| <= rho``, ``|dH/domega| <= drho``; shape (G, N)."""
    return _group_bounds_of(plant.actuators, lo, hi)


def _group_bounds_of(actuators, lo: np.ndarray, hi: np.ndarray):
    """:func:`_group_bounds` of the groups ``actuators``."""
    rho, drho = [], []
    for act in actuators:
        taus = act.time_constants_s
        den_lo = np.prod(np.sqrt(1.0 + np.outer(lo, taus) ** 2), axis=1)
        num_hi = _poly_abs(act.numerator, hi)
        dnum_hi = _poly_abs(np.polynomial.polynomial.polyder(act.numerator), hi) \
            if act.numerator.size > 1 else np.zeros_like(hi)
        tau_sum = np.sum(taus / np.sqrt(1.0 + np.outer(lo, taus) ** 2), axis=1)
        rho.append(num_hi / den_lo)
        drho.append((dnum_hi + num_hi * tau_sum) / den_lo)
    return np.array(rho), np.array(drho)


@functools.lru_cache(maxsize=256)
def _low_frequency_terms(actuators: tuple, theta: tuple):
    """``rho`` and ``beta + rho omega theta`` of :func:`_low_frequency_limit` on its grid per
    group, shape (G, K) each (they depend on the dynamics and delays only; never written)."""
    rho, beta = [], []
    for act in actuators:
        n = np.zeros(max(act.numerator.size, act.denominator.size))
        d = np.zeros_like(n)
        n[: act.numerator.size] = act.numerator
        d[: act.denominator.size] = act.denominator
        rho.append(_poly_abs(act.numerator, _LOW_GRID))
        beta.append(_poly_abs(np.concatenate([[0.0], (n - d)[1:]]), _LOW_GRID))
    rho, beta = np.array(rho), np.array(beta)                          # (G, K)
    return rho, np.ascontiguousarray(beta + rho * _LOW_GRID * np.array(theta)[:, None])


def _low_frequency_limit(plant: Plant, kp, ki, gains) -> np.ndarray:
    """Largest grid frequency (rad/s) below which ``Im(1 + L) < 0`` is guaranteed, shape (M,).

    ``h = (1 + j omega K_P/K_I) sum_g f_g H_g exp(-j omega theta_g)`` with ``f_g = K_g / sum K``;
    ``|h - 1| <= omega a sum f rho + sum f (beta + rho omega theta)`` where ``rho = sum|n_i| w^i``
    bounds ``|H|`` (``|den| >= 1``) and ``beta = sum_{i>=1} |n_i - d_i| w^i`` bounds ``|H - 1|``.
    The bound is nondecreasing, so the last grid point where it is <= 1/2 is safe (found by
    a compiled scan that stops at the first point where it is not,
    :func:`adnmesh.loopmodel.frequency_kernels.first_above`).
    """
    frac = np.ascontiguousarray(gains / gains.sum(axis=1, keepdims=True))
    rho, beta_term = _low_frequency_terms(plant.actuators, tuple(plant.loop_delays_s.tolist()))
    idx = first_above(np.ascontiguousarray(kp / ki, dtype=float), frac, rho, beta_term,
                      _LOW_GRID, 0.5) - 1
    if np.any(idx < 0):
        raise ValueError("low-frequency certificate failed: gains out of range")
    return _LOW_GRID[idx]


@functools.lru_cache(maxsize=256)
def _high_frequency_bounds(actuators: tuple) -> np.ndarray:
    """``|H_g| <= rho`` on the intervals of :func:`_high_frequency_limit`'s grid, shape
    (G, K - 1) (the dynamics only; never written)."""
    return np.ascontiguousarray(_group_bounds_of(actuators, _HIGH_GRID[:-1], _HIGH_GRID[1:])[0])


@functools.lru_cache(maxsize=256)
def _high_frequency_monotone(actuators: tuple) -> bool:
    """Every row of :func:`_high_frequency_bounds` is nonincreasing (as computed)."""
    return bool(np.all(np.diff(_high_frequency_bounds(actuators), axis=1) <= 0.0))


def _high_frequency_limit(plant: Plant, kp, ki, gains, level: float = 1.0) -> np.ndarray:
    """Frequency (rad/s) above which ``|L| < level`` is guaranteed, shape (M,).

    On ``[w_j, w_j+1]``: ``|L| <= (K_P + K_I/w_j) sum_g K_g num(w_j+1)/|den(j w_j)|``. Past the
    last grid point (1e7 rad/s) the envelope decreases because every actuator is strictly proper.
    """
    lo, hi = _HIGH_GRID[:-1], _HIGH_GRID[1:]
    last = last_at_least(np.ascontiguousarray(kp, dtype=float),
                         np.ascontiguousarray(ki, dtype=float),
                         np.ascontiguousarray(gains, dtype=float),
                         _high_frequency_bounds(plant.actuators), lo, level,
                         _high_frequency_monotone(plant.actuators))
    return np.where(last >= 0, hi[np.maximum(last, 0)], lo[0])


def _lipschitz(plant: Plant, kp, ki, gains, lo, hi) -> np.ndarray:
    """Bound of ``|dL/domega|`` on each interval ``[lo, hi]``.

    ``lo, hi`` of shape (K,) are shared by all candidates, of shape (M, K) per candidate;
    the result has shape (M, K).
    """
    rho, drho = _group_bounds(plant, np.ravel(lo), np.ravel(hi))
    theta = plant.loop_delays_s[:, None]
    if np.ndim(lo) == 1:
        s1, s2 = gains @ rho, gains @ (drho + theta * rho)
    else:
        shape = (len(plant.actuators),) + np.shape(lo)
        s1 = np.einsum("mg,gmk->mk", gains, rho.reshape(shape))
        s2 = np.einsum("mg,gmk->mk", gains, (drho + theta * rho).reshape(shape))
    lo = np.atleast_2d(lo)
    return ki[:, None] / lo**2 * s1 + (kp[:, None] + ki[:, None] / lo) * s2


def _refine(plant, kp, ki, gains, lo, hi):
    """Certified arg change of F on intervals that failed the coarse test.

    Returns (dtheta, ok) per interval, ``ok`` False when 2**16 pieces were not enough.
    """
    dtheta = np.zeros(lo.size)
    ok = np.zeros(lo.size, dtype=bool)
    pending = np.arange(lo.size)
    for exp in range(2, _MAX_REFINE_EXP + 1, 2):
        if pending.size == 0:
            break
        n = 2**exp
        frac = np.linspace(0.0, 1.0, n + 1)
        pts = lo[pending, None] + (hi[pending] - lo[pending])[:, None] * frac     # (P, n+1)
        sub = plant.with_gains(gains[pending])
        f = 1.0 + loop_at(sub, kp[pending], ki[pending], pts)
        a, b = pts[:, :-1], pts[:, 1:]
        lip = _lipschitz(plant, kp[pending], ki[pending], gains[pending], a, b)
        good = np.all((b - a) * lip < 0.999 * np.abs(f[:, :-1]), axis=1)
        done = pending[good]
        dtheta[done] = np.angle(f[good, 1:] / f[good, :-1]).sum(axis=1)
        ok[done] = True
        pending = pending[~good]
    return dtheta, ok


def certified_grid(plant: Plant, kp, ki, per_decade: int = _PER_DECADE):
    """The common frequency grid of :func:`nyquist_stability` and ``L(j omega)`` on it.

    Returns (omega rad/s, shape (N,); loop, complex, shape (M, N)). The grid reaches from
    below the low-frequency limit of the proof to ``|L| <= 0.01`` for every candidate.
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    omega = certified_omega(plant, kp, ki, per_decade)
    pl = plant.with_gains(gains)
    return omega, loop_response(pl, kp, ki, omega)


def certified_omega(plant: Plant, kp, ki, per_decade: int = _PER_DECADE) -> np.ndarray:
    """The frequencies of :func:`certified_grid` alone, rad/s, shape (N,)."""
    kp, ki, gains = as_candidates(plant, kp, ki)
    # The proof needs (0, w_lo] with Im F < 0 and [w_hi, inf) with |L| < 1. The grid reaches
    # further, to |L| >= 100 and |L| <= 0.01, so that margins found on it miss nothing that
    # matters: there 2|S - 1/2| = |1 - L|/|1 + L| is within 2 % of its limit 1.
    total = gains.sum(axis=1)
    w_lo = np.minimum(_low_frequency_limit(plant, kp, ki, gains), ki * total * 0.5 / 100.0)
    w_hi = _high_frequency_limit(plant, kp, ki, gains, level=0.01)
    return log_grid(float(w_lo.min()), max(float(w_hi.max()), 10.0 * float(w_lo.min())),
                    per_decade)


def interval_bounds(plant: Plant, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group and grid interval, ``|H_g| <= rho`` and ``|dH_g/domega| + theta_g |H_g| <=
    drho`` (theta_g the group's loop delay): what the Lipschitz bound of ``L`` on each
    interval of ``omega`` needs besides the gains (:func:`_lipschitz`); shape (G, N - 1)."""
    rho, drho = _group_bounds(plant, omega[:-1], omega[1:])
    theta = plant.loop_delays_s[:, None]
    return np.ascontiguousarray(rho), np.ascontiguousarray(drho + theta * rho)


def winding_verdict(plant: Plant, kp, ki, gains, omega, winding, bad):
    """Stability from :func:`adnmesh.loopmodel.frequency_kernels.grid_pass`: the arg change of ``F`` over
    the intervals that passed the Lipschitz test (``winding``, (M,)) plus that of the failed
    ones (``bad``, (M, N - 1)), certified by bisection (:func:`_refine`) as in
    :func:`nyquist_stability`; returns (stable, unstable poles, certified), each (M,)."""
    winding = np.array(winding, dtype=float)
    cert = np.ones(winding.size, dtype=bool)
    bad_m, bad_k = np.nonzero(bad)
    if bad_m.size:
        d, ok = _refine(plant, kp[bad_m], ki[bad_m], gains[bad_m], omega[bad_k],
                        omega[bad_k + 1])
        np.add.at(winding, bad_m, d)
        cert[bad_m[~ok]] = False
    z = 0.5 - winding / np.pi
    zi = np.rint(z)
    cert &= np.abs(z - zi) < 1e-6
    unstable = np.where(cert, zi, -1).astype(int)
    return cert & (unstable == 0), unstable, cert


def nyquist_stability(plant: Plant, kp, ki, per_decade: int = _PER_DECADE, grid=None,
                      only=None) -> NyquistData:
    """Decide closed-loop stability of M candidate PI pairs with exact delays.

    Parameters
    ----------
    plant : Plant
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s), > 0.
    per_decade : int
        Grid density, points per decade (more only costs time; correctness is certified).
    grid : (omega, loop), optional
        :func:`certified_grid` of the same candidates, if already computed.
    only : array_like of bool, shape (M,), optional
        Certify only these candidates; the others are reported not certified (and not
        stable, ``unstable_poles`` -1) without any work.

    Returns
    -------
    NyquistData
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    omega, loop = certified_grid(plant, kp, ki, per_decade) if grid is None else grid
    certified = np.zeros(kp.size, dtype=bool)
    unstable = np.full(kp.size, -1)
    rows = np.arange(kp.size) if only is None else np.nonzero(np.asarray(only, bool))[0]
    if rows.size:
        kp_r, ki_r, gains_r = kp[rows], ki[rows], gains[rows]
        pl = plant.with_gains(gains_r)
        f = 1.0 + loop[rows]
        lip = _lipschitz(plant, kp_r, ki_r, gains_r, omega[:-1], omega[1:])
        good = np.diff(omega)[None, :] * lip < 0.999 * np.abs(f[:, :-1])
        dtheta = np.angle(f[:, 1:] / f[:, :-1])
        cert = np.ones(rows.size, dtype=bool)
        bad_m, bad_k = np.nonzero(~good)
        if bad_m.size:
            d, ok = _refine(pl, kp_r[bad_m], ki_r[bad_m], gains_r[bad_m], omega[bad_k],
                            omega[bad_k + 1])
            dtheta[bad_m, bad_k] = d
            cert[bad_m[~ok]] = False
        winding = (np.angle(f[:, 0]) + np.pi / 2) + dtheta.sum(axis=1) - np.angle(f[:, -1])
        z = 0.5 - winding / np.pi
        zi = np.rint(z)
        cert &= np.abs(z - zi) < 1e-6
        certified[rows] = cert
        unstable[rows] = np.where(cert, zi, -1).astype(int)
    return NyquistData(omega, loop, certified & (unstable == 0), unstable, certified)
