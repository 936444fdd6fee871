"""Whether a DER model's output is held back by one of its limits at an instant.

``held_at(params, state, t_ns)`` is +1 while a limit keeps the output from rising as its
dynamics would (a rate or ramp limit on the way up), -1 while one keeps it from falling, 0
otherwise; the absolute limits act on the setpoint and are the DER controller's to report. The
state is not changed. Used for the CPFC's anti-windup (:mod:`adnmesh.control.der_controller`),
which takes the infeed and the flag of a sample at once (:func:`infeed_and_held`).
"""

from __future__ import annotations

import math

from adnmesh.dermodels import MODULE_OF_PARAMS, chp, infeed_at, wt
from adnmesh.dermodels.state import DerState, evaluate_core

__all__ = ["held_at", "infeed_and_held"]


def _core_at(module, params, state: DerState, t_ns: int) -> tuple[tuple, float]:
    """The model's core and the input its dynamics see at ``t_ns`` (no change to ``state``)."""
    core, u, t = state.core, state.u_w, state.t_ns
    for t_change, u_next in state.queue:
        if t_change > t_ns:
            break
        if t_change > t:
            core = module.advance(params, core, u, (t_change - t) * 1e-9)
            t = t_change
        u = min(max(u_next, params.p_min_w), params.p_max_w)
    if t_ns > t:
        core = module.advance(params, core, u, (t_ns - t) * 1e-9)
    return core, u


def _sign(wanted: float, rate_up: float, rate_down: float) -> int:
    if wanted > rate_up * (1 + 1e-9):
        return 1
    if wanted < -rate_down * (1 + 1e-9):
        return -1
    return 0


def held_at(params, state, t_ns: int) -> int:
    """+1 / -1 / 0 (see the module docstring)."""
    module = MODULE_OF_PARAMS.get(type(params))
    if module is None:
        return 0                                         # the reference PT1 has no such limit
    return _held(params, *_core_at(module, params, state, t_ns))


def infeed_and_held(params, state, t_ns: int) -> tuple[float, int]:
    """``(infeed_at(params, state, t_ns), held_at(params, state, t_ns))`` (W and +1 / -1 / 0),
    the same numbers as those two calls in a row and the same change to ``state``, from one
    evaluation of the model's core (the two calls evaluate it twice)."""
    module = MODULE_OF_PARAMS.get(type(params))
    if module is None:
        return infeed_at(params, state, t_ns), 0
    core = evaluate_core(module.advance, params, state, t_ns)
    return module.output(params, core), _held(params, core, state.u_w)


def _held(params, core: tuple, u: float) -> int:
    """+1 / -1 / 0 of a detailed model with ``core`` at its limited setpoint ``u``."""
    if type(params) is wt.WTParams:
        r, x = core
        ramp = 1 if r < u - 1e-9 * params.p_inst_w else -1 if r > u + 1e-9 * params.p_inst_w \
            and params.ramp_down_w_per_s != math.inf else 0
        return ramp or _sign((r - x) / params.t_lag_s, params.rate_up_w_per_s,
                             params.rate_down_w_per_s)
    if type(params) is chp.CHPParams:
        m, _ = core
        return _sign((u - m) / params.t_fuel_s, params.rate_up_w_per_s,
                     params.rate_down_w_per_s)
    (x,) = core
    return _sign((u - x) / params.t_lag_s, params.rate_up_w_per_s, params.rate_down_w_per_s)
