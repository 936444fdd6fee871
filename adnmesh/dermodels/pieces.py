"""Exact solutions of rate-limited first-order lags, as pieces ``a + b t + c exp(-t / tau)``.

The detailed DER models are chains of first-order lags whose inputs are constant or ramps
between events, some with rate limits on their output. Each such system is linear in each of its
modes (free, or held at a rate limit), and the instants where the mode changes have closed forms,
so the solution is exact: a list of :class:`Piece` s, each ``x(t) = a + b t + c e^{-t/tau}`` on
``[0, duration]`` (time measured from the piece's start, s).

- :func:`rate_limited_lag`: ``T dx/dt = r(t) - x`` with ``r(t) = r0 + s t``, the rate ``dx/dt``
  held within ``[-rate_down, rate_up]``;
- :func:`lag_of_pieces`: a plain lag driven by such pieces (the second stage of the CHP).

With the lag's derivative ``d = (r - x) / T``: free, ``d' = (s - d) / T``, so
``d(t) = s + (d0 - s) e^{-t/T}`` and ``x = r - T d``; held at ``rate_up``, ``x`` rises at
``rate_up`` and ``d(t) = d0 + (s - rate_up) t / T``. A free lag reaches ``rate_up`` only if the
ramp is steeper than it (``s > rate_up``), at ``t = T ln((s - d0) / (s - rate_up))``; a held one
is released when ``d`` falls back to the limit, at ``t = T (d0 - rate_up) / (rate_up - s)``. So a
constant-slope input gives at most two pieces. Rounding is the only error (relative ~1e-15).
"""

from __future__ import annotations

import math
from typing import NamedTuple

__all__ = ["Piece", "rate_limited_lag", "rate_limited_lag_end", "lag_of_pieces", "end_value"]

_REL = 1e-12          # relative tolerance deciding whether a derivative sits at its limit


class Piece(NamedTuple):
    """``x(t) = a + b t + c exp(-t / tau)`` for ``0 <= t <= duration`` (s; W, W/s)."""

    duration: float
    a: float
    b: float
    c: float
    tau: float

    def value(self, t: float) -> float:
        """``x(t)``, W."""
        return self.a + self.b * t + (self.c * math.exp(-t / self.tau) if self.c else 0.0)


def end_value(pieces: list[Piece], x0: float) -> float:
    """Value at the end of the last piece (``x0`` if there is none)."""
    return pieces[-1].value(pieces[-1].duration) if pieces else x0


def _mode(d: float, s: float, rate_up: float, rate_down: float) -> int:
    """+1 held at ``rate_up``, -1 held at ``-rate_down``, 0 free."""
    tol_up, tol_down = _REL * max(1.0, rate_up), _REL * max(1.0, rate_down)
    if d > rate_up + tol_up or (d >= rate_up - tol_up and s > rate_up):
        return 1
    if d < -rate_down - tol_down or (d <= -rate_down + tol_down and s < -rate_down):
        return -1
    return 0


def rate_limited_lag(x0: float, r0: float, s: float, t_lag: float, rate_up: float,
                     rate_down: float, duration: float) -> list[Piece]:
    """Pieces of ``x`` over ``[0, duration]`` (see the module docstring).

    Parameters
    ----------
    x0 : float
        ``x`` at the start, W.
    r0, s : float
        The input ``r(t) = r0 + s t``, W and W/s.
    t_lag : float
        Time constant ``T``, s (> 0).
    rate_up, rate_down : float
        Limits of ``dx/dt`` upwards and downwards, W/s (> 0; ``math.inf`` for none).
    duration : float
        Length of the interval, s (>= 0).
    """
    d0 = (r0 - x0) / t_lag
    if -rate_down <= s <= rate_up and -rate_down < d0 < rate_up:      # free throughout
        return [Piece(duration, r0 - s * t_lag, s, -t_lag * (d0 - s), t_lag)]
    pieces: list[Piece] = []
    t, x = 0.0, x0
    mode = _mode(d0, s, rate_up, rate_down)
    while t < duration:
        r, d = r0 + s * t, (r0 + s * t - x) / t_lag
        if mode == 0:
            if s > rate_up:
                switch = t_lag * math.log((s - d) / (s - rate_up)) if d < rate_up else 0.0
            elif s < -rate_down:
                switch = t_lag * math.log((d - s) / (-rate_down - s)) if d > -rate_down else 0.0
            else:
                switch = math.inf
            step = min(duration - t, switch)
            pieces.append(Piece(step, r - s * t_lag, s, -t_lag * (d - s), t_lag))
            next_mode = 1 if s > rate_up else -1
        else:
            limit = rate_up if mode == 1 else -rate_down
            gap = (d - limit) * mode                       # how far d is beyond the limit, >= 0
            approach = (limit - s) * mode                  # how fast d falls back to it
            switch = t_lag * max(gap, 0.0) / approach if approach > 0 else math.inf
            step = min(duration - t, switch)
            pieces.append(Piece(step, x, limit, 0.0, t_lag))
            next_mode = 0
        x = pieces[-1].value(step)
        t += step
        if step == switch:
            mode = next_mode
    return pieces


def rate_limited_lag_end(x0: float, r0: float, s: float, t_lag: float, rate_up: float,
                         rate_down: float, duration: float) -> float:
    """``x`` at the end of :func:`rate_limited_lag` (the same solution, without the pieces
    where the lag stays free: the hot path of the models)."""
    d0 = (r0 - x0) / t_lag
    if -rate_down <= s <= rate_up and -rate_down < d0 < rate_up:
        return r0 + s * (duration - t_lag) + t_lag * (s - d0) * math.exp(-duration / t_lag)
    return end_value(rate_limited_lag(x0, r0, s, t_lag, rate_up, rate_down, duration), x0)


def lag_of_pieces(x0: float, pieces: list[Piece], t_lag: float) -> float:
    """End value of ``T dx/dt = y(t) - x``, ``x(0) = x0``, with ``y`` given as ``pieces``.

    For ``y = a + b t + c e^{-t/tau}`` (``tau != T``):
    ``x = a + b (t - T) + c tau / (tau - T) e^{-t/tau} + K e^{-t/T}``; for ``tau == T`` the
    ``c`` term is ``c (t / T) e^{-t/T}``. ``K`` follows from ``x(0)``.
    """
    x = x0
    for p in pieces:
        t, e = p.duration, math.exp(-p.duration / t_lag)
        if p.c == 0.0:
            forced0, forced = p.a - p.b * t_lag, p.a + p.b * (t - t_lag)
        elif abs(p.tau - t_lag) > 1e-9 * t_lag:
            k = p.c * p.tau / (p.tau - t_lag)
            forced0 = p.a - p.b * t_lag + k
            forced = p.a + p.b * (t - t_lag) + k * math.exp(-t / p.tau)
        else:                                        # resonant case tau == T
            forced0 = p.a - p.b * t_lag
            forced = p.a + p.b * (t - t_lag) + p.c * (t / t_lag) * e
        x = forced + (x - forced0) * e
    return x
