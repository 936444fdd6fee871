"""A DER's recorded set-point and infeed on one uniform time grid, as :mod:`model_fit` takes them.

A set-point holds from each of its samples to the next (zero-order hold); the infeed, a measured
quantity, is interpolated linearly between its samples. Times in s, powers in W.
"""

from __future__ import annotations

import numpy as np

__all__ = ["on_grid", "sample_period"]

_SAME = 1e-6
"""A set-point sample this close to a grid time (in periods) counts as at it."""


def sample_period(t_s: np.ndarray) -> float:
    """The median spacing of ``t_s`` (s), rounded to 1 ns (recorded times are whole ns; the
    spacing of their float seconds is not exact); ValueError if there are fewer than two
    distinct times."""
    steps = np.diff(np.unique(np.asarray(t_s, dtype=float)))
    if len(steps) == 0:
        raise ValueError("fewer than two distinct sample times")
    period = round(float(np.median(steps)), 9)
    if period <= 0:
        raise ValueError("samples closer than 1 ns")
    return period


def on_grid(setpoint_t_s: np.ndarray, setpoint: np.ndarray, measured_t_s: np.ndarray,
            measured: np.ndarray, period_s: float, start_s: float | None = None,
            stop_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, set-point, measured)`` every ``period_s`` from ``start_s`` to ``stop_s`` (default:
    where both series have samples). ValueError if they do not overlap."""
    ts, u = _sorted(setpoint_t_s, setpoint)
    tm, y = _sorted(measured_t_s, measured)
    first = max(ts[0], tm[0]) if start_s is None else max(start_s, ts[0], tm[0])
    last = tm[-1] if stop_s is None else min(stop_s, tm[-1])
    if last - first < period_s:
        raise ValueError(f"the set-point and the infeed overlap in less than one period "
                         f"({first:g} s to {last:g} s)")
    t = first + period_s * np.arange(int(np.floor((last - first) / period_s + 1e-9)) + 1)
    held = u[np.searchsorted(ts, t + _SAME * period_s, side="right") - 1]
    return t, held, np.interp(t, tm, y)


def _sorted(t_s, values) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(values, dtype=float)
    if t.shape != v.shape or t.ndim != 1 or len(t) == 0:
        raise ValueError("a series needs as many times as values, at least one")
    keep = np.isfinite(t) & np.isfinite(v)
    order = np.argsort(t[keep], kind="stable")
    return t[keep][order], v[keep][order]
