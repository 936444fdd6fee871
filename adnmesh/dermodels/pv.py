"""PV plant: a processing delay, then a first-order lag with absolute and rate limits
(docs/method.md#detailed-der-models).

    setpoint --(dead time t_delay_s: inverter processing)--> limit to [p_min_w, p_max_w]
             --> T dP/dt = u - P,  -rate_down <= dP/dt <= rate_up  --> infeed P

The inverter's power controller is fast and close to first order; what distinguishes the plant
from the reference model is the processing delay and that it cannot exceed the power the sun
gives (``p_max_w``, e.g. the study case's available power) nor go below ``p_min_w``. The rate
limits (default none) model a ramp-rate setting of the inverter. The solution is exact
(:mod:`adnmesh.dermodels.pieces`). With the defaults of :func:`default_params` and
``p_max_w = p_inst_w`` the PV model is the reference PT1 with limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from adnmesh.dermodels.pieces import rate_limited_lag_end
from adnmesh.dermodels.risetime import ModelFunctions
from adnmesh.dermodels.state import DeadTime, DerState, infeed_function, set_point

__all__ = ["PVParams", "default_params", "steady_state", "set_point", "infeed_at", "advance",
           "output"]


@dataclass(frozen=True)
class PVParams(DeadTime):
    """Parameters of the PV model (W, s, W/s).

    Parameters
    ----------
    p_inst_w : float
        Installed power, W.
    t_delay_s : float
        Processing delay (dead time), s.
    t_lag_s : float
        Time constant of the power controller's lag, s.
    rate_up_w_per_s, rate_down_w_per_s : float
        Limits of the infeed's rate of change, W/s (``math.inf``: none).
    p_min_w, p_max_w : float
        Absolute limits of the infeed, W (``p_max_w``: available power).
    """

    p_inst_w: float
    t_delay_s: float
    t_lag_s: float
    rate_up_w_per_s: float = math.inf
    rate_down_w_per_s: float = math.inf
    p_min_w: float = 0.0
    p_max_w: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.p_max_w):
            object.__setattr__(self, "p_max_w", float(self.p_inst_w))
        _check(self)


def _check(p) -> None:
    if not (p.p_inst_w > 0 and p.t_delay_s >= 0 and p.t_lag_s > 0
            and p.rate_up_w_per_s > 0 and p.rate_down_w_per_s > 0
            and 0 <= p.p_min_w <= p.p_max_w):
        raise ValueError(f"invalid PV model parameters: {p}")


def default_params(p_inst_w: float, t_delay_s: float, t_rise_s: float,
                   p_max_w: float | None = None) -> PVParams:
    """Defaults whose 10-90 % rise time is ``t_rise_s`` (``T = t_rise / ln 9``, exact for any
    step inside the limits) and whose reaction is the processing delay ``t_delay_s``."""
    return PVParams(p_inst_w, t_delay_s, t_rise_s / math.log(9.0),
                    p_max_w=p_inst_w if p_max_w is None else p_max_w)


def steady_state(params: PVParams, p_w: float, t_ns: int = 0) -> DerState:
    """At rest at ``p_w`` (limited) at ``t_ns``."""
    p = min(max(float(p_w), params.p_min_w), params.p_max_w)
    return DerState(t_ns, (p,), p, t_last_ns=t_ns)


def advance(params: PVParams, core: tuple, u_w: float, dt_s: float) -> tuple:
    """Exact ``core`` after ``dt_s`` with the lag's input at ``u_w``."""
    (x,) = core
    return (rate_limited_lag_end(x, u_w, 0.0, params.t_lag_s, params.rate_up_w_per_s,
                                 params.rate_down_w_per_s, dt_s),)


def output(params: PVParams, core: tuple) -> float:
    """Infeed, W."""
    return core[0]


infeed_at = infeed_function(advance, output)


FUNCTIONS = ModelFunctions(steady_state, set_point, infeed_at)
