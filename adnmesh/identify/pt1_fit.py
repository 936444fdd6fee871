"""A DER's reaction time and rise time from its set-point and measured infeed: the reference
model (a dead time, then a first-order lag of gain 1) fitted by least squares.

:func:`pt1_response` is the model's exact response on a uniform time grid to a set-point that
is constant between grid points (as a DER's recorded set-point is: it changes when a message
comes, and the recording samples it at the DER's period): the dead time need not be a multiple
of the grid, the part of a step that falls within a grid interval is integrated exactly.
:func:`fit_pt1` fits the dead time ``T_delay`` and the lag ``T = T_rise / ln 9`` (the 10-90 %
rise time ``T_rise``) with :func:`scipy.optimize.least_squares`, started from several dead times
(the error is not convex in it), and gives 95 % intervals from the fit's Jacobian. Those assume
independent residuals; a measured response's residuals are correlated, so read them as a lower
bound of the uncertainty. Times in s, powers in W.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

__all__ = ["PT1Fit", "RISE_PER_LAG", "fit_pt1", "pt1_response"]

RISE_PER_LAG = math.log(9.0)
"""10-90 % rise time of a first-order lag over its time constant (2.197)."""

_Z95 = 1.959963984540054


def pt1_response(period_s: float, setpoint: np.ndarray, y0: float, delay_s: float,
                 lag_s: float) -> np.ndarray:
    """The model's infeed at ``k * period_s``, W: ``setpoint[k]`` holds on
    ``[k * period_s, (k + 1) * period_s)`` (and ``setpoint[0]`` before), the infeed starts at
    ``y0``, reacts ``delay_s`` later and follows with the lag ``lag_s`` (gain 1)."""
    u = np.asarray(setpoint, dtype=float)
    n_delay, frac = divmod(delay_s / period_s, 1.0)
    n_delay = int(n_delay)
    a = math.exp(-period_s / lag_s)
    tail = math.exp(-(1.0 - frac) * period_s / lag_s)
    c_now, c_before = 1.0 - tail, tail - a          # input of this interval, of the one before
    base = u[0]
    v = np.concatenate([np.zeros(min(n_delay, len(u))), u[:max(len(u) - n_delay, 0)] - base])
    forced = lfilter([0.0, c_now, c_before], [1.0, -a], v)
    free = (y0 - base) * a ** np.arange(len(u))
    return base + forced + free


@dataclass(frozen=True)
class PT1Fit:
    """A fitted reference model and how well it fits."""

    delay_s: float
    """Reaction time T_delay, s."""
    rise_s: float
    """10-90 % rise time T_rise, s."""
    delay_ci_s: tuple[float, float]
    """95 % interval of the reaction time, s (from the Jacobian: see the module docstring)."""
    rise_ci_s: tuple[float, float]
    """95 % interval of the rise time, s."""
    rmse_w: float
    """Root mean square of the residuals, W."""
    r2: float
    """Share of the measured infeed's variance the model explains."""
    samples: int
    """Samples fitted."""

    def model(self, period_s: float, setpoint: np.ndarray, y0: float) -> np.ndarray:
        """This model's response (see :func:`pt1_response`), W."""
        return pt1_response(period_s, setpoint, y0, self.delay_s, self.rise_s / RISE_PER_LAG)


def fit_pt1(period_s: float, setpoint: np.ndarray, measured: np.ndarray,
            max_delay_s: float = 30.0, max_rise_s: float = 600.0) -> PT1Fit:
    """Fit the reference model to ``measured`` (W) driven by ``setpoint`` (W), both sampled
    every ``period_s`` s (see the module docstring).

    Raises
    ------
    ValueError
        Fewer than 10 samples, arrays of different lengths, or a set-point that never moves
        (nothing to identify).
    """
    u = np.asarray(setpoint, dtype=float)
    y = np.asarray(measured, dtype=float)
    if u.shape != y.shape or u.ndim != 1:
        raise ValueError(f"set-point and measurement must be series of one length, got "
                         f"{u.shape} and {y.shape}")
    if len(u) < 10:
        raise ValueError(f"{len(u)} samples: at least 10 are needed")
    if np.ptp(u) <= 1e-9 * max(1.0, float(np.max(np.abs(u)))):
        raise ValueError("the set-point never moves: nothing to identify")
    y0 = float(y[0])
    scale = float(np.ptp(u))
    min_lag = period_s / 20.0

    def residuals(x: np.ndarray) -> np.ndarray:
        return (pt1_response(period_s, u, y0, x[0], x[1]) - y) / scale

    bounds = ([0.0, min_lag], [max_delay_s, max_rise_s / RISE_PER_LAG])
    best = None
    for delay0 in [d for d in (0.0, 0.1, 1.0, 3.0) if d < max_delay_s]:
        for lag0 in (0.1, 10.0):
            start = [delay0, min(max(lag0, min_lag * 2), bounds[1][1] / 2)]
            found = least_squares(residuals, start, bounds=bounds, x_scale=[0.1, 1.0])
            if best is None or found.cost < best.cost:
                best = found
    delay, lag = (float(v) for v in best.x)
    rss = float(np.sum((best.fun * scale) ** 2))
    dof = max(len(y) - 2, 1)
    jac = best.jac * scale
    try:
        cov = np.linalg.inv(jac.T @ jac) * rss / dof
        half = _Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        half = np.array([math.inf, math.inf])
    total = float(np.sum((y - y.mean()) ** 2))
    return PT1Fit(
        delay_s=delay, rise_s=lag * RISE_PER_LAG,
        delay_ci_s=(max(delay - half[0], 0.0), delay + half[0]),
        rise_ci_s=(max(lag - half[1], 0.0) * RISE_PER_LAG, (lag + half[1]) * RISE_PER_LAG),
        rmse_w=math.sqrt(rss / len(y)), r2=1.0 - rss / total if total > 0 else math.nan,
        samples=len(y))
