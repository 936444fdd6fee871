"""Step response of the whole nested loop, every delay exact.

The upper reference steps by one unit at ``t = 0``; the response is the sum of every ADN's
DERs' infeed change, normalised so that its final value is 1 (the upper integrator). The
method is that of :mod:`adnmesh.loopmodel.step_response`, applied to the nested structure:

- every DER group of every ADN is discretised exactly for an input linear between samples
  (:meth:`~adnmesh.loopmodel.plant.Actuator.foh_discretisation`),
- every delay (inter-site, upper measurement, each ADN's T_com, T_delay,g, T_meas) is a whole
  number of steps ``h``: ``h`` divides their common unit, at least 0.1 ms
  (:func:`choose_step`),
- both PIs integrate by the trapezoidal rule, and the step's jump (``K_P`` of the upper PI,
  then ``K_P,i K_i K_P`` of each lower PI when it arrives) is carried as left and right
  limits, so the only approximation is the hold of the PI outputs between samples: global
  error ``O(h^2)``, which the tests bound against the same response at ``h/2`` and against
  python-control with Padé approximants.

With ``upper=None`` the upper loop is open: each ADN's reference offset is ``K_i`` times a
unit step delayed by its ``T_com,i`` (what the equivalent-model fit uses).
"""
from __future__ import annotations

import math

import numba
import numpy as np
import scipy.linalg

from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.step_response import commensurate_unit

__all__ = ["NestedStep", "choose_step", "simulate", "simulate_until_settled", "MAX_HORIZON_S",
           "MAX_STEPS", "MIN_UNIT_S"]

#: the step's target error: h as in the reference loop's simulation (s)
_H_MAX_S = 0.05
#: longest simulated horizon, s, and most steps simulated (bounds memory to ~24 MB per ADN)
MAX_HORIZON_S = 20000.0
MAX_STEPS = 1_000_000
#: the smallest common unit of the delays the simulation takes, s
MIN_UNIT_S = 1e-4
#: settled: within this of the final value over the last quarter of the horizon
_SETTLED = 0.005


class NestedStep:
    """A simulated response: ``t_s`` (s) and ``y`` (final value 1), plus each ADN's share
    ``y_adn`` (they sum to ``y``), shapes (N,) and (M, N); ``h`` the step, s."""

    def __init__(self, t_s: np.ndarray, y: np.ndarray, y_adn: np.ndarray, h: float):
        self.t_s, self.y, self.y_adn, self.h = t_s, y, y_adn, h


def choose_step(cascade: Cascade, bandwidth_rad_s: float | None = None) -> float:
    """Simulation step h, s: at most half the fastest lag, ``0.05 / bandwidth``, 50 ms and
    the shortest lower forward delay, and a whole fraction of the delays' common unit.

    Raises ValueError when the delays share no unit of at least :data:`MIN_UNIT_S` (they are
    then not representable exactly on a practical grid; whole milliseconds always are)."""
    taus = [float(a.time_constants_s.min()) for adn in cascade.adns
            for a, g in zip(adn.plant.actuators, adn.plant.gains_w) if g > 0]
    h = min(0.5 * min(taus), _H_MAX_S,
            min(float(adn.plant.path_delays_s.min()) for adn in cascade.adns))
    if bandwidth_rad_s is not None and bandwidth_rad_s > 0 and math.isfinite(bandwidth_rad_s):
        h = min(h, 0.05 / bandwidth_rad_s)
    delays = tuple(d for d in cascade.delays_s if d > 0)
    unit = commensurate_unit(delays)
    if delays and unit < MIN_UNIT_S - 1e-12:
        raise ValueError(f"the cascade's delays share no unit of at least {MIN_UNIT_S * 1e3:g} "
                         f"ms (their unit is {unit * 1e6:.3g} us; whole milliseconds always do)")
    return unit / math.ceil(unit / h - 1e-9) if delays else h


def _steps(delay_s: float, h: float) -> int:
    n = round(delay_s / h)
    if abs(n * h - delay_s) > 1e-9 * max(1.0, delay_s):
        raise ValueError(f"delay {delay_s:g} s is not a whole number of steps of {h:g} s")
    return n


def _layout(cascade: Cascade, h: float):
    """Block-diagonal FOH discretisation of every DER group with a gain, and the integer
    delays: ``(phi, gamma_left, gamma_right, c_out, owner, k_w, n_path)``."""
    phis, gls, grs, cs, owner, k_w, n_path = [], [], [], [], [], [], []
    for i, adn in enumerate(cascade.adns):
        for act, gain in zip(adn.plant.actuators, adn.plant.gains_w):
            if gain <= 0:
                continue
            phi, gl, gr, c = act.foh_discretisation(h)
            phis.append(phi)
            gls.append(gl[:, None])
            grs.append(gr[:, None])
            cs.append(c[None, :])
            owner.append(i)
            k_w.append(float(gain))
            n_path.append(_steps(adn.plant.t_com_s + act.t_delay_s, h))
    if min(n_path) < 1:
        raise ValueError("every lower forward delay T_com + T_delay must be at least one step")
    return (scipy.linalg.block_diag(*phis), scipy.linalg.block_diag(*gls),
            scipy.linalg.block_diag(*grs), scipy.linalg.block_diag(*cs),
            np.array(owner, np.int64), np.array(k_w), np.array(n_path, np.int64))


