"""The dynamics of each DER type from the interconnection point: a reference step's ``P_IP``
against the set-points the CPFC commanded, fitted by least squares (for the run-time model
watch, docs/method.md#model-watch).

The CPFC knows every set-point it commanded (its DERs' shares of ``P_Y``, limited) but not
the DERs' infeeds; ``P_IP`` is their sum plus a rest that holds still over a step's window.
DERs of one type share one model (the uncertainty set's rule, docs/tuning.md#robust-tables),
so the part of ``P_IP`` that moves is, for each type, its model's response to the sum of its
DERs' set-points (:func:`~adnmesh.identify.model_fit.model_response`: exact for any dead
time; the responses add up because the model is linear). Each type whose set-points carry at
least :data:`MIN_SHARE` of the window's movement gets its dead time and lag fitted
(:func:`scipy.optimize.least_squares`, started from the configured models and from two
other dead times, the error not being convex in them); the others keep their configured model.
Intervals are 95 % from the Jacobian (a lower bound: the residuals are correlated). Times in
s, powers in W.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from adnmesh.identify.model_fit import ModelFit, fits_of, model_response
from adnmesh.loopmodel.plant import RISE_PER_LAG, Actuator

__all__ = ["MIN_SHARE", "fit_types"]

#: a type whose summed set-point moves less than this share of all types' movement keeps its
#: configured model (too little of P_IP is its own to fit)
MIN_SHARE = 0.2

#: starts besides the configured models: (dead time, lag) of every fitted type, s
_STARTS_S = ((0.0, 10.0), (3.0, 10.0))


def fit_types(period_s: float, setpoints: dict[str, np.ndarray], measured: np.ndarray,
              configured: dict[str, Actuator], model: str = "pt1", max_delay_s: float = 30.0,
              max_rise_s: float = 600.0) -> dict[str, ModelFit]:
    """Fit ``model`` per DER type to ``measured`` (``P_IP``, W) driven by ``setpoints`` (type
    -> the summed set-points of its DERs, W), all sampled every ``period_s`` s from the
    instant before the step on; ``configured`` holds each type's configured model. Returns
    type -> fit for the types fitted (see the module docstring).

    Raises
    ------
    ValueError
        Fewer than 10 samples, series of different lengths, or no set-point moves.
    """
    y = np.asarray(measured, dtype=float)
    u = {t: np.asarray(v, dtype=float) for t, v in setpoints.items()}
    if len(y) < 10:
        raise ValueError(f"{len(y)} samples: at least 10 are needed")
    if any(v.shape != y.shape for v in u.values()):
        raise ValueError("set-points and measurement must be series of one length")
    moves = {t: float(np.ptp(v)) for t, v in u.items()}
    total = scale = sum(moves.values())      # W: the residuals' unit (types may move apart)
    if total <= 1e-9 * max(1.0, float(np.max(np.abs(y)))):
        raise ValueError("no set-point moves: nothing to identify")
    fitted = [t for t in u if moves[t] >= MIN_SHARE * total]
    fixed = sum((model_response(configured[t], period_s, u[t], u[t][0]) - u[t][0]
                 for t in u if t not in fitted), np.zeros_like(y))
    target = y - y[0] - fixed
    min_lag = period_s / 20.0

    def residuals(x: np.ndarray) -> np.ndarray:
        out = -target
        for i, t in enumerate(fitted):
            act = Actuator(x[2 * i], x[2 * i + 1], model)
            out = out + model_response(act, period_s, u[t], u[t][0]) - u[t][0]
        return out / scale

    low = [0.0, min_lag] * len(fitted)
    high = [max_delay_s, max_rise_s / RISE_PER_LAG] * len(fitted)
    best = None
    given = [x for t in fitted for x in (configured[t].t_delay_s, configured[t].t_lag_s)]
    for start in (given, *([d, lag] * len(fitted) for d, lag in _STARTS_S)):
        start = np.clip(start, np.add(low, 1e-9), np.subtract(high, 1e-9))
        found = least_squares(residuals, start, bounds=(low, high), x_scale=[0.1, 1.0] * len(fitted))
        if best is None or found.cost < best.cost:
            best = found
    return dict(zip(fitted, fits_of(best, scale, target, model)))
