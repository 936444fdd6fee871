"""Detailed DER models for time-domain runs (docs/method.md#detailed-der-models), pure: parameters /
state / inputs.

- :mod:`~adnmesh.dermodels.wt`: wind turbine, IEC 61400-27-1 Type 4B-like (ramp-rate limited
  reference, rate-limited first-order lag; steps up slower than steps down);
- :mod:`~adnmesh.dermodels.chp`: CHP plant, two lags in series with a rate limit (S-shaped,
  slow);
- :mod:`~adnmesh.dermodels.pv`: PV plant, processing delay and a first-order lag with limits;
- :mod:`~adnmesh.dermodels.pt1`: the reference model (docs/method.md#reference-model), a first-order
  lag behind a dead time, exact between setpoint changes.

Every model has a frozen parameter dataclass (plain numbers: W, s, W/s), the shared
:class:`~adnmesh.dermodels.state.DerState`, and the reference model's two functions
``set_point(params, state, t_ns, setpoint_w)`` and ``infeed_at(params, state, t_ns) -> W``, so the
DER agent can switch models by config. This module dispatches them on the parameters' type, and
:func:`default_params` derives each model's defaults from what the config says of a DER (type,
P_inst, T_delay, T_rise): the same reaction time and the same 10-90 % rise time for a setpoint
step of 10 % of P_inst (from 50 % to 60 %). The solutions are exact between events (closed-form
pieces, :mod:`~adnmesh.dermodels.pieces`) and do not depend on when the infeed is asked for.
"""

from __future__ import annotations

import dataclasses

from adnmesh.dermodels import chp, pt1, pv, wt
from adnmesh.dermodels.chp import CHPParams
from adnmesh.dermodels.pv import PVParams
from adnmesh.dermodels.risetime import ModelFunctions
from adnmesh.dermodels.state import DerState
from adnmesh.dermodels.wt import WTParams

__all__ = ["MODULES", "MODULE_OF_PARAMS", "CHPParams", "DerState", "PVParams", "WTParams",
           "default_params", "params_with", "functions", "steady_state", "set_point", "infeed_at",
           "reference_pt1"]

#: Model module of each DER type of the config: a hydro plant's governor and penstock are
#: modelled like a CHP's two stages (two lags in series with a rate limit), a generator of
#: another kind like a PV plant (a delay and a lag with limits) — docs/models.md#der-types.
MODULES = {"WT": wt, "CHP": chp, "PV": pv, "HYDRO": chp, "GEN": pv}
#: Model module of each detailed model's parameter type.
MODULE_OF_PARAMS = {WTParams: wt, CHPParams: chp, PVParams: pv}


def default_params(der_type: str, p_inst_w: float, t_delay_s: float, t_rise_s: float,
                   p_max_w: float | None = None):
    """Default parameters of the detailed model of a DER of type ``der_type`` (:data:`MODULES`).

    Reaction ``t_delay_s``; 10-90 % rise time ``t_rise_s`` for a setpoint step from 50 % to
    60 % of ``p_inst_w``; upper limit ``p_max_w`` (default ``p_inst_w``).
    """
    if der_type not in MODULES:
        raise ValueError(f"unknown DER type {der_type!r} (one of {', '.join(MODULES)})")
    return MODULES[der_type].default_params(p_inst_w, t_delay_s, t_rise_s, p_max_w)


def params_with(params, **overrides):
    """``params`` with some fields replaced (e.g. from a config's ``model:`` block); an unknown
    name is a ``ValueError`` naming the known ones."""
    names = [f.name for f in dataclasses.fields(params)]
    unknown = [k for k in overrides if k not in names]
    if unknown:
        raise ValueError(f"unknown {type(params).__name__} parameter {unknown[0]!r} "
                         f"(known: {', '.join(names)})")
    return dataclasses.replace(params, **overrides)


def functions(params) -> ModelFunctions:
    """The model functions that go with ``params`` (any model here, or the reference PT1)."""
    if type(params) in MODULE_OF_PARAMS:
        return MODULE_OF_PARAMS[type(params)].FUNCTIONS
    if isinstance(params, pt1.PT1DelayParams):
        return _PT1_FUNCTIONS
    raise TypeError(f"no DER model has parameters of type {type(params).__name__}")


def steady_state(params, p_w: float, t_ns: int = 0):
    """A state at rest at ``p_w`` (W) at ``t_ns``."""
    return functions(params).steady_state(params, p_w, t_ns)


def set_point(params, state, t_ns: int, setpoint_w: float) -> None:
    """Input: the setpoint becomes ``setpoint_w`` (W) at ``t_ns`` (time order)."""
    functions(params).set_point(params, state, t_ns, setpoint_w)


def infeed_at(params, state, t_ns: int) -> float:
    """Infeed at ``t_ns`` (not before an earlier call), W."""
    return functions(params).infeed_at(params, state, t_ns)


def reference_pt1(p_inst_w: float, t_delay_s: float, t_lag_s: float):
    """Parameters of the reference model (:mod:`adnmesh.dermodels.pt1`)."""
    return pt1.PT1DelayParams(p_inst_w, int(round(t_delay_s * 1e9)), t_lag_s)


_PT1_FUNCTIONS = ModelFunctions(lambda params, p_w, t_ns=0: pt1.PT1DelayState.steady(p_w, t_ns),
                                pt1.set_point, pt1.infeed_at)
