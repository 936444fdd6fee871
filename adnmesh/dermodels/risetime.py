"""The 10-90 % rise time of a DER model's step response, exactly (to 1 ns).

A model is given by its four functions (``steady_state``, ``set_point``, ``infeed_at``; see
:mod:`adnmesh.dermodels.state`) and its parameters. The response is evaluated from a fresh state
for every instant, so the crossings of 10 % and 90 % of the step can be found by bracketing on a
grid and Brent's method, to the model's own 1 ns time resolution; nothing is interpolated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["ModelFunctions", "step_value", "normalised", "first_crossing", "crossing_time",
           "rise_time"]


@dataclass(frozen=True)
class ModelFunctions:
    """The functions of a DER model, as the DER agent calls them.

    ``steady_state(params, p_w, t_ns) -> state``, ``set_point(params, state, t_ns, p_w)``,
    ``infeed_at(params, state, t_ns) -> p_w``.
    """

    steady_state: Callable
    set_point: Callable
    infeed_at: Callable


def step_value(model: ModelFunctions, params, p0_w: float, p1_w: float) -> Callable:
    """``f(t_s)``: infeed ``t_s`` after the setpoint steps from ``p0_w`` (at rest) to ``p1_w``."""
    def f(t_s: float) -> float:
        state = model.steady_state(params, p0_w, 0)
        model.set_point(params, state, 0, p1_w)
        return model.infeed_at(params, state, int(round(max(t_s, 0.0) * 1e9)))
    return f


def first_crossing(f: Callable, t: np.ndarray, y: np.ndarray, level: float) -> float | None:
    """First time the rising ``f`` (sampled as ``y`` at ``t``) reaches ``level``, refined
    between the bracketing samples with Brent's method; None if no sample reaches it."""
    above = np.nonzero(y >= level)[0]
    if above.size == 0:
        return None
    i = int(above[0])
    if i == 0:
        return float(t[0])
    from scipy.optimize import brentq   # calibration only: a DER agent of a PV or PT1 needs none

    return float(brentq(lambda x: f(x) - level, t[i - 1], t[i], xtol=1e-10, rtol=1e-12))


def crossing_time(f: Callable, level: float, t_end_s: float, n: int = 400) -> float | None:
    """First ``t`` in ``[0, t_end_s]`` where the rising ``f`` reaches ``level``; None if never."""
    t = np.linspace(0.0, t_end_s, n + 1)
    return first_crossing(f, t, np.array([f(x) for x in t]), level)


def normalised(model: ModelFunctions, params, p0_w: float, p1_w: float) -> Callable:
    """``g(t_s)``: the step response ``p0_w -> p1_w`` scaled to rise from 0 to 1."""
    f = step_value(model, params, p0_w, p1_w)
    return lambda t_s: (f(t_s) - p0_w) / (p1_w - p0_w)


def rise_time(model: ModelFunctions, params, p0_w: float, p1_w: float,
              t_end_s: float) -> float:
    """10-90 % rise time, s, of the step ``p0_w -> p1_w`` (up or down; ``p1_w != p0_w``).

    ``t_end_s`` is a first guess of how long the response needs to pass 90 %; it is doubled
    until it does (at most 20 times).
    """
    g = normalised(model, params, p0_w, p1_w)
    for _ in range(20):
        t = np.linspace(0.0, t_end_s, 401)
        y = np.array([g(x) for x in t])
        t90 = first_crossing(g, t, y, 0.9)
        if t90 is not None:
            return t90 - first_crossing(g, t, y, 0.1)
        t_end_s *= 2.0
    raise ValueError(f"the response never reaches 90 % of the step {p0_w} -> {p1_w} W")
