"""Wind turbine: IEC 61400-27-1 Type 4B-like active power control
(docs/method.md#detailed-der-models).

    setpoint --(dead time t_delay_s)--> limit to [p_min_w, p_max_w]
             --> ramp-rate limiter: dr/dt in [-ramp_down, ramp_up]          (reference r)
             --> T dP/dt = r - P,  dP/dt in [-rate_down, rate_up]            (P_ord, infeed P)

The first stage is the plant controller's ramp-rate limit on the turbine's power reference, the
second the Type 4 P control's first-order lag of the power order with its rate limit
(``dpmax``) and absolute limits; the absolute limits act on the reference, so the lag cannot
wind up beyond them (a lag never leaves the range of its input and start). Increases of the
reference are ramp-limited, decreases not by default (curtailment is immediate at the
reference), so **steps up are slower than steps down**; the lag's rate limit bounds large
decreases (and increases too, should ``ramp_up`` exceed it).

Exact solution: between events the reference is a ramp or constant, and the rate-limited lag
with a ramp input is solved in closed form (:mod:`adnmesh.dermodels.pieces`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from adnmesh.dermodels.pieces import rate_limited_lag_end
from adnmesh.dermodels.risetime import ModelFunctions, rise_time
from adnmesh.dermodels.state import DeadTime, DerState, infeed_function, set_point

__all__ = ["WTParams", "default_params", "steady_state", "set_point", "infeed_at", "advance",
           "output", "DESIGN_STEP", "RAMP_SHARE", "RATE_STEP"]

#: Step of the reference that the defaults' rise time is calibrated on, fraction of P_inst
#: (from 50 % to 60 % of P_inst).
DESIGN_STEP = 0.10
#: Share of ``t_rise_s`` the ramp-rate limiter alone takes for the design step.
RAMP_SHARE = 0.8
#: The lag's rate limit is reached by free steps larger than this fraction of P_inst.
RATE_STEP = 0.25


@dataclass(frozen=True)
class WTParams(DeadTime):
    """Parameters of the WT model (W, s, W/s).

    Parameters
    ----------
    p_inst_w : float
        Installed power, W.
    t_delay_s : float
        Dead time, s.
    t_lag_s : float
        Time constant of the power-order lag, s.
    ramp_up_w_per_s, ramp_down_w_per_s : float
        Ramp-rate limits of the reference, W/s (``math.inf``: none).
    rate_up_w_per_s, rate_down_w_per_s : float
        Rate limits of the lag's output, W/s (``math.inf``: none).
    p_min_w, p_max_w : float
        Absolute limits, W (``p_max_w``: available power; default ``p_inst_w``).
    """

    p_inst_w: float
    t_delay_s: float
    t_lag_s: float
    ramp_up_w_per_s: float
    ramp_down_w_per_s: float = math.inf
    rate_up_w_per_s: float = math.inf
    rate_down_w_per_s: float = math.inf
    p_min_w: float = 0.0
    p_max_w: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.p_max_w):
            object.__setattr__(self, "p_max_w", float(self.p_inst_w))
        if not (self.p_inst_w > 0 and self.t_delay_s >= 0 and self.t_lag_s > 0
                and min(self.ramp_up_w_per_s, self.ramp_down_w_per_s, self.rate_up_w_per_s,
                        self.rate_down_w_per_s) > 0 and 0 <= self.p_min_w <= self.p_max_w):
            raise ValueError(f"invalid WT model parameters: {self}")


def steady_state(params: WTParams, p_w: float, t_ns: int = 0) -> DerState:
    """At rest at ``p_w`` (limited) at ``t_ns``."""
    p = min(max(float(p_w), params.p_min_w), params.p_max_w)
    return DerState(t_ns, (p, p), p, t_last_ns=t_ns)


def advance(params: WTParams, core: tuple, u_w: float, dt_s: float) -> tuple:
    """Exact ``(reference, infeed)`` after ``dt_s`` with the limited setpoint ``u_w``."""
    r, x = core
    if (u_w > r and math.isinf(params.ramp_up_w_per_s)) or \
            (u_w < r and math.isinf(params.ramp_down_w_per_s)):
        r = u_w
    t = 0.0
    while t < dt_s:
        if r < u_w:
            s = params.ramp_up_w_per_s
            t_reach = (u_w - r) / s
        elif r > u_w:
            s = -params.ramp_down_w_per_s
            t_reach = (r - u_w) / -s
        else:
            s, t_reach = 0.0, math.inf
        step = min(dt_s - t, t_reach)
        x = rate_limited_lag_end(x, r, s, params.t_lag_s, params.rate_up_w_per_s,
                                 params.rate_down_w_per_s, step)
        r = u_w if step == t_reach else r + s * step
        t += step
    return (r, x)


def output(params: WTParams, core: tuple) -> float:
    """Infeed, W."""
    return core[1]


infeed_at = infeed_function(advance, output)


FUNCTIONS = ModelFunctions(steady_state, set_point, infeed_at)


def default_params(p_inst_w: float, t_delay_s: float, t_rise_s: float,
                   p_max_w: float | None = None) -> WTParams:
    """Defaults with reaction ``t_delay_s`` and 10-90 % rise time ``t_rise_s`` for a step of
    the setpoint from 50 % to 60 % of ``p_inst_w`` (:data:`DESIGN_STEP`).

    The ramp-rate limit takes :data:`RAMP_SHARE` of the rise time for that step
    (``ramp_up = 0.1 P_inst / (0.8 t_rise)``); the lag's time constant is then solved for
    (Brent's method on the exact rise time), and its rate limit is set so that free steps
    above :data:`RATE_STEP` of ``P_inst`` reach it (``rate = 0.25 P_inst / T``, both ways).
    Decreases of the reference are not ramp-limited. ``p_max_w`` (default ``p_inst_w``) does
    not enter the calibration.
    """
    return _params(p_inst_w, t_delay_s, t_rise_s, _lag_for(t_delay_s, t_rise_s),
                   p_inst_w if p_max_w is None else p_max_w)


def _params(p_inst_w, t_delay_s, t_rise_s, t_lag, p_max_w) -> WTParams:
    ramp = DESIGN_STEP * p_inst_w / (RAMP_SHARE * t_rise_s)
    rate = RATE_STEP * p_inst_w / t_lag
    return WTParams(p_inst_w, t_delay_s, t_lag, ramp, math.inf, rate, rate, p_max_w=p_max_w)


@lru_cache(maxsize=64)
def _lag_for(t_delay_s: float, t_rise_s: float) -> float:
    """The lag's time constant, s; every limit scales with P_inst, so P_inst = 1 W will do."""
    from scipy.optimize import brentq   # calibration only (once per t_delay, t_rise)

    def excess(t_lag: float) -> float:
        return rise_time(FUNCTIONS, _params(1.0, t_delay_s, t_rise_s, t_lag, 1.0), 0.5,
                         0.5 + DESIGN_STEP, t_delay_s + 2 * t_rise_s) - t_rise_s

    return brentq(excess, 1e-4 * t_rise_s, t_rise_s / math.log(9.0), xtol=1e-9 * t_rise_s)
