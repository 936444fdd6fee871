"""The uncertainty set of a robust table as a box of plants (docs/tuning.md#robust-tables).

A config's ``constraints.robust`` (:class:`adnmesh.config.RobustSet`) names actuator structures
and, per DER type, an interval of the time-constant factor ``b`` and one of added dead time.
Over a tuning problem's actuator groups (each of one type) that is, per structure, a box
``[0, 1]^D``: one coordinate per type and per interval that is not a single point. Coordinate
``x`` maps to ``b = b_lo (b_hi / b_lo)^x`` (geometric, as the model-uncertainty scan) and to
``delay = lo + x (hi - lo)`` (s), on a grid of :data:`DELAY_GRID_S` (the interval's ends
rounded outwards: the box holds the configured interval); a group's dead time never goes
below 0. Every DER of a type shares its type's point; types move independently.

Why the grid: a step response is simulated with a step that divides every delay of the loop
when they have a common unit (:func:`adnmesh.loopmodel.step_response.choose_steps`); added
dead times of any value would leave none, every candidate its own step and every simulation
its own discretisation (the robust SimBench table took 685 s instead of 240 s).

:class:`UncertaintyBox` turns points into actuator tuples (pure, no numerics beyond that);
:mod:`adnmesh.tuning.robust_check` finds the worst member of the box for given loops.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from adnmesh.loopmodel.plant import Actuator

__all__ = ["Member", "UncertaintyBox", "Coordinate", "DELAY_GRID_S"]

#: added dead times are multiples of this, s
DELAY_GRID_S = 0.01


def _on_grid(value_s: float) -> float:
    return round(round(value_s / DELAY_GRID_S) * DELAY_GRID_S, 9)


@dataclass(frozen=True)
class Coordinate:
    """One dimension of the box: a DER type's ``lag`` factor or added ``delay``."""

    der_type: str
    kind: str                     # "lag" or "delay"
    low: float                    # b_lo, or the lowest added dead time in s
    high: float

    def value(self, x: float) -> float:
        """The factor ``b`` (lag) or the added dead time in s (delay) at ``x`` in [0, 1]."""
        if self.kind == "lag":
            return self.low * (self.high / self.low) ** x
        return _on_grid(self.low + x * (self.high - self.low))


@dataclass(frozen=True)
class Member:
    """One plant of the set: a structure and a point ``x`` (one value per coordinate, 0..1)."""

    model: str
    x: tuple[float, ...]


class UncertaintyBox:
    """The uncertainty set over a problem's actuator groups.

    Parameters
    ----------
    robust : adnmesh.config.RobustSet
    actuators : tuple of Actuator
        The problem's nominal groups (reference PT1).
    group_types : sequence of str
        The DER type of each group.
    """

    def __init__(self, robust, actuators: tuple[Actuator, ...], group_types):
        self.actuators = tuple(actuators)
        self.group_types = tuple(group_types)
        self.models = tuple(robust.models)
        coords = []
        for t in dict.fromkeys(self.group_types):
            u = robust.of_type(t)
            if u.lag_scale[0] < u.lag_scale[1]:
                coords.append(Coordinate(t, "lag", *map(float, u.lag_scale)))
            if u.delay_add_s[0] < u.delay_add_s[1]:
                low = math.floor(u.delay_add_s[0] / DELAY_GRID_S + 1e-9) * DELAY_GRID_S
                high = math.ceil(u.delay_add_s[1] / DELAY_GRID_S - 1e-9) * DELAY_GRID_S
                coords.append(Coordinate(t, "delay", round(low, 9), round(high, 9)))
        self.coordinates = tuple(coords)
        # the fixed values of the types' one-point intervals
        self._fixed = {t: robust.of_type(t) for t in dict.fromkeys(self.group_types)}

    @property
    def dimension(self) -> int:
        return len(self.coordinates)

    def _scales(self, x) -> tuple[dict, dict]:
        lag = {t: float(u.lag_scale[0]) for t, u in self._fixed.items()}
        delay = {t: float(u.delay_add_s[0]) for t, u in self._fixed.items()}
        for c, xi in zip(self.coordinates, x):
            (lag if c.kind == "lag" else delay)[c.der_type] = c.value(float(xi))
        return lag, delay

    def actuators_of(self, member: Member) -> tuple[Actuator, ...]:
        """The groups' actuators of ``member``: structure, time constant times the type's b,
        dead time plus the type's addition (at least 0)."""
        lag, delay = self._scales(member.x)
        return tuple(Actuator(max(0.0, a.t_delay_s + delay[t]), a.t_lag_s * lag[t], member.model)
                     for a, t in zip(self.actuators, self.group_types))

    def describe(self, member: Member, types=None) -> str:
        """``pt2, CHP b 1.6, CHP dead time +10.2 s``: the member in words (of the DER types
        ``types`` only, if given: those a loop has)."""
        lag, delay = self._scales(member.x)
        parts = [member.model]
        for t in dict.fromkeys(self.group_types):
            if types is not None and t not in types:
                continue
            u = self._fixed[t]
            if u.lag_scale != (1.0, 1.0):
                parts.append(f"{t} b {lag[t]:.4g}")
            if u.delay_add_s != (0.0, 0.0):
                parts.append(f"{t} dead time {delay[t]:+.4g} s")
        return ", ".join(parts)

    def vertices(self) -> list[Member]:
        """Every corner of the box, per structure (``2^D`` each)."""
        corners = list(itertools.product((0.0, 1.0), repeat=self.dimension))
        return [Member(m, c) for m in self.models for c in corners]

    def centres(self) -> list[Member]:
        """The box's centre, per structure."""
        return [Member(m, (0.5,) * self.dimension) for m in self.models]

    def design_members(self) -> list[Member]:
        """The members the searches check besides the reference model: per structure the
        slowest corner (every lag and dead time at its top) and the corner of fast lags with
        long dead times (the RHPZ loops lose stability as their actuators get faster). The
        certificate (:func:`adnmesh.tuning.robust_check.worst_members`) covers the rest."""
        slow = tuple(1.0 for _ in self.coordinates)
        fast = tuple(0.0 if c.kind == "lag" else 1.0 for c in self.coordinates)
        out = []
        for m in self.models:
            for x in dict.fromkeys((slow, fast)):
                out.append(Member(m, x))
        return out
