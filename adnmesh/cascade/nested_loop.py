"""Stability and disk margin of the upper loop over the ADNs' exact closed loops.

Stability of the cascade needs both layers:

1. every lower loop stable: each ADN's ``1 + L_i`` by the certified winding argument of
   :mod:`adnmesh.loopmodel.stability`, so every ``T_i`` has its poles in the open left
   half-plane;
2. the upper loop: ``L_up = C_up exp(-s T_meas) sum_i K_i exp(-s T_com,i) T_i`` then has one
   open-loop pole at ``s = 0`` (the upper integrator) and ``|L_up| -> 0`` as ``|s| -> inf``
   (each ``T_i`` falls like ``1/omega``), so the Nyquist criterion of the reference loop holds:
   ``Z = 1/2 - W/pi`` closed-loop poles in the right half-plane, W the change of
   ``arg(1 + L_up)`` from ``omega = 0+`` to infinity.

W is taken from samples of the exact response on a log grid, refined until no interval turns
``arg(1 + L_up)`` by more than pi/8 (at most :data:`MAX_REFINE` rounds); below the grid
``Im(1 + L_up) < 0`` (the integrator dominates: checked at the first sample) and above it
``|L_up| < 1/2`` (checked at the last). Unlike the lower loops' this verdict has no
Lipschitz certificate (``T_i`` has no closed-form bounds); the tests hold it to the closed-loop
poles of a python-control model with Padé approximants.

The disk margin (balanced) is ``1 / max |S - 1/2|`` with ``S = 1 / (1 + L_up)``: the grid's
three largest local maxima, each refined by a bounded scalar search in ``log omega`` between
its neighbours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.stability import nyquist_stability

__all__ = ["UpperLoop", "upper_loop", "lower_stable", "MAX_REFINE"]

#: refinement rounds of the winding grid
MAX_REFINE = 24
_PER_DECADE = 200
_TURN = math.pi / 8


@dataclass(frozen=True)
class UpperLoop:
    """Frequency-domain verdict of the cascade under one upper PI pair.

    Attributes
    ----------
    lower_stable : bool
        Every ADN's own loop is stable (certified).
    stable : bool
        The whole cascade is stable (lower loops and upper loop).
    unstable_poles : int
        Closed-loop poles of the upper loop in the right half-plane (winding count).
    resolved : bool
        The winding grid met its refinement rule (otherwise ``stable`` is False).
    disk_margin : float
        Balanced disk margin alpha of the upper loop, 0 if unstable.
    disk_omega : float
        Its critical frequency, rad/s.
    """

    lower_stable: bool
    stable: bool
    unstable_poles: int
    resolved: bool
    disk_margin: float
    disk_omega: float


def lower_stable(cascade: Cascade) -> bool:
    """Every ADN's own loop stable, by the certified winding argument."""
    for adn in cascade.adns:
        nyq = nyquist_stability(adn.plant, adn.kp, adn.ki)
        if not (bool(nyq.stable[0]) and bool(nyq.certified[0])):
            return False
    return True


def _grid(cascade: Cascade, kp: float, ki: float):
    """Log grid with ``Im F < 0`` at its first sample and ``|L_up| < 1/2`` at its last."""
    lo, hi = 1e-6, 1e3
    for _ in range(12):
        if cascade.open_loop(kp, ki, np.array([lo]))[0].imag < -2.0:
            break
        lo /= 100
    for _ in range(12):
        tail = np.geomspace(hi, hi * 100, 41)
        if np.abs(cascade.open_loop(kp, ki, tail)).max() < 0.5:
            break
        hi *= 100
    n = int(math.ceil(math.log10(hi / lo) * _PER_DECADE)) + 1
    return np.geomspace(lo, hi, n)


def _winding(cascade: Cascade, kp: float, ki: float):
    """``(W, omega, F, resolved)`` of ``F = 1 + L_up`` on the refined grid."""
    omega = _grid(cascade, kp, ki)
    f = 1.0 + cascade.open_loop(kp, ki, omega)
    resolved = False
    for _ in range(MAX_REFINE):
        turn = np.abs(np.angle(f[1:] / f[:-1]))
        wide = np.nonzero(turn > _TURN)[0]
        if wide.size == 0:
            resolved = True
            break
        mid = np.sqrt(omega[wide] * omega[wide + 1])
        omega = np.insert(omega, wide + 1, mid)
        f = np.insert(f, wide + 1, 1.0 + cascade.open_loop(kp, ki, mid))
    ok = resolved and f[0].imag < 0 and np.abs(f[-1] - 1.0) < 0.5
    steps = np.angle(f[1:] / f[:-1])
    change = (np.angle(f[0]) + math.pi / 2) + steps.sum() + (0.0 - np.angle(f[-1]))
    return change, omega, f, bool(ok)


def _disk(cascade: Cascade, kp: float, ki: float, omega: np.ndarray, f: np.ndarray):
    """``(alpha, omega_c)``: the largest ``|S - 1/2|`` refined around the grid's top peaks."""
    dist = np.abs(1.0 / f - 0.5)
    inner = np.nonzero((dist[1:-1] >= dist[:-2]) & (dist[1:-1] >= dist[2:]))[0] + 1
    local = np.concatenate(([0], inner, [dist.size - 1]))
    peaks = local[np.argsort(dist[local])[::-1][:3]]
    best, at = float(dist.max()), float(omega[int(np.argmax(dist))])

    def neg(logw: float) -> float:
        w = np.array([math.exp(logw)])
        return -float(np.abs(1.0 / (1.0 + cascade.open_loop(kp, ki, w))[0] - 0.5))

    for i in peaks:
        a, b = omega[max(i - 1, 0)], omega[min(i + 1, omega.size - 1)]
        res = scipy.optimize.minimize_scalar(neg, bounds=(math.log(a), math.log(b)),
                                             method="bounded", options={"xatol": 1e-10})
        if -res.fun > best:
            best, at = -float(res.fun), math.exp(float(res.x))
    return 1.0 / best, at


def upper_loop(cascade: Cascade, kp: float, ki: float) -> UpperLoop:
    """Stability and disk margin of the cascade under the upper PI ``(kp, ki)``
    (1/W and 1/(W s), > 0)."""
    if not (kp > 0 and ki > 0):
        raise ValueError("the upper K_P and K_I must be positive")
    if not lower_stable(cascade):
        return UpperLoop(False, False, 0, True, 0.0, float("nan"))
    change, omega, f, resolved = _winding(cascade, kp, ki)
    poles = int(round(0.5 - change / math.pi))
    stable = resolved and poles == 0
    if not stable:
        return UpperLoop(True, False, poles, resolved, 0.0, float("nan"))
    alpha, at = _disk(cascade, kp, ki, omega, f)
    return UpperLoop(True, True, 0, True, alpha, at)
