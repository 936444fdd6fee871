"""DER dynamics for time-domain runs, split into parameters, state and inputs.

For now the one model is the reference model (docs/method.md#reference-model), a first-order lag
behind a dead time::

    P(s) / P_set(s) = exp(-T_delay s) / (1 + T s),      T = T_rise / ln 9

driven by a setpoint that is constant between commands (the local controller changes it only
when a command arrives or its mode changes). Such an input makes the exact solution a chain of
exponentials, so the model is **exact** at every instant it is evaluated, whatever the spacing of
commands and samples: a setpoint given at ``t`` reaches the lag at ``t + T_delay`` (it is queued),
and between two changes of the lag's input ``u`` the infeed follows
``P(t) = u + (P(t0) - u) exp(-(t - t0) / T)``.

The detailed WT, CHP and PV models (docs/method.md#detailed-der-models, :mod:`adnmesh.dermodels`)
have the same three
parts (parameters, state, the setpoint as input) and the same two functions
(:func:`set_point`, :func:`infeed_at`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field


__all__ = ["PT1DelayParams", "PT1DelayState", "infeed_at", "set_point"]


@dataclass(frozen=True)
class PT1DelayParams:
    """Static parameters of the reference model of one DER.

    Parameters
    ----------
    p_inst_w : float
        Installed power, W.
    t_delay_ns : int
        Dead time (reaction time), ns.
    t_lag_s : float
        Time constant ``T`` of the lag, s.
    """

    p_inst_w: float
    t_delay_ns: int
    t_lag_s: float


@dataclass
class PT1DelayState:
    """Evolving state: the infeed at ``t_ns``, the lag's current input, queued setpoints.

    Attributes
    ----------
    t_ns : int
        Time the state refers to, ns.
    p_w : float
        Infeed at ``t_ns``, W.
    u_w : float
        Setpoint currently seen by the lag (after the dead time), W.
    queue : deque of (int, float)
        Setpoints given but not yet through the dead time: (time they reach the lag, value).
    """

    t_ns: int
    p_w: float
    u_w: float
    queue: deque = field(default_factory=deque)

    @classmethod
    def steady(cls, p_w: float, t_ns: int = 0) -> PT1DelayState:
        """A state at rest at ``p_w``."""
        return cls(t_ns, p_w, p_w)


def set_point(params: PT1DelayParams, state: PT1DelayState, t_ns: int, setpoint_w: float) -> None:
    """Input: the setpoint changes to ``setpoint_w`` at ``t_ns`` (reaches the lag after the dead
    time). Setpoints must be given in time order."""
    state.queue.append((t_ns + params.t_delay_ns, setpoint_w))


def infeed_at(params: PT1DelayParams, state: PT1DelayState, t_ns: int) -> float:
    """Advance ``state`` exactly to ``t_ns`` (>= ``state.t_ns``) and return the infeed there, W."""
    if t_ns < state.t_ns:
        raise ValueError(f"cannot go back in time ({t_ns} < {state.t_ns} ns)")
    queue = state.queue
    lag = params.t_lag_s
    while queue and queue[0][0] <= t_ns:
        t_change, u_next = queue.popleft()
        if t_change > state.t_ns:
            state.p_w = _decay(state.p_w, state.u_w, (t_change - state.t_ns) * 1e-9, lag)
            state.t_ns = t_change
        state.u_w = u_next
    if t_ns > state.t_ns:
        state.p_w = _decay(state.p_w, state.u_w, (t_ns - state.t_ns) * 1e-9, lag)
        state.t_ns = t_ns
    return state.p_w


def _decay(p_w: float, u_w: float, dt_s: float, lag_s: float) -> float:
    """Exact response of the lag with constant input ``u_w`` after ``dt_s``."""
    return u_w + (p_w - u_w) * math.exp(-dt_s / lag_s)
