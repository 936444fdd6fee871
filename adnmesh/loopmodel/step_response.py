"""Closed-loop step response with exact delays, and MATLAB-style step info.

The response is that of ``G_CL = C exp(-s T_com) G_A / (1 + L)`` (P_ref -> sum of DER infeeds)
to a unit step, computed by the method of steps on a uniform grid ``t_k = k h``:

- each actuator group is discretised *exactly* for an input that is linear between samples
  (first-order hold, :meth:`Actuator.foh_discretisation`),
- delays are ring buffers; when every delay is a multiple of ``h`` (the default: ``h`` is chosen
  commensurate with the delays) they are exact, otherwise the delayed signal is interpolated
  linearly,
- the integrator uses the trapezoidal rule (exact for linear error signals),
- the reference step at ``t = 0`` is represented with its left and right limits, so the jump of
  ``P_Y`` by ``K_P`` is propagated exactly.

The only approximation is the hold: ``P_Y`` and the error are taken linear between samples. The
local error is ``O(h^3 |u''|)`` and the global error ``O(h^2)``; the step ``h`` is chosen from the
fastest active actuator and the loop bandwidth so that the error on ``y`` stays below
``1e-4`` (relative to the final value) — :mod:`tests.test_stepresp` checks this bound against
the same response at ``h/4`` and against a python-control Padé model. The figures are those
of :mod:`adnmesh.loopmodel.step_figures` (the one rule of adnmesh): times (rise, settling) are
interpolated linearly between samples, the peak parabolically; their error is ``O(h^2)`` plus
the amplitude error divided by the slope.

Every candidate is simulated until its response has stayed within 0.5 % of the final value for
the last quarter of the simulated time, and at least for 4 x its slowest active actuator's time
constant plus delay (so the slow tail of a minor CHP share is seen) and 20 / bandwidth.
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math
from fractions import Fraction
from functools import reduce
from math import gcd

import numpy as np

from adnmesh.loopmodel.step_kernels import (advance, advance_exact, advance_exact_first_order_lanes,
                       advance_first_order_lanes, delay_taps)
from adnmesh.loopmodel.settle_kernel import (COARSEN_CURVATURE, MAX_BLOCK_VALUES, SETTLED_FRACTION,
                           coarsen_buffer, settle_lanes)
from adnmesh.loopmodel.frequency_response import as_candidates
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.step_figures import StepFigureAccumulator

__all__ = ["StepInfo", "simulate_step", "step_info", "step_info_from_samples", "choose_step",
           "choose_steps", "integral_rate", "commensurate_unit"]

_SETTLED_BAND = 0.005
#: samples per block of precomputed delay taps (bounds their memory to ~100 MB)
_TAP_BLOCK = 200_000


@dataclass(frozen=True)
class StepInfo:
    """Step-response figures of ``G_CL`` per candidate (arrays of shape (M,)).

    The final value is the DC gain, exactly 1 (integral action). Candidates not simulated
    (left out by ``mask``: the callers leave out the unstable ones) carry NaN.

    Attributes
    ----------
    overshoot_pct : ndarray
        ``100 (peak - 1)``, >= 0, percent of the final value.
    rise_time_s : ndarray
        10 % -> 90 % rise time (first crossings), s.
    settling_time_s : ndarray
        Time after which ``|y - 1| <= band`` (the configured band, 5 % by default), s.
    settling_time_2pct_s : ndarray
        Same with a 2 % band, s.
    peak : ndarray
        Peak value (final value = 1).
    peak_time_s : ndarray
        Time of the peak, s.
    step_s : float
        Simulation step h used, s.
    horizon_s : ndarray
        Simulated horizon per candidate, s.
    """

    overshoot_pct: np.ndarray
    rise_time_s: np.ndarray
    settling_time_s: np.ndarray
    settling_time_2pct_s: np.ndarray
    peak: np.ndarray
    peak_time_s: np.ndarray
    step_s: float
    horizon_s: np.ndarray


@functools.lru_cache(maxsize=256)
def commensurate_unit(delays: tuple[float, ...]) -> float:
    """Largest t with every delay an integer multiple of t (1 us resolution), s; 0 if none."""
    us = [int(round(float(Fraction(d).limit_denominator(10**6)) * 1e6)) for d in delays if d > 0]
    if not us:
        return 0.0
    return reduce(gcd, us) * 1e-6


def choose_steps(plant: Plant, bandwidth_rad_s=None) -> np.ndarray:
    """Default simulation step h per candidate, s; shape (M,) (see :func:`choose_step`)."""
    gains = np.atleast_2d(plant.gains_w)
    tau_min = np.array([float(a.time_constants_s.min()) for a in plant.actuators])
    tau = np.min(np.where(gains > 0, tau_min[None, :], np.inf), axis=1)
    h = np.minimum(0.5 * tau, 0.05)
    if bandwidth_rad_s is not None:
        bw = np.broadcast_to(np.asarray(bandwidth_rad_s, float), h.shape)
        h = np.where(np.isfinite(bw) & (bw > 0), np.minimum(h, 0.05 / np.where(bw > 0, bw, 1.0)),
                     h)
    h = np.minimum(h, float(plant.path_delays_s.min()))
    unit = commensurate_unit(tuple(np.append(plant.path_delays_s, plant.t_meas_s).tolist()))
    if unit > 0:
        snap = unit >= h / 100
        h = np.where(snap, unit / np.ceil(unit / h - 1e-9), h)
    return h


def choose_step(plant: Plant, bandwidth_rad_s: float | None = None) -> float:
    """Default simulation step h, s.

    ``h <= min(0.5 tau_min, 0.05 / omega_b, 0.05 s)`` over the actuator groups with a gain
    (``tau_min`` their fastest time constant, ``omega_b`` the loop bandwidth in rad/s), then
    shrunk so that every delay is a multiple of h when the delays are commensurate.
    """
    return float(choose_steps(plant, bandwidth_rad_s)[0])


def _delay_taps(delay_s: np.ndarray, h: float):
    """Integer part and fraction of each delay in steps."""
    q = np.asarray(delay_s) / h
    n = np.floor(q + 1e-9).astype(int)
    f = np.where(np.abs(q - n) < 1e-9, 0.0, q - n)
    return n, f


@functools.lru_cache(maxsize=1024)
def _discretised(actuators: tuple, order: int, path_delays_s: tuple, t_meas_s: float, h: float):
    """The simulation's matrices for step h (s), shared by every simulator of the same plant
    dynamics and step (never written to): each group's FOH discretisation padded to
    ``order`` states (Phi (G, n, n), gamma left and right (G, n), C (G, n)), the delays in
    whole steps and fractions (path (G,), measurement (1,)) and the ring length. A search
    builds thousands of simulators of the same few plants and steps."""
    g, n = len(actuators), order
    phi, gl, gr, c = np.zeros((g, n, n)), np.zeros((g, n)), np.zeros((g, n)), np.zeros((g, n))
    for i, act in enumerate(actuators):
        p_i, l_i, r_i, c_i = act.foh_discretisation(h)
        k = p_i.shape[0]
        phi[i, :k, :k], gl[i, :k], gr[i, :k], c[i, :k] = p_i, l_i, r_i, c_i
    n_in, f_in = _delay_taps(np.array(path_delays_s), h)
    n_meas, f_meas = _delay_taps(np.array([t_meas_s]), h)
    if np.any(n_in + f_in < 1.0 - 1e-9):
        raise ValueError("simulation step must not exceed T_com + T_delay")
    # columns 0..ring-1 hold samples j % ring; column `ring` is the constant 0 of t < 0
    ring = int(max(n_in.max(), n_meas.max())) + 3
    return phi, gl, gr, c, n_in, f_in, n_meas, f_meas, ring


class _Simulator:
    """Method-of-steps simulation of M loops sharing actuator dynamics and step h."""

    def __init__(self, plant: Plant, kp, ki, h: float, coarsen_limit_s: float | None = None,
                 lanes: bool | None = None):
        kp, ki, gains = as_candidates(plant, kp, ki)
        # 2h must not exceed this (the full plant's shortest forward path delay when the
        # plant is a reduction of it to its active groups: same steps as the full plant)
        self.coarsen_limit_s = (float(plant.path_delays_s.min()) if coarsen_limit_s is None
                                else float(coarsen_limit_s))
        # own writable copies: the candidates may be read-only views, and numba compiles a
        # kernel once per argument type (read-only and writable arrays are two)
        self.kp, self.ki, self.gains = (np.array(a, dtype=float) for a in (kp, ki, gains))
        self.plant = plant
        self.order = max(a.denominator.size - 1 for a in plant.actuators)
        # first-order groups (PT1, the reference model): the candidates are the kernels' inner
        # loop, so the buffers are stored sample by sample, (ring + 1, M), and the states
        # (G, M); else candidate by candidate, (M, ring + 1) and (M, G, n), with the general
        # kernels (``lanes`` False: also for first order; tests compare the two).
        self.lanes = self.order == 1 if lanes is None else bool(lanes) and self.order == 1
        m, g = self.kp.size, len(plant.actuators)
        self._discretise(h)
        self.p_y = np.zeros(self._buffer_shape(m))
        self.y_hist = np.zeros(self._buffer_shape(m))
        self.x = np.zeros((g, m) if self.lanes else (m, g, self.order))
        self.x_int = np.zeros(m)
        self.err = np.ones(m)
        if self.lanes:
            self.p_y[0, :] = self.kp             # right limit of P_Y at t = 0
        else:
            self.p_y[:, 0] = self.kp
        self.k = 0
        self.kc = self._output_gains()

    def _buffer_shape(self, m: int) -> tuple[int, int]:
        return (self.ring + 1, m) if self.lanes else (m, self.ring + 1)

    def _output_gains(self) -> np.ndarray:
        """``K_g C_g`` per candidate and group: (G, M) in lanes, else (M, G, n)."""
        kc = self.gains[:, :, None] * self.c[None]                 # (M, G, n)
        return np.ascontiguousarray(kc[:, :, 0].T) if self.lanes else kc

    @property
    def time_s(self) -> float:
        """Simulated time of the latest sample, s."""
        return self.k * self.h

    def _discretise(self, h: float) -> None:
        self.h = h
        (self.phi, self.gl, self.gr, self.c, self.n_in, self.f_in, self.n_meas, self.f_meas,
         self.ring) = _discretised(self.plant.actuators, self.order,
                                   tuple(self.plant.path_delays_s.tolist()),
                                   float(self.plant.t_meas_s), float(h))
        self.exact_delays = not (np.any(self.f_in) or np.any(self.f_meas))

    def can_coarsen(self) -> bool:
        """Doubling h keeps the scheme explicit (2h <= every forward path delay)."""
        return 2.0 * self.h <= self.coarsen_limit_s + 1e-12

    def coarsen(self) -> None:
        """Double the step, keeping every second sample of the delay buffers (exact)."""
        if self.k % 2:
            raise ValueError("coarsen at an even sample index")
        old_ring, k = self.ring, self.k
        self._discretise(2.0 * self.h)
        self.k = k // 2
        # the buffers' rule (every second sample kept) is the compiled loop's, in its layout
        if self.lanes:
            self.p_y = coarsen_buffer(self.p_y, k, old_ring, self.ring)
            self.y_hist = coarsen_buffer(self.y_hist, k, old_ring, self.ring)
        else:
            self.p_y, self.y_hist = (
                np.ascontiguousarray(coarsen_buffer(np.ascontiguousarray(b.T), k, old_ring,
                                                self.ring).T) for b in (self.p_y, self.y_hist))
        self.kc = self._output_gains()

    def keep(self, rows: np.ndarray) -> None:
        """Continue with the candidates ``rows`` only."""
        for name in ("kp", "ki", "gains", "x_int", "err"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[rows]))
        for name in ("p_y", "y_hist", "x", "kc"):
            a = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(a[:, rows] if self.lanes else a[rows]))

    def _taps(self, n, f, first: int, steps: int, right_end: bool):
        """Ring columns and weights of a delayed signal for ``steps`` consecutive samples.

        Sample position ``pos = j - n - f`` for ``j = first, ..., first + steps - 1``: columns
        ``floor(pos) % ring`` and the next, weight ``pos - floor(pos)`` on the next; positions
        before 0 read the zero column, and with ``right_end`` the position 0 itself reads the
        left limit (0) of the step at t = 0. Returns ``(c0, c1, w1)``, each (steps, len(n))
        (compiled: :func:`adnmesh.loopmodel.step_kernels.delay_taps`).
        """
        return delay_taps(first, steps, np.asarray(n, np.int64), np.asarray(f, float),
                          self.ring, right_end)

    def run(self, steps: int) -> np.ndarray:
        """Advance ``steps`` steps and return y at the new samples, shape (M, steps) (in
        lanes a transposed view of a (steps, M) array)."""
        if self.lanes:
            return self._run_lanes(steps)
        out = np.empty((self.kp.size, steps))
        dyn = (self.kc, self.phi, self.gl, self.gr, self.x)
        if self.exact_delays:
            advance_exact(steps, self.k, self.ring, self.h, self.kp, self.ki, *dyn, self.p_y,
                          self.y_hist, self.x_int, self.err, self.n_in, int(self.n_meas[0]), out)
            self.k += steps
            return out
        # the taps are (steps, G) arrays: in blocks, so that a long run stays within memory
        # (the kernel carries its state over, so the blocks change no result)
        for start in range(0, steps, _TAP_BLOCK):
            n = min(_TAP_BLOCK, steps - start)
            l0, l1, lw = self._taps(self.n_in, self.f_in, self.k, n, right_end=False)
            r0, r1, rw = self._taps(self.n_in, self.f_in, self.k + 1, n, right_end=True)
            m0, m1, mw = self._taps(self.n_meas, self.f_meas, self.k + 1, n, right_end=False)
            block = np.empty((self.kp.size, n))
            advance(n, self.k, self.ring, self.h, self.kp, self.ki, *dyn, self.p_y, self.y_hist,
                    self.x_int, self.err, l0, l1, lw, r0, r1, rw, np.ascontiguousarray(m0[:, 0]),
                    np.ascontiguousarray(m1[:, 0]), np.ascontiguousarray(mw[:, 0]), block)
            out[:, start:start + n] = block
            self.k += n
        return out

    def _run_lanes(self, steps: int) -> np.ndarray:
        """:meth:`run` with the first-order lanes kernels."""
        out = np.empty((steps, self.kp.size))
        g = self.x.shape[0]
        dyn = (self.kc, self.phi.reshape(g), self.gl.reshape(g), self.gr.reshape(g), self.x)
        if self.exact_delays:
            advance_exact_first_order_lanes(steps, self.k, self.ring, self.h, self.kp, self.ki,
                                            *dyn, self.p_y, self.y_hist, self.x_int, self.err,
                                            self.n_in, int(self.n_meas[0]), out)
            self.k += steps
            return out.T
        advance_first_order_lanes(steps, self.k, self.ring, self.h, self.kp, self.ki, *dyn,
                                  self.p_y, self.y_hist, self.x_int, self.err,
                                  np.asarray(self.n_in, np.int64), np.asarray(self.f_in, float),
                                  int(self.n_meas[0]), float(self.f_meas[0]), out)
        self.k += steps
        return out.T


def simulate_step(plant: Plant, kp, ki, t_end_s: float, h: float | None = None):
    """Unit-step response of ``G_CL`` on ``t = 0, h, ..., t_end``.

    Parameters
    ----------
    plant : Plant
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    t_end_s : float
        Horizon, s.
    h : float, optional
        Step, s (default :func:`choose_step`).

    Returns
    -------
    t : ndarray, shape (N,)
        Times, s.
    y : ndarray, shape (M, N)
        Sum of DER infeeds for a unit reference step (final value 1).
    """
    h = choose_step(plant) if h is None else h
    sim = _Simulator(plant, kp, ki, h)
    steps = int(np.ceil(t_end_s / h - 1e-9))
    y = np.concatenate([np.zeros((sim.kp.size, 1)), sim.run(steps)], axis=1)
    return np.arange(steps + 1) * h, y


def step_info_from_samples(h: float, y: np.ndarray, band_pct: float = 5.0) -> StepInfo:
    """Step info of sampled unit-step responses ``y`` (shape (M, N), ``y[:, 0]`` at t = 0,
    step h): the rule of :mod:`adnmesh.loopmodel.step_figures` on the uniform grid (crossing times
    interpolated linearly between samples, the peak parabolically)."""
    y = np.atleast_2d(y)
    acc = StepFigureAccumulator(y.shape[0], (band_pct / 100.0, 0.02))
    acc.last = y[:, 0].copy()
    acc.add(0.0, h, y[:, 1:])
    horizon = np.full(y.shape[0], h * (y.shape[1] - 1))
    return StepInfo(acc.overshoot_pct(), acc.rise_time_s(), acc.settle[0], acc.settle[1],
                    acc.peak, acc.peak_t, float(h), horizon)


def integral_rate(gains: np.ndarray, kp, ki) -> np.ndarray:
    """``K_I P / (1 + K_P P)`` with ``P = sum_g K_g`` (the loop's DC gain), 1/s; shape (M,).

    The closed loop's slowest pole when the loop gain is small at the actuators' corner
    frequencies (the PI zero and the integrator against a plant that is 1 there): a lower
    bound of the loop's bandwidth wherever the sampled disk-margin peak lies (for a loop
    with tiny gains that peak sits at the low end of the frequency grid, ~1e-7 rad/s).
    """
    total = np.atleast_2d(gains).sum(axis=1)
    return np.asarray(ki) * total / (1.0 + np.asarray(kp) * total)


def _horizon_floor(plant: Plant, gains: np.ndarray, bandwidth: np.ndarray,
                   rate: np.ndarray | None = None) -> np.ndarray:
    """Shortest horizon per candidate, s: 4 x (slowest active time constant + path delay)
    and 20 / bandwidth, so slow tails of minor actuators are seen before settling is judged.

    ``rate`` (1/s, :func:`integral_rate`) bounds the bandwidth from below: a disk-margin
    frequency far below it (the peak of a loop with tiny gains) would ask for a horizon no
    response needs (20 / 1.2e-7 rad/s = 5 years for a 6.5 kW DER alone at 1e-8 1/W).
    """
    slow = np.array([a.time_constants_s.max() + d
                     for a, d in zip(plant.actuators, plant.path_delays_s)])
    base = np.max(np.where(gains > 0, slow[None, :], 0.0), axis=1) * 4.0
    if rate is not None:
        bandwidth = np.where(np.isfinite(bandwidth), np.maximum(bandwidth, rate), bandwidth)
    return np.maximum(base, np.where(np.isfinite(bandwidth), 20.0 / bandwidth, 0.0))


_OUTPUTS = ("os", "tr", "ts", "ts2", "pk", "tp", "hor")


def _first_block(t_min: np.ndarray, h: float, m: int) -> int:
    """Samples of the first block of a bucket (even): ``min(t_min, 10 s) / h``, at least 50,
    at most :data:`~adnmesh.loopmodel.settle_kernel.MAX_BLOCK_VALUES` values in all."""
    chunk = int(np.clip(np.ceil(min(t_min.min(), 10.0) / h), 50,
                        MAX_BLOCK_VALUES // max(m, 1)))
    return chunk + chunk % 2


def _simulate_until_settled(plant, kp, ki, gains, h, t_min, band_pct, t_max, stop_above=None,
                            coarsen_limit_s=None, until_rise=False):
    """Simulate one step-size bucket; drop every candidate once it has settled.

    A candidate is settled when it has stayed within 0.5 % of the final value for the last
    quarter of the simulated time and at least ``t_min`` has been simulated; candidates still
    unsettled at ``t_max`` (s, one per candidate) keep ``inf`` settling times. With ``stop_above``, a candidate whose
    response exceeds that value is dropped at once (its overshoot is then a lower bound and its
    settling times are NaN): a search only needs to know that it violates the constraint.
    With ``until_rise``, a candidate is dropped once it has reached 90 % (its rise time is
    then known; overshoot and settling are not).

    First-order plants run the loop compiled (:func:`adnmesh.loopmodel.settle_kernel.settle_lanes`,
    the same figures bit for bit); others run :func:`_simulate_until_settled_stepwise`,
    which the tests also hold the compiled loop to.
    """
    if max(a.denominator.size - 1 for a in plant.actuators) != 1:
        return _simulate_until_settled_stepwise(plant, kp, ki, gains, h, t_min, band_pct, t_max,
                                                stop_above, coarsen_limit_s, until_rise)
    m = kp.size
    limit = (float(plant.path_delays_s.min()) if coarsen_limit_s is None
             else float(coarsen_limit_s))
    levels = _levels(plant.actuators, tuple(plant.path_delays_s.tolist()),
                     float(plant.t_meas_s), float(h), limit)
    res = settle_lanes(np.array(kp, dtype=float), np.array(ki, dtype=float),
                       np.array(gains, dtype=float), np.array(t_min, dtype=float),
                       np.array(np.broadcast_to(np.asarray(t_max, float), (m,))),
                       np.array([band_pct / 100.0, 0.02, _SETTLED_BAND]),
                       np.inf if stop_above is None else float(stop_above), bool(until_rise),
                       _first_block(t_min, h, m), levels)
    return dict(zip(_OUTPUTS, res))


@functools.lru_cache(maxsize=1024)
def _levels(actuators: tuple, path_delays_s: tuple, t_meas_s: float, h: float, limit: float):
    """The discretisations of first-order groups at every step the settle loop may double
    to: ``h, 2h, 4h, ...`` while ``2h <= limit + 1e-12`` (s): the ``levels`` argument of
    :func:`adnmesh.loopmodel.settle_kernel.settle_lanes`, a tuple (steps (L,); phi, gamma
    left and right, C (L, G); forward delays in steps and fractions (L, G); measurement
    delay (L,) twice; ring lengths (L,); whole-step delays (L,))."""
    hs = [h]
    while 2.0 * hs[-1] <= limit + 1e-12:
        hs.append(2.0 * hs[-1])
    rows = [_discretised(actuators, 1, path_delays_s, t_meas_s, x) for x in hs]
    g = len(actuators)
    phi, gl, gr, c = (np.array([r[i].reshape(g) for r in rows]) for i in range(4))
    n_in = np.array([r[4] for r in rows], dtype=np.int64)
    f_in = np.array([r[5] for r in rows], dtype=float)
    n_meas = np.array([int(r[6][0]) for r in rows], dtype=np.int64)
    f_meas = np.array([float(r[7][0]) for r in rows])
    ring = np.array([r[8] for r in rows], dtype=np.int64)
    exact = (~np.any(f_in != 0, axis=1)) & (f_meas == 0)
    out = (np.array(hs), phi, gl, gr, c, n_in, f_in, n_meas, f_meas, ring, exact)
    for a in out:
        a.setflags(write=False)
    return out


def _simulate_until_settled_stepwise(plant, kp, ki, gains, h, t_min, band_pct, t_max,
                                     stop_above=None, coarsen_limit_s=None, until_rise=False,
                                     lanes: bool | None = None):
    """:func:`_simulate_until_settled` as a Python loop over blocks of the compiled step
    kernels (any order of dynamics; ``lanes`` as :class:`_Simulator`'s)."""
    m = kp.size
    out = {k: np.full(m, np.nan) for k in _OUTPUTS}
    sim = _Simulator(plant.with_gains(gains), kp, ki, h, coarsen_limit_s, lanes=lanes)
    t_max = np.broadcast_to(np.asarray(t_max, float), (m,))
    acc = StepFigureAccumulator(m, (band_pct / 100.0, 0.02, _SETTLED_BAND))
    alive = np.arange(m)
    t_min_alive, t_max_alive = t_min, t_max
    chunk = _first_block(t_min, h, m)
    while alive.size:
        t0 = sim.time_s
        y = sim.run(chunk)
        samples = y.shape[1]
        curvature = acc.add(t0, sim.h, y)
        elapsed = sim.time_s
        settled = (acc.settle[2] <= SETTLED_FRACTION * elapsed) & (elapsed >= t_min_alive)
        over = acc.peak > stop_above if stop_above is not None else np.zeros(alive.size, bool)
        if until_rise:
            over = over | np.isfinite(acc.t90)
        finished = settled | over | (elapsed >= t_max_alive)
        if finished.any():
            idx = alive[finished]
            out["os"][idx] = acc.overshoot_pct()[finished]
            out["tr"][idx] = acc.rise_time_s()[finished]
            unsettled = np.where(over[finished], np.nan, np.inf)
            out["ts"][idx] = np.where(settled[finished], acc.settle[0][finished], unsettled)
            out["ts2"][idx] = np.where(settled[finished], acc.settle[1][finished], unsettled)
            out["pk"][idx] = acc.peak[finished]
            out["tp"][idx] = acc.peak_t[finished]
            out["hor"][idx] = elapsed
            keep = np.nonzero(~finished)[0]
            alive = alive[keep]
            t_min_alive, t_max_alive = t_min[alive], t_max[alive]
            sim.keep(keep)
            acc.keep(keep)
            curvature = curvature[keep]
        if not alive.size:
            break
        # smooth responses (second differences far below the error target) need no fine
        # step: doubling h multiplies the hold error by ~4, still within COARSEN_CURVATURE*4
        if (samples > 2 and sim.can_coarsen()
                and curvature.max() < COARSEN_CURVATURE):
            sim.coarsen()
        # np.clip's rule on scalars: max with the floor first, then min with the cap
        chunk = int(min(max(math.ceil(0.5 * elapsed / sim.h), chunk // 2),
                        MAX_BLOCK_VALUES // alive.size))
        chunk += (sim.k + chunk) % 2          # end every chunk on an even sample index
    return out


def _by_active_groups(plant: Plant, gains: np.ndarray, sel: np.ndarray):
    """Candidates ``sel`` split by the set of groups with a gain, each with the plant reduced
    to those groups: ``(rows, Plant)`` pairs.

    A group without gain adds exactly 0.0 to the output at every step, so leaving it out
    changes no bit of the response (same step h, same coarsening rule: the caller passes the
    full plant's limit), and the cost of a sparse candidate (e.g. a single-DER loop of a
    plant with 100 groups) is that of its own groups only.
    """
    active = gains[sel] > 0
    if active.all():
        yield sel, plant.with_gains(gains[sel])
        return
    if active.shape[1] <= 62:
        # each row's pattern as one integer (np.unique over rows costs ~50 us a call)
        codes = active.astype(np.int64) @ (np.int64(1) << np.arange(active.shape[1],
                                                                    dtype=np.int64))
        _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
        patterns = active[first]
    else:
        patterns, inverse = np.unique(active, axis=0, return_inverse=True)
    for p, pattern in enumerate(patterns):
        rows = sel[inverse.ravel() == p]
        cols = np.nonzero(pattern)[0]
        acts = tuple(plant.actuators[c] for c in cols)
        yield rows, Plant(acts, gains[np.ix_(rows, cols)], plant.t_com_s, plant.t_meas_s)


def step_info(plant: Plant, kp, ki, band_pct: float = 5.0, h: float | None = None,
              bandwidth_rad_s=None, mask=None, t_max_s: float = 20000.0,
              overshoot_stop_pct: float | None = None, until_rise: bool = False) -> StepInfo:
    """Step info of ``G_CL`` for M candidates (simulated as they are: an unstable loop's
    figures describe its diverging response up to the horizon; callers that need stable loops
    pass them in ``mask``).

    Parameters
    ----------
    plant : Plant
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    band_pct : float
        Settling band, percent of the final value (the 2 % figure is always computed too).
    h : float, optional
        Simulation step for every candidate, s (default :func:`choose_step` per candidate).
    bandwidth_rad_s : float or array_like, optional
        Loop bandwidth per candidate (e.g. the disk-margin frequency), rad/s; sets the step and
        the shortest horizon.
    mask : array_like of bool, optional
        Candidates to simulate (e.g. the stable ones); the rest get NaN.
    t_max_s : float or array_like, shape (M,)
        Longest horizon, s (one per candidate or one for all); a response not settled by
        then reports infinite settling times.
    overshoot_stop_pct : float, optional
        Stop simulating a candidate as soon as its overshoot exceeds this (percent); its
        overshoot is then only a lower bound and its settling times NaN.
    until_rise : bool
        Stop simulating a candidate once it has reached 90 % of the final value: only its
        rise time is wanted (overshoot a lower bound, settling times NaN); the simulation is
        the full one cut short.
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    m = kp.size
    mask = np.ones(m, bool) if mask is None else np.asarray(mask, bool)
    bw = np.broadcast_to(np.asarray(np.nan if bandwidth_rad_s is None else bandwidth_rad_s,
                                    float), (m,))
    fields = {k: np.full(m, np.nan) for k in ("os", "tr", "ts", "ts2", "pk", "tp", "hor")}
    steps = np.full(m, np.nan)
    idx = np.nonzero(mask)[0]
    if idx.size:
        if h is None:
            steps[idx] = choose_steps(plant.with_gains(gains[idx]), bw[idx])
        else:
            steps[idx] = h
        t_min = _horizon_floor(plant, gains, bw, integral_rate(gains, kp, ki))
        t_max = np.broadcast_to(np.asarray(t_max_s, float), (m,))
        stop = None if overshoot_stop_pct is None else 1.0 + overshoot_stop_pct / 100.0
        limit = float(plant.path_delays_s.min())
        for hb in np.unique(steps[idx]):
            for sel, reduced in _by_active_groups(plant, gains, idx[steps[idx] == hb]):
                res = _simulate_until_settled(reduced, kp[sel], ki[sel], reduced.gains_w,
                                              float(hb), t_min[sel], band_pct, t_max[sel],
                                              stop, coarsen_limit_s=limit,
                                              until_rise=until_rise)
                for k in fields:
                    fields[k][sel] = res[k]
    h_used = float(np.nanmin(steps)) if idx.size else float("nan")
    return StepInfo(fields["os"], fields["tr"], fields["ts"], fields["ts2"], fields["pk"],
                    fields["tp"], h_used, fields["hor"])
