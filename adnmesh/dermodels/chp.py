"""CHP plant: slow, second order with a rate limit, ~1 s reaction time
(docs/method.md#detailed-der-models).

    setpoint --(dead time t_delay_s)--> limit to [p_min_w, p_max_w]
             --> T1 dm/dt = u - m,  dm/dt in [-rate_down, rate_up]     (fuel / mechanical power m)
             --> T2 dP/dt = m - P                                      (electrical infeed P)

Two lags in series: the response to a step starts with zero slope (an S-shaped rise, unlike any
first-order lag) and its rate limit on the fuel stage turns large steps into ramps. Absolute
limits act on the input, so neither stage winds up beyond them.

Exact solution: the rate-limited first stage is a chain of ramp and exponential pieces
(:func:`~adnmesh.dermodels.pieces.rate_limited_lag`), through which the second stage is solved
in closed form (:func:`~adnmesh.dermodels.pieces.lag_of_pieces`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from adnmesh.dermodels.pieces import end_value, lag_of_pieces, rate_limited_lag
from adnmesh.dermodels.risetime import ModelFunctions, rise_time
from adnmesh.dermodels.state import DeadTime, DerState, infeed_function, set_point

__all__ = ["CHPParams", "default_params", "steady_state", "set_point", "infeed_at", "advance",
           "output", "DESIGN_STEP", "LAG_RATIO", "RATE_STEP"]

#: Step the defaults' rise time is calibrated on, fraction of P_inst (50 % -> 60 %).
DESIGN_STEP = 0.10
#: Time constant of the electrical stage over the fuel stage's (1: two equal lags, the most
#: S-shaped second-order response that does not oscillate).
LAG_RATIO = 1.0
#: The fuel stage's rate limit is reached by steps larger than this fraction of P_inst.
RATE_STEP = 0.15


@dataclass(frozen=True)
class CHPParams(DeadTime):
    """Parameters of the CHP model (W, s, W/s).

    Parameters
    ----------
    p_inst_w : float
        Installed power, W.
    t_delay_s : float
        Dead time (reaction time), s.
    t_fuel_s, t_el_s : float
        Time constants of the fuel/mechanical stage and of the electrical stage, s.
    rate_up_w_per_s, rate_down_w_per_s : float
        Rate limits of the fuel stage, W/s (``math.inf``: none).
    p_min_w, p_max_w : float
        Absolute limits, W (default 0 and ``p_inst_w``).
    """

    p_inst_w: float
    t_delay_s: float
    t_fuel_s: float
    t_el_s: float
    rate_up_w_per_s: float = math.inf
    rate_down_w_per_s: float = math.inf
    p_min_w: float = 0.0
    p_max_w: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.p_max_w):
            object.__setattr__(self, "p_max_w", float(self.p_inst_w))
        if not (self.p_inst_w > 0 and self.t_delay_s >= 0 and self.t_fuel_s > 0
                and self.t_el_s > 0 and self.rate_up_w_per_s > 0
                and self.rate_down_w_per_s > 0 and 0 <= self.p_min_w <= self.p_max_w):
            raise ValueError(f"invalid CHP model parameters: {self}")


def steady_state(params: CHPParams, p_w: float, t_ns: int = 0) -> DerState:
    """At rest at ``p_w`` (limited) at ``t_ns``."""
    p = min(max(float(p_w), params.p_min_w), params.p_max_w)
    return DerState(t_ns, (p, p), p, t_last_ns=t_ns)


def advance(params: CHPParams, core: tuple, u_w: float, dt_s: float) -> tuple:
    """Exact ``(fuel stage, infeed)`` after ``dt_s`` with the limited setpoint ``u_w``."""
    m, p = core
    pieces = rate_limited_lag(m, u_w, 0.0, params.t_fuel_s, params.rate_up_w_per_s,
                              params.rate_down_w_per_s, dt_s)
    return (end_value(pieces, m), lag_of_pieces(p, pieces, params.t_el_s))


def output(params: CHPParams, core: tuple) -> float:
    """Infeed, W."""
    return core[1]


infeed_at = infeed_function(advance, output)


FUNCTIONS = ModelFunctions(steady_state, set_point, infeed_at)


def default_params(p_inst_w: float, t_delay_s: float, t_rise_s: float,
                   p_max_w: float | None = None) -> CHPParams:
    """Defaults with reaction ``t_delay_s`` and 10-90 % rise time ``t_rise_s`` for a step of
    the setpoint from 50 % to 60 % of ``p_inst_w``.

    The electrical stage's time constant is :data:`LAG_RATIO` times the fuel stage's; their
    linear rise time is ``T1 · rho`` with ``rho`` the rise time of the unit pair (3.358 for two
    equal lags), so
    ``T1 = t_rise / rho``; the rate limit (``0.15 P_inst / T1``) is reached by steps above
    :data:`RATE_STEP` of ``P_inst`` and so leaves the design step linear.
    """
    t_fuel = t_rise_s / _unit_rise_time()
    rate = RATE_STEP * p_inst_w / t_fuel
    return CHPParams(p_inst_w, t_delay_s, t_fuel, LAG_RATIO * t_fuel, rate, rate,
                     p_max_w=p_inst_w if p_max_w is None else p_max_w)


@lru_cache(maxsize=1)
def _unit_rise_time() -> float:
    """Rise time of the two stages with ``T1 = 1 s``, ``T2 = LAG_RATIO s``, no rate limit."""
    return rise_time(FUNCTIONS, CHPParams(1.0, 0.0, 1.0, LAG_RATIO), 0.5, 0.5 + DESIGN_STEP,
                     10.0)
