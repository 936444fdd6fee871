"""State and inputs shared by the detailed DER models: dead time, limits, event commits.

A model is its parameters (a frozen dataclass with ``t_delay_s``, ``p_min_w``, ``p_max_w``,
derived from :class:`DeadTime`), a *core* (a tuple of its internal values, W) and two pure
functions of the model's module::

    advance(params, core, u_w, dt_s) -> core      # exact, input u_w constant over dt_s
    output(params, core) -> p_w

:class:`DerState` holds the core at ``t_ns``, the input the dynamics currently see and the
setpoints still inside the dead time. Every model's ``set_point`` is :func:`set_point`, its
``infeed_at`` is :func:`infeed_function` of its ``advance`` and ``output``; both have the shape
of the reference model's (:mod:`adnmesh.dermodels.pt1`): a setpoint given at ``t`` reaches the
dynamics at ``t + t_delay`` (limited to ``[p_min_w, p_max_w]``), and ``infeed_at(t)`` is exact.

The core is committed only at the instants where the dynamics' input changes; the infeed at any
other instant is computed from the last commit without changing the state. So the value at an
instant depends only on the setpoints, never on when or how often the infeed was asked for —
bit for bit, whatever the spacing of the calls.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import cached_property

__all__ = ["DerState", "DeadTime", "set_point", "evaluate", "infeed_function"]


@dataclass
class DerState:
    """Evolving state of a detailed DER model.

    Attributes
    ----------
    t_ns : int
        Time of ``core``, ns (the last change of the dynamics' input).
    core : tuple of float
        The model's internal values at ``t_ns``, W.
    u_w : float
        Setpoint the dynamics see from ``t_ns`` on (after the dead time, limited), W.
    queue : deque of (int, float)
        Setpoints inside the dead time: (time they reach the dynamics, ns; value, W).
    t_last_ns : int
        Latest instant asked for; time does not go back.
    """

    t_ns: int
    core: tuple
    u_w: float
    queue: deque = field(default_factory=deque)
    t_last_ns: int = 0


class DeadTime:
    """Base of the models' parameter dataclasses: their dead time ``t_delay_s`` in ns."""

    @cached_property
    def t_delay_ns(self) -> int:
        """Dead time, ns."""
        return int(round(self.t_delay_s * 1e9))


def set_point(params, state: DerState, t_ns: int, setpoint_w: float) -> None:
    """Input: the setpoint becomes ``setpoint_w`` (W) at ``t_ns`` (in time order), seen by the
    dynamics ``t_delay_s`` later. Every model's ``set_point``."""
    if t_ns < state.t_last_ns:
        raise ValueError(f"set-point at {t_ns} ns is before {state.t_last_ns} ns")
    state.queue.append((t_ns + params.t_delay_ns, float(setpoint_w)))


def evaluate(advance, output, params, state: DerState, t_ns: int) -> float:
    """Infeed at ``t_ns`` (>= every earlier call), W, with the model's ``advance`` and
    ``output`` (see the module docstring)."""
    return output(params, evaluate_core(advance, params, state, t_ns))


def evaluate_core(advance, params, state: DerState, t_ns: int) -> tuple:
    """The model's core at ``t_ns`` (>= every earlier call) with its ``advance``: what
    :func:`evaluate` gives ``output``; the setpoint changes due by then are taken into
    ``state`` (its core at the last one)."""
    if t_ns < state.t_last_ns:
        raise ValueError(f"cannot go back in time ({t_ns} < {state.t_last_ns} ns)")
    state.t_last_ns = t_ns
    queue = state.queue
    while queue and queue[0][0] <= t_ns:
        t_change, u_next = queue.popleft()
        if t_change > state.t_ns:
            state.core = advance(params, state.core, state.u_w, (t_change - state.t_ns) * 1e-9)
            state.t_ns = t_change
        state.u_w = min(max(u_next, params.p_min_w), params.p_max_w)
    core = state.core
    if t_ns > state.t_ns:
        core = advance(params, core, state.u_w, (t_ns - state.t_ns) * 1e-9)
    return core


def infeed_function(advance, output):
    """A model's ``infeed_at(params, state, t_ns) -> W``: :func:`evaluate` with the model's
    ``advance`` and ``output``."""
    def infeed_at(params, state: DerState, t_ns: int) -> float:
        """Infeed at ``t_ns`` (not before an earlier call), exact, W."""
        return evaluate(advance, output, params, state, t_ns)
    return infeed_at
