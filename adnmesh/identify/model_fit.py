"""A DER's reaction time and rise time from its set-point and measured infeed: an actuator
model of the analyses (:class:`~adnmesh.loopmodel.plant.Actuator`: a dead time, then ``pt1``,
``pt2`` or ``rhpz`` of unit gain) fitted by least squares.

:func:`model_response` is the model's exact response on a uniform time grid to a set-point that
is constant between grid points (as a DER's recorded set-point is: it changes when a message
comes, and the recording samples it at the DER's period). The dead time need not be a multiple
of the grid: the part of a step that falls within a grid interval is integrated exactly
(``x[k+1] = Phi x[k] + Gamma_before u(before) + Gamma_now u(now)`` with the matrix exponentials
of the model's state space). The model starts at rest at the first measured value.
:func:`fit_model` fits the dead time ``T_delay`` and the time constant ``T`` (reported as
``T_rise = T ln 9``, the convention of the config and of the analyses' models) with
:func:`scipy.optimize.least_squares`, started from several dead times and lags (the error is not
convex in the dead time), and gives 95 % intervals from the fit's Jacobian. Those assume
independent residuals; a measured response's residuals are correlated, so read them as a lower
bound of the uncertainty. Times in s, powers in W.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.optimize import least_squares
from scipy.signal import lfilter, ss2tf

from adnmesh.loopmodel.plant import MODELS, RISE_PER_LAG, Actuator

__all__ = ["MODELS", "ModelFit", "RISE_PER_LAG", "fit_model", "fits_of", "model_response"]

_Z95 = 1.959963984540054


def _integral(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """``(exp(A tau), integral_0^tau exp(A s) ds B)``."""
    n = a.shape[0]
    block = np.zeros((n + 1, n + 1))
    block[:n, :n] = a * tau
    block[:n, n] = b * tau
    e = scipy.linalg.expm(block)
    return e[:n, :n], e[:n, n]


def model_response(actuator: Actuator, period_s: float, setpoint: np.ndarray,
                   y0: float) -> np.ndarray:
    """The model's infeed at ``k * period_s``, W: ``setpoint[k]`` holds on
    ``[k * period_s, (k + 1) * period_s)`` (and ``setpoint[0]`` from 0 on), the infeed starts
    at rest at ``y0`` and follows ``actuator`` (unit gain) ``t_delay_s`` after the set-point."""
    u = np.asarray(setpoint, dtype=float)
    a, b, c = actuator.state_space()
    whole, frac = divmod(actuator.t_delay_s / period_s, 1.0)
    whole = int(whole)
    phi, _ = _integral(a, b, period_s)
    late, gamma_now = _integral(a, b, (1.0 - frac) * period_s)
    _, early = _integral(a, b, frac * period_s)
    gamma_before = late @ early
    now = np.concatenate([np.full(min(whole, len(u)), u[0]), u[:max(len(u) - whole, 0)]]) - y0
    before = np.concatenate([[u[0] - y0], now[:-1]])
    out = np.full(len(u), y0)
    for gamma, v in ((gamma_now, now), (gamma_before, before)):
        num, den = ss2tf(phi, gamma.reshape(-1, 1), c.reshape(1, -1), np.zeros((1, 1)))
        out += lfilter(num[0], den, v)
    return out


@dataclass(frozen=True)
class ModelFit:
    """A fitted actuator model and how well it fits."""

    model: str
    """``pt1``, ``pt2`` or ``rhpz``."""
    delay_s: float
    """Reaction time T_delay, s."""
    rise_s: float
    """``T ln 9``, s: the 10-90 % rise time for ``pt1`` (the config's t_rise_s)."""
    delay_ci_s: tuple[float, float]
    """95 % interval of the reaction time, s (from the Jacobian: see the module docstring)."""
    rise_ci_s: tuple[float, float]
    """95 % interval of ``rise_s``, s."""
    rmse_w: float
    """Root mean square of the residuals, W."""
    r2: float
    """Share of the measured infeed's variance the model explains."""
    samples: int
    """Samples fitted."""

    @property
    def actuator(self) -> Actuator:
        """The fitted model."""
        return Actuator(self.delay_s, self.rise_s / RISE_PER_LAG, self.model)

    def response(self, period_s: float, setpoint: np.ndarray, y0: float) -> np.ndarray:
        """This model's response (see :func:`model_response`), W."""
        return model_response(self.actuator, period_s, setpoint, y0)


def fit_model(period_s: float, setpoint: np.ndarray, measured: np.ndarray, model: str = "pt1",
              max_delay_s: float = 30.0, max_rise_s: float = 600.0) -> ModelFit:
    """Fit ``model`` to ``measured`` (W) driven by ``setpoint`` (W), both sampled every
    ``period_s`` s (see the module docstring).

    Raises
    ------
    ValueError
        An unknown model, fewer than 10 samples, arrays of different lengths, or a set-point
        that never moves (nothing to identify).
    """
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
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
        return (model_response(Actuator(x[0], x[1], model), period_s, u, y0) - y) / scale

    bounds = ([0.0, min_lag], [max_delay_s, max_rise_s / RISE_PER_LAG])
    best = None
    for delay0 in [d for d in (0.0, 0.1, 1.0, 3.0) if d < max_delay_s]:
        for lag0 in (0.1, 10.0):
            start = [delay0, min(max(lag0, min_lag * 2), bounds[1][1] / 2)]
            found = least_squares(residuals, start, bounds=bounds, x_scale=[0.1, 1.0])
            if best is None or found.cost < best.cost:
                best = found
    return fits_of(best, scale, y, model)[0]


def fits_of(found, scale: float, measured: np.ndarray, model: str) -> list[ModelFit]:
    """The :class:`ModelFit` of each (dead time, lag) pair of ``found``'s parameters (a
    :func:`scipy.optimize.least_squares` result whose residuals are W over ``scale``), with
    95 % intervals from its Jacobian; RMSE and R² are of the whole fit."""
    y = np.asarray(measured, dtype=float)
    rss = float(np.sum((found.fun * scale) ** 2))
    jac = found.jac * scale
    try:
        cov = np.linalg.inv(jac.T @ jac) * rss / max(len(y) - found.x.size, 1)
        half = _Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        half = np.full(found.x.size, math.inf)
    total = float(np.sum((y - y.mean()) ** 2))
    out = []
    for i in range(0, found.x.size, 2):
        delay, lag = round(float(found.x[i]), 9), float(found.x[i + 1])   # a dead time to 1 ns
        out.append(ModelFit(
            model=model, delay_s=delay, rise_s=lag * RISE_PER_LAG,
            delay_ci_s=(max(delay - half[i], 0.0), delay + half[i]),
            rise_ci_s=(max(lag - half[i + 1], 0.0) * RISE_PER_LAG,
                       (lag + half[i + 1]) * RISE_PER_LAG),
            rmse_w=math.sqrt(rss / len(y)), r2=1.0 - rss / total if total > 0 else math.nan,
            samples=len(y)))
    return out
