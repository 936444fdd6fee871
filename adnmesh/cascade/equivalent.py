"""An ADN's equivalent reference model: the first-order lag plus dead time its closed loop
looks like from above.

What an ADN publishes to the level above, so that the upper controller can be tuned with the
DER machinery it already has: the lag ``T_eq`` and the dead time ``D_eq`` of the first-order
model with the same 10 % and 90 % times as the exact closed-loop step response ``T_i``
(offset of the ADN's reference -> its DERs' infeed, upper loop open):

    t10 = D_eq + T_eq ln(10/9),    t90 = D_eq + T_eq ln 10,
    so  T_eq = (t90 - t10) / ln 9,  D_eq = t10 - T_eq ln(10/9).

A loop that starts faster than a first-order lag would from its 10 % time (its PI's
proportional kick through a fast group: the fit's ``D_eq`` would fall below the loop's true
dead time, its shortest forward delay ``T_com + T_delay,g``) gets that dead time and the lag
with its 90 % time, ``T_eq = (t90 - D_eq) / ln 10``: what the upper loop's speed depends on.

The model is for tuning only: every upper entry is certified on the exact cascade
(:mod:`adnmesh.cascade.certificate`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adnmesh.cascade.lower_adn import LowerAdn
from adnmesh.cascade.nested_step import simulate_until_settled
from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.step_figures import step_figures

__all__ = ["Equivalent", "equivalent", "first_crossing"]


@dataclass(frozen=True)
class Equivalent:
    """The equivalent model of one ADN's closed loop.

    Attributes
    ----------
    delay_s : float
        Dead time D_eq, s.
    lag_s : float
        Time constant T_eq, s (its 10-90 % rise time is ``T_eq ln 9``).
    rise_time_s, overshoot_pct, settling_time_s : float
        The exact closed loop's own step figures, s, %, s.
    """

    delay_s: float
    lag_s: float
    rise_time_s: float
    overshoot_pct: float
    settling_time_s: float

    @property
    def t_rise_s(self) -> float:
        """The model's 10-90 % rise time ``T_eq ln 9``, s."""
        return self.lag_s * math.log(9.0)


def first_crossing(t_s: np.ndarray, y: np.ndarray, level: float) -> float:
    """First time ``y`` reaches ``level``, linearly interpolated, s (NaN if never)."""
    above = np.nonzero(y >= level)[0]
    if above.size == 0:
        return float("nan")
    i = int(above[0])
    if i == 0:
        return float(t_s[0])
    return float(t_s[i - 1] + (level - y[i - 1]) / (y[i] - y[i - 1]) * (t_s[i] - t_s[i - 1]))


def equivalent(adn: LowerAdn, band_pct: float = 5.0) -> Equivalent:
    """Fit the equivalent model to the ADN's exact closed-loop step response."""
    alone = Cascade((adn,), (1.0,), (0.0,), 0.0)
    slow = max(float(a.time_constants_s.max()) for a in adn.plant.actuators)
    horizon = 4.0 * (slow + sum(adn.delays_s)) + 20.0 / (adn.ki * float(adn.plant.total_gain_w))
    run = simulate_until_settled(alone, None, horizon)
    t10, t90 = first_crossing(run.t_s, run.y, 0.1), first_crossing(run.t_s, run.y, 0.9)
    if not (math.isfinite(t10) and math.isfinite(t90)):
        raise ValueError(f"ADN {adn.name}: its closed loop does not reach 90 % in "
                         f"{run.t_s[-1]:g} s")
    lag = max((t90 - t10) / math.log(9.0), 1e-6)
    delay = t10 - lag * math.log(10.0 / 9.0)
    dead = float(adn.plant.path_delays_s[adn.plant.gains_w > 0].min())
    if delay < dead:
        delay = dead
        lag = max((t90 - dead) / math.log(10.0), 1e-6)
    fig = step_figures(run.t_s, run.y, band_pct)
    return Equivalent(delay, lag, t90 - t10, fig.overshoot_pct, fig.settling_time_s)