def simulate(cascade: Cascade, upper: tuple[float, float] | None, t_end_s: float,
             h: float | None = None) -> NestedStep:
    """The nested loop's unit step response up to ``t_end_s`` (s).

    Parameters
    ----------
    cascade : Cascade
    upper : (kp, ki) or None
        The upper PI's gains (1/W, 1/(W s)), or None for the open upper loop.
    t_end_s : float
        Horizon, s.
    h : float, optional
        Step, s (default :func:`choose_step`); every delay must be a whole number of steps.
    """
    h = choose_step(cascade) if h is None else float(h)
    n = int(math.ceil(t_end_s / h))
    phi, gl, gr, c_out, owner, k_w, n_path = _layout(cascade, h)
    m = len(cascade.adns)
    lower = np.array([[adn.kp, adn.ki] for adn in cascade.adns])
    n_site = np.array([_steps(d, h) for d in cascade.t_com_s], np.int64)
    n_meas = np.array([_steps(adn.plant.t_meas_s, h) for adn in cascade.adns], np.int64)
    closed = upper is not None
    kp, ki = upper if closed else (0.0, 0.0)
    y, y_adn = _run(n, h, phi, gl, gr, c_out, owner, k_w, n_path, m, lower, n_site, n_meas,
                    np.array(cascade.gains_w, float), _steps(cascade.t_meas_s, h),
                    closed, float(kp), float(ki))
    scale = 1.0 if closed else 1.0 / cascade.total_gain_w
    return NestedStep(np.arange(n + 1) * h, y * scale, y_adn * scale, h)


def simulate_until_settled(cascade: Cascade, upper: tuple[float, float] | None,
                           horizon_s: float, h: float | None = None) -> NestedStep:
    """:func:`simulate` from ``horizon_s`` on, doubling the horizon until the response has
    stayed within 0.5 % of its final value for the last quarter of it, up to
    :data:`MAX_HORIZON_S` or :data:`MAX_STEPS` steps (then it is returned unsettled)."""
    h = choose_step(cascade) if h is None else float(h)
    longest = min(MAX_HORIZON_S, MAX_STEPS * h)
    horizon = min(horizon_s, longest)
    while True:
        run = simulate(cascade, upper, horizon, h)
        tail = run.y[int(0.75 * run.y.size):]
        if np.abs(tail - 1.0).max() <= _SETTLED or horizon >= longest:
            return run
        horizon = min(2.0 * horizon, longest)


@numba.njit(cache=True)
def _run(n, h, phi, gl, gr, c_out, owner, k_w, n_path, m, lower, n_site, n_meas, gains,
         n_up_meas, closed, kp, ki):  # pragma: no cover - compiled
    """The method of steps over ``n`` steps; returns ``(y, y_adn)`` in W (per unit step)."""
    g = owner.size
    ns = phi.shape[0]
    x = np.zeros(ns)
    x_next = np.zeros(ns)
    y = np.zeros(n + 1)
    y_adn = np.zeros((m, n + 1))
    u = np.zeros(n + 1)            # upper P_Y, right limits
    u_jump = np.zeros(n + 1)
    lo = np.zeros((m, n + 1))      # lower P_Y, right limits
    lo_jump = np.zeros((m, n + 1))
    e_lo = np.zeros(m)
    xi_lo = np.zeros(m)
    u[0] = kp if closed else 1.0
    u_jump[0] = u[0]
    e_up, xi_up = 1.0, 0.0
    in_r = np.zeros(g)
    in_l = np.zeros(g)
    for i in range(m):
        if n_site[i] == 0:
            ref = gains[i] * u[0]
            e_lo[i] = ref
            lo[i, 0] = lower[i, 0] * ref
            lo_jump[i, 0] = lo[i, 0]
    for k in range(n):
        for j in range(g):
            a, r = owner[j], k - n_path[j]
            in_r[j] = k_w[j] * lo[a, r] if r >= 0 else 0.0
            in_l[j] = k_w[j] * (lo[a, r + 1] - lo_jump[a, r + 1]) if r + 1 >= 0 else 0.0
        for r in range(ns):
            acc = 0.0
            for c in range(ns):
                acc += phi[r, c] * x[c]
            for j in range(g):
                acc += gl[r, j] * in_r[j] + gr[r, j] * in_l[j]
            x_next[r] = acc
        x, x_next = x_next, x
        total = 0.0
        for j in range(g):
            out = 0.0
            for c in range(ns):
                out += c_out[j, c] * x[c]
            y_adn[owner[j], k + 1] += out
            total += out
        y[k + 1] = total
        if closed:
            back = k + 1 - n_up_meas
            e_new = 1.0 - (y[back] if back >= 0 else 0.0)
            xi_up += 0.5 * h * (e_up + e_new)
            e_up = e_new
            u[k + 1] = kp * e_new + ki * xi_up
        else:
            u[k + 1] = 1.0
        for i in range(m):
            s = k + 1 - n_site[i]
            ref = gains[i] * u[s] if s >= 0 else 0.0
            jump = gains[i] * u_jump[s] if s >= 0 else 0.0
            back = k + 1 - n_meas[i]
            e_r = ref - (y_adn[i, back] if back >= 0 else 0.0)
            xi_lo[i] += 0.5 * h * (e_lo[i] + e_r - jump)
            e_lo[i] = e_r
            lo[i, k + 1] = lower[i, 0] * e_r + lower[i, 1] * xi_lo[i]
            lo_jump[i, k + 1] = lower[i, 0] * jump
    return y, y_adn
