"""The upper loop's certificate: its figures on the exact cascade, the verdict against the
design constraints, and the back-off that restores them.

The figures are those of a table entry (disk margin, overshoot, rise and settling times), but
of the *nested* loop: the upper PI over the ADNs' exact closed loops with every delay
(:mod:`adnmesh.cascade.nested_loop`, :mod:`adnmesh.cascade.nested_step`). The step response is
simulated until it has stayed within 0.5 % of its final value for the last quarter of the
horizon, and at least for ``20 / omega_c`` and four times the slowest lag plus every delay;
a response not settled by :data:`~adnmesh.cascade.nested_step.MAX_HORIZON_S` (or
:data:`~adnmesh.cascade.nested_step.MAX_STEPS` steps) reports infinite settling times.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from adnmesh.cascade.nested_loop import upper_loop
from adnmesh.cascade.nested_step import choose_step, simulate_until_settled
from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.step_figures import step_figures

__all__ = ["CascadeFigures", "cascade_figures", "back_off", "settled_horizon", "BACK_OFF_STEP"]

#: factor on both upper gains per back-off step
BACK_OFF_STEP = 0.97


@dataclass(frozen=True)
class CascadeFigures:
    """Figures of the upper loop on the exact cascade (NaN where not applicable).

    Attributes
    ----------
    stable : bool
        Lower loops and upper loop stable.
    lower_stable : bool
    resolved : bool
        The upper loop's winding grid met its refinement rule (if not: no verdict, taken as
        failing).
    disk_margin : float
        Balanced disk margin alpha of the upper loop, 0 if unstable.
    disk_omega : float
        rad/s.
    overshoot_pct, rise_time_s, settling_time_s, settling_time_2pct_s : float
        Step figures of the nested loop (upper reference -> sum of the ADNs' infeed), %, s.
    step_s : float
        Simulation step, s.
    """

    stable: bool
    lower_stable: bool
    resolved: bool
    disk_margin: float
    disk_omega: float
    overshoot_pct: float
    rise_time_s: float
    settling_time_s: float
    settling_time_2pct_s: float
    step_s: float

    def problem(self, disk_margin_min: float, overshoot_max_pct: float) -> str | None:
        """Why the loop fails the constraints (one line), or None if it meets them."""
        if not self.lower_stable:
            return "a lower ADN's own loop is unstable"
        if not self.resolved:
            return "the upper loop's stability could not be resolved (treated as unstable)"
        if not self.stable:
            return "the upper loop is unstable"
        if self.disk_margin < disk_margin_min:
            return f"disk margin {self.disk_margin:.3f} < {disk_margin_min:g}"
        if not self.overshoot_pct < overshoot_max_pct:
            return f"overshoot {self.overshoot_pct:.3f} % >= {overshoot_max_pct:g} %"
        return None

def settled_horizon(cascade: Cascade, bandwidth_rad_s: float) -> float:
    """The shortest horizon simulated, s: ``20 / bandwidth`` and 4 x (slowest lag + every
    delay of the cascade)."""
    slow = max(float(a.time_constants_s.max()) for adn in cascade.adns
               for a in adn.plant.actuators)
    floor = 4.0 * (slow + sum(cascade.delays_s))
    if math.isfinite(bandwidth_rad_s) and bandwidth_rad_s > 0:
        floor = max(floor, 20.0 / bandwidth_rad_s)
    return floor


def _settled_step(cascade: Cascade, upper, bandwidth_rad_s: float, band_pct: float):
    """Simulate until the response has settled; its figures and the step."""
    h = choose_step(cascade, bandwidth_rad_s)
    run = simulate_until_settled(cascade, upper, settled_horizon(cascade, bandwidth_rad_s), h)
    return step_figures(run.t_s, run.y, band_pct), h


def cascade_figures(cascade: Cascade, kp: float, ki: float,
                    band_pct: float = 5.0) -> CascadeFigures:
    """Figures of the cascade under the upper PI ``(kp, ki)`` (1/W, 1/(W s))."""
    loop = upper_loop(cascade, kp, ki)
    nan = float("nan")
    if not loop.stable:
        return CascadeFigures(False, loop.lower_stable, loop.resolved, 0.0, nan, nan, nan, nan,
                              nan, nan)
    fig, h = _settled_step(cascade, (kp, ki), loop.disk_omega, band_pct)
    return CascadeFigures(True, True, True, loop.disk_margin, loop.disk_omega, fig.overshoot_pct,
                          fig.rise_time_s, fig.settling_time_s, fig.settling_time_2pct_s, h)


def back_off(cascade: Cascade, kp: float, ki: float, disk_margin_min: float,
             overshoot_max_pct: float, band_pct: float = 5.0, most: int = 150):
    """The largest ``BACK_OFF_STEP ** n`` (n <= ``most``) by which both upper gains must be
    scaled for the cascade to meet the constraints: ``(factor, figures)``; factor is None
    (figures of the last try) if none does.

    The search bisects on ``n`` between 0 (the gains as they are) and ``most``: about eight
    cascade evaluations instead of up to ``most`` (a strong back-off of a CHP-dominated ADN
    needs n of 50-80). It takes the margins to fall as the gains grow; the factor it returns
    meets the constraints in any case, and the one a step larger does not."""
    def meets(n: int):
        fig = cascade_figures(cascade, kp * BACK_OFF_STEP ** n, ki * BACK_OFF_STEP ** n,
                              band_pct)
        return fig.problem(disk_margin_min, overshoot_max_pct) is None, fig

    ok, fig = meets(0)
    if ok:
        return 1.0, fig
    if not fig.lower_stable:            # no factor on the upper gains helps a lower loop
        return None, fig
    ok, last = meets(most)
    if not ok:
        return None, last
    lo, hi = 0, most                     # lo fails, hi meets
    while hi - lo > 1:
        mid = (lo + hi) // 2
        ok, found = meets(mid)
        if ok:
            hi, last = mid, found
        else:
            lo = mid
    return BACK_OFF_STEP ** hi, last
