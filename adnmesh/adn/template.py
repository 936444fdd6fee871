"""Schedules and a scenario sized to what the actuators can deliver (pure).

Every actuator is scheduled at half of its infeed at the study case (``p_sched_w``), so that it
can move both ways: up to its study-case infeed (its available power) and down to 0. The
controllable range is the sum of the headroom: up ``sum(p_case - p_sched)``, down
``sum(p_sched)``.

The scenario (:func:`scenario_template`), 100 s between events so that the slowest default
dynamics (CHP, T_rise 24.6 s) settle inside each window:

- at 20 s a step of P_ref by ``+s`` and at 120 s back by ``-s``, ``s`` 40 % of the smaller of
  the two ranges, rounded down to 1, 2 or 5 times a power of ten (W);
- with two or more DER types, at 220 s the type with the most installed power becomes
  unavailable (its infeed returns to its schedule), and at 240 s and 340 s steps of ``+s2`` and
  ``-s2`` sized by the same rule to what is left;
- the run lasts until 100 s after the last step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Planned", "STEP_SHARE", "nice_floor", "schedule_w", "ranges_w",
           "scenario_template"]

#: the share of the smaller controllable range a template step takes
STEP_SHARE = 0.4
_GAP_S = 100.0


@dataclass(frozen=True)
class Planned:
    """A scenario: steps ``(t_s, delta_w)``, availability changes ``(t_s, ders)`` (unavailable
    from then on) and the duration, s."""

    steps: tuple[tuple[float, float], ...]
    unavailable: tuple[tuple[float, tuple[str, ...]], ...]
    duration_s: float
    dropped_type: str | None


def nice_floor(value: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``value`` (> 0)."""
    exponent = math.floor(math.log10(value))
    for mantissa in (5.0, 2.0, 1.0):
        candidate = mantissa * 10.0 ** exponent
        if candidate <= value * (1 + 1e-12):
            return candidate
    return 10.0 ** exponent


def schedule_w(p_case_w: float) -> float:
    """An actuator's schedule: half of its study-case infeed, to the watt, W."""
    return float(round(p_case_w / 2.0))


def ranges_w(ders) -> tuple[float, float]:
    """``(up, down)``: the sum of the headroom of ``ders`` (``(p_case_w, p_sched_w)`` pairs), W."""
    ders = list(ders)
    return (sum(max(c - s, 0.0) for c, s in ders), sum(max(s, 0.0) for _, s in ders))


def scenario_template(ders) -> Planned:
    """The scenario of the module docstring for ``ders``: ``(id, type, p_inst_w, p_case_w,
    p_sched_w)`` tuples."""
    ders = list(ders)
    up, down = ranges_w((c, s) for _, _, _, c, s in ders)
    step = nice_floor(STEP_SHARE * min(up, down))
    steps = [(20.0, step), (120.0, -step)]
    unavailable: list = []
    dropped = None
    power: dict[str, float] = {}
    for _, kind, p_inst, _, _ in ders:
        power[kind] = power.get(kind, 0.0) + p_inst
    if len(power) >= 2:
        dropped = max(power, key=lambda k: (power[k], k))
        left = [d for d in ders if d[1] != dropped]
        up2, down2 = ranges_w((c, s) for _, _, _, c, s in left)
        if min(up2, down2) > 0:
            step2 = nice_floor(STEP_SHARE * min(up2, down2))
            unavailable.append((220.0, tuple(d[0] for d in ders if d[1] == dropped)))
            steps += [(240.0, step2), (340.0, -step2)]
        else:
            dropped = None
    return Planned(tuple(steps), tuple(unavailable), steps[-1][0] + _GAP_S, dropped)
