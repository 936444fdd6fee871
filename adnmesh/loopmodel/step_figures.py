"""Figures of a sampled step response: the one rule behind every step figure in adnmesh.

The closed-loop model's step info (:mod:`adnmesh.loopmodel.step_response`, hence tuning and the analyses),
``adnmesh up``'s end-of-run summary and ``adnmesh inspect`` all compute rise time, settling
time, overshoot and peak here, with one compiled kernel (:func:`adnmesh.loopmodel.step_kernels.accumulate`):

- :func:`step_figures`: one response, sampled at any increasing times, normalised so that
  the step goes from 0 to 1 -> :class:`StepFigures`;
- :class:`StepFigureAccumulator`: the same for M responses on a uniform grid, block by block
  (the simulation's long horizons need little memory);
- :func:`reference_step_figures`: the rule applied to a run's recorded P_IP after each step
  of P_ref -> one :class:`ReferenceStep` per step.

The conventions are MATLAB's ``stepinfo`` (docs/method.md#figures-of-merit) with the final value
fixed at 1 (the
reference; a loop with integral action has DC gain 1) and times interpolated between
samples; see :class:`StepFigures`. python-control's ``step_info`` uses the same definitions
but reports the first sample past each threshold, so the two agree to one sampling interval
(``tests/test_stepfigures.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.step_kernels import accumulate, accumulate_lanes

__all__ = ["ReferenceStep", "StepFigureAccumulator", "StepFigures", "reference_step_figures",
           "step_figures"]

_UNIFORM = np.empty(0)


@dataclass(frozen=True)
class StepFigures:
    """Figures of a step response ``y`` sampled at ``(t_k, y_k)``, k = 0 .. N-1.

    ``y`` is normalised: 0 is the value before the step, 1 the target (final value); times
    count from the step, s. A first crossing of a level L is the first k with
    ``y_(k-1) < L <= y_k`` (k >= 1), placed at ``t_(k-1) + (t_k - t_(k-1)) (L - y_(k-1)) /
    (y_k - y_(k-1))``; it does not exist if ``y_0 >= L``.

    Attributes
    ----------
    rise_time_s : float
        First crossing of 0.9 minus first crossing of 0.1, s; NaN if either does not exist.
    settling_time_s : float
        Settling time in the band ``band_pct`` % of the step around 1, s: with k the last
        sample where ``|y_k - 1| > band``, the interpolated instant between ``t_k`` and
        ``t_(k+1)`` where y enters the band (``1 + band`` from above, ``1 - band`` from
        below); 0 if no sample is outside; ``inf`` if the last sample is outside (not settled
        within the samples).
    settling_time_2pct_s : float
        The same with a 2 % band, s.
    overshoot_pct : float
        ``max(0, 100 (peak - 1))``, % of the step.
    peak : float
        The largest sample ``y_j`` (the first of equal ones), refined to the vertex of the
        parabola through samples j-1, j, j+1 when j is neither the first nor the last sample
        and that parabola is concave.
    peak_time_s : float
        Time of the peak (of the vertex when refined), s.
    steady_error : float
        ``1 - y_(N-1)``, the error left at the last sample, fraction of the step.
    band_pct : float
        The settling band used for ``settling_time_s``, %.
    """

    rise_time_s: float
    settling_time_s: float
    settling_time_2pct_s: float
    overshoot_pct: float
    peak: float
    peak_time_s: float
    steady_error: float
    band_pct: float


class StepFigureAccumulator:
    """The figures of M responses on a uniform grid, taken in block by block.

    Attributes hold the running state (shape (M,)): ``t10``, ``t90`` (first crossings, NaN
    until found), ``peak``, ``peak_t``, ``settle`` (shape (len(bands), M): last band exits),
    ``last`` (the latest sample, y before the next block; 0 initially).

    Parameters
    ----------
    m : int
        Number of responses.
    bands : tuple of float
        Settling bands, fractions of the step (e.g. 0.05, 0.02).
    """

    FIELDS = ("t10", "t90", "peak", "peak_t", "last")

    def __init__(self, m: int, bands: tuple[float, ...]):
        self.t10 = np.full(m, np.nan)
        self.t90 = np.full(m, np.nan)
        self.peak = np.full(m, -np.inf)
        self.peak_t = np.zeros(m)
        self.bands = bands
        self.settle = np.zeros((len(bands), m))
        self.last = np.zeros(m)

    def keep(self, rows: np.ndarray) -> None:
        """Continue with the responses ``rows`` only."""
        for name in self.FIELDS:
            setattr(self, name, getattr(self, name)[rows])
        # C order as allocated (a column selection would be F order: a second compilation
        # of the kernels, and a slower scan)
        self.settle = np.ascontiguousarray(self.settle[:, rows])

    def add(self, t0: float, h: float, chunk: np.ndarray, times: np.ndarray | None = None):
        """Take in y at ``t0 + h, ..., t0 + n h`` (shape (M, n); ``last`` is at t0),
        or at ``times[1:]`` (``times`` (n + 1,), s, increasing, ``times[0]`` the time of
        ``last``). Returns each response's largest ``|second difference|`` of y in the block.
        """
        curvature = np.zeros(chunk.shape[0])
        if chunk.shape[1] == 0:
            return curvature
        times = _UNIFORM if times is None else np.ascontiguousarray(times, dtype=float)
        if times.size and times.shape != (chunk.shape[1] + 1,):
            raise ValueError(f"{chunk.shape[1]} samples need {chunk.shape[1] + 1} times, got "
                             f"{times.shape}")
        chunk = np.asarray(chunk, dtype=float)
        # the transposed (steps, M) block of a lanes simulation as it is, else in C order
        lanes = chunk.T.flags.c_contiguous and not chunk.flags.c_contiguous
        (accumulate_lanes if lanes else accumulate)(
            float(t0), float(h), times, chunk.T if lanes else np.ascontiguousarray(chunk),
            self.last, self.t10, self.t90, self.peak, self.peak_t,
            np.asarray(self.bands, float), self.settle, curvature)
        return curvature

    def overshoot_pct(self) -> np.ndarray:
        """``max(0, 100 (peak - 1))`` per response, %."""
        return np.maximum(0.0, 100.0 * (self.peak - 1.0))

    def rise_time_s(self) -> np.ndarray:
        """10 % -> 90 % rise time per response, s (NaN until both crossings are seen)."""
        return self.t90 - self.t10


def step_figures(t_s, y, band_pct: float = 5.0) -> StepFigures:
    """Figures of one sampled step response (see :class:`StepFigures` for the definitions).

    Parameters
    ----------
    t_s : array_like, shape (N,)
        Sample times from the step, s; strictly increasing, any spacing; N >= 2.
    y : array_like, shape (N,)
        Response normalised to the step (0 before it, 1 at the target); finite.
    band_pct : float
        Settling band, % of the step (the 2 % figure is always computed too).

    Returns
    -------
    StepFigures
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or t.shape != y.shape or t.size < 2:
        raise ValueError(f"step figures need t and y of the same length >= 2, got shapes "
                         f"{t.shape} and {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("step figures need finite sample times and values")
    if not np.all(np.diff(t) > 0):
        raise ValueError("step figures need strictly increasing sample times")
    if not band_pct > 0:
        raise ValueError(f"settling band must be positive, got {band_pct:g} %")
    acc = StepFigureAccumulator(1, (band_pct / 100.0, 0.02))
    acc.last[0] = y[0]
    acc.add(t[0], 0.0, y[None, 1:], times=t)
    return StepFigures(float(acc.rise_time_s()[0]), float(acc.settle[0, 0]),
                       float(acc.settle[1, 0]), float(acc.overshoot_pct()[0]),
                       float(acc.peak[0]), float(acc.peak_t[0]), float(1.0 - y[-1]),
                       float(band_pct))


@dataclass(frozen=True)
class ReferenceStep:
    """P_IP's response to one step of P_ref in a run (see :func:`reference_step_figures`).

    Attributes
    ----------
    t_s : float
        Time of the step, s on the run's clock.
    step_w : float
        Height of the step, ``P_ref after - P_ref before``, W.
    p_ref_w : float
        The new P_ref, W.
    figures : StepFigures or None
        Figures of the normalised P_IP in the window; None with fewer than 2 samples.
    steady_error_w : float or None
        ``P_ref - P_IP`` at the window's last sample, W; None without samples.
    window_s : float
        Length of the window, s.
    """

    t_s: float
    step_w: float
    p_ref_w: float
    figures: StepFigures | None
    steady_error_w: float | None
    window_s: float


def _clean_samples(t_ns, values) -> tuple[np.ndarray, np.ndarray]:
    """Finite samples in time order (stable), the first of several at the same instant."""
    t = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(values, dtype=float)
    if t.shape != v.shape or t.ndim != 1:
        raise ValueError(f"sample times and values differ in shape: {t.shape} vs {v.shape}")
    keep = np.isfinite(v)
    t, v = t[keep], v[keep]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    first = np.ones(t.size, bool)
    first[1:] = t[1:] != t[:-1]
    return t[first], v[first]


OWN_STEP_RESOLUTION = 1e-12
"""A change of a reference less its offset from a level above (an ADN of a hierarchy) is a step
only if larger than this fraction of the reference (or 1 nW): the difference of a sum and one
of its terms carries rounding of a few parts in 1e16, which is no step."""


def is_own_step(before_w: float, before_offset_w: float, after_w: float,
                after_offset_w: float) -> bool:
    """Whether the reference ``after_w`` (its offset ``after_offset_w``) is a step from the one
    before: without offsets any change; with them, a change of the reference less its offset
    beyond :data:`OWN_STEP_RESOLUTION`."""
    if before_offset_w == 0.0 and after_offset_w == 0.0:
        return after_w != before_w
    change = (after_w - after_offset_w) - (before_w - before_offset_w)
    return abs(change) > OWN_STEP_RESOLUTION * max(abs(after_w), abs(before_w), 1e3)


def own_steps(values_w, offsets_w) -> np.ndarray:
    """The indices (from 1) of the records of ``values_w`` that are steps from the one before
    (:func:`is_own_step`), given each record's offset ``offsets_w``."""
    v = np.asarray(values_w, dtype=float)
    o = np.asarray(offsets_w, dtype=float)
    if v.size < 2:
        return np.zeros(0, dtype=np.intp)
    plain = (o[1:] == 0.0) & (o[:-1] == 0.0)
    change = (v[1:] - o[1:]) - (v[:-1] - o[:-1])
    scale = np.maximum(np.maximum(np.abs(v[1:]), np.abs(v[:-1])), 1e3)
    step = np.where(plain, v[1:] != v[:-1], np.abs(change) > OWN_STEP_RESOLUTION * scale)
    return np.flatnonzero(step) + 1


def reference_step_figures(p_ip_t_ns, p_ip_w, p_ref_t_ns, p_ref_w, window_ends_ns, end_ns: int,
                           *, band_pct: float = 5.0, origin_ns: int = 0, offset_w=None
                           ) -> tuple[ReferenceStep, ...]:
    """Figures of P_IP after every step of P_ref in a run.

    A step is a P_ref value that differs from the one before. With ``offset_w``, the part of
    each P_ref record that is the level above's offset (an ADN of a hierarchy), a step is a
    record whose P_ref less its offset differs from the one before: the offset is an input
    the loop tracks, not a step of its own reference. Its window runs from the step
    to the first later instant among the next step and ``window_ends_ns`` (exclusive), or to
    the end of the run (inclusive). The P_IP samples in the window, normalised by the
    reference step, ``y = (P_IP - P_ref before) / (P_ref after - P_ref before)``, at their
    sampling times from the step, give the :class:`StepFigures` (:func:`step_figures`).

    The reference, not the P_IP measured before the step, is the origin of ``y``: the measured
    value is one noisy sample (or a loop still settling from an earlier event), while the
    reference step is what the controller was asked to do, known exactly; with the loop at
    rest both are the same, and an offset left from before shows in the figures (as a steady
    error or a shifted rise) instead of silently rescaling them.

    Parameters
    ----------
    p_ip_t_ns, p_ip_w : array_like of int, array_like of float
        P_IP sampling instants (ns) and values (W). Non-finite values are left out, and so is
        every sample at the same instant as an earlier one.
    p_ref_t_ns, p_ref_w : array_like of int, array_like of float
        Instants (ns) at which P_ref was sent, with its value (W); the first is the initial
        value.
    window_ends_ns : array_like of int
        Other instants that end a step's window (gain switches, availability changes, fault
        starts and ends), ns.
    offset_w : array_like of float, optional
        Per P_ref record, the level above's offset it includes, W (see above).
    end_ns : int
        End of the run, ns.
    band_pct : float
        Settling band, % of the step.
    origin_ns : int
        Instant that ``t_s`` counts from, ns.

    Returns
    -------
    tuple of ReferenceStep
        In time order.
    """
    t_ip, p_ip = _clean_samples(p_ip_t_ns, p_ip_w)
    t_ref, v_ref = _clean_samples(p_ref_t_ns, p_ref_w)
    if offset_w is None:
        change = np.flatnonzero(v_ref[1:] != v_ref[:-1]) + 1
    else:
        v = np.asarray(p_ref_w, dtype=float)
        _, offset = _clean_samples(p_ref_t_ns, np.where(np.isfinite(v), np.asarray(
            offset_w, dtype=float), np.nan))
        if offset.shape != v_ref.shape:
            raise ValueError("offsets must be finite where P_ref is")
        change = own_steps(v_ref, offset)
    ends = np.unique(np.concatenate([t_ref[change],
                                     np.asarray(window_ends_ns, dtype=np.int64).ravel()]))
    steps = []
    for i in change:
        t0, before, after = int(t_ref[i]), float(v_ref[i - 1]), float(v_ref[i])
        later = ends[ends > t0]
        t1 = min(int(later[0]), end_ns) if later.size else end_ns
        inside = (t_ip >= t0) & ((t_ip < t1) | ((t_ip == end_ns) & (t1 == end_ns)))
        t_rel, y = (t_ip[inside] - t0) / 1e9, (p_ip[inside] - before) / (after - before)
        figures = step_figures(t_rel, y, band_pct) if t_rel.size >= 2 else None
        steady = after - float(p_ip[inside][-1]) if t_rel.size else None
        steps.append(ReferenceStep((t0 - origin_ns) / 1e9, after - before, after, figures,
                                   steady, max(t1 - t0, 0) / 1e9))
    return tuple(steps)

