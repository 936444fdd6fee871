"""Whether a DER model's output is held back by one of its limits at an instant.

``held_at(params, state, t_ns)`` is +1 while a limit keeps the output from rising as its
dynamics would (a rate or ramp limit on the way up), -1 while one keeps it from falling, 0
otherwise; the absolute limits act on the setpoint and are the DER controller's to report. The
state is not changed. Used for the CPFC's anti-windup (:mod:`adnmesh.control.der_controller`).
"""

from __future__ import annotations

from adnmesh.dermodels import chp, pv, wt
from adnmesh.dermodels.state import DerState

__all__ = ["held_at"]


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
    if isinstance(params, wt.WTParams):
        (r, x), u = _core_at(wt, params, state, t_ns)
        ramp = 1 if r < u - 1e-9 * params.p_inst_w else -1 if r > u + 1e-9 * params.p_inst_w \
            and params.ramp_down_w_per_s != float("inf") else 0
        return ramp or _sign((r - x) / params.t_lag_s, params.rate_up_w_per_s,
                             params.rate_down_w_per_s)
    if isinstance(params, chp.CHPParams):
        (m, _), u = _core_at(chp, params, state, t_ns)
        return _sign((u - m) / params.t_fuel_s, params.rate_up_w_per_s,
                     params.rate_down_w_per_s)
    if isinstance(params, pv.PVParams):
        (x,), u = _core_at(pv, params, state, t_ns)
        return _sign((u - x) / params.t_lag_s, params.rate_up_w_per_s, params.rate_down_w_per_s)
    return 0                                             # the reference PT1 has no such limit
