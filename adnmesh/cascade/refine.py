"""Tuning an upper entry on the exact cascade where its equivalent models misled it.

A back-off only scales both gains down, so it keeps the equivalent models' ratio ``K_I/K_P``
even where the exact cascade wants another one (an ADN whose closed loop has a long slow tail,
which a first-order model does not have, wants less integral action). :func:`refine` searches
the ratio: for each ratio it takes the largest gains that still meet both constraints on the
exact cascade (feasibility is an interval ``0 < K_P <= K_P,max`` along a ray: it is found by
growing or shrinking, then bisecting in ``log K_P``), and it moves the ratio by a factor while
that lowers the rise time, halving the factor (in log) when neither direction does, down to
:data:`RATIO_TOLERANCE`. The start is the backed-off pair, so the result is never slower than
it and always certified: every pair it returns was evaluated by
:func:`~adnmesh.cascade.certificate.cascade_figures` and met both constraints.
"""
from __future__ import annotations

import math

from adnmesh.cascade.certificate import CascadeFigures, cascade_figures
from adnmesh.cascade.structure import Cascade

__all__ = ["refine", "RATIO_TOLERANCE"]

#: the search stops when the ratio factor is below this
RATIO_TOLERANCE = 1.03
_BISECTIONS = 10
_FIRST_FACTOR = 2.0


def _meets(fig: CascadeFigures, constraints) -> bool:
    return fig.problem(constraints.disk_margin_min, constraints.overshoot_max_pct) is None


def _largest(cascade: Cascade, ratio: float, kp0: float, constraints):
    """The largest feasible ``K_P`` on the ray ``K_I = ratio K_P`` near ``kp0``, with its
    figures: ``(kp, figures)`` or ``(None, None)``."""
    band = constraints.settling_band_pct
    check = lambda kp: cascade_figures(cascade, kp, kp * ratio, band)  # noqa: E731
    fig = check(kp0)
    lo = hi = None
    if _meets(fig, constraints):
        lo, lo_fig = kp0, fig
        for _ in range(12):
            up = lo * 1.5
            f = check(up)
            if not _meets(f, constraints):
                hi = up
                break
            lo, lo_fig = up, f
        else:
            return lo, lo_fig
    else:
        hi = kp0
        for _ in range(12):
            down = hi / 1.5
            f = check(down)
            if _meets(f, constraints):
                lo, lo_fig = down, f
                break
            hi = down
        else:
            return None, None
    for _ in range(_BISECTIONS):
        mid = math.sqrt(lo * hi)
        f = check(mid)
        if _meets(f, constraints):
            lo, lo_fig = mid, f
        else:
            hi = mid
    return lo, lo_fig


def refine(cascade: Cascade, kp: float, ki: float, figures: CascadeFigures, constraints):
    """From a certified pair ``(kp, ki)`` with its ``figures``, the certified pair of lowest
    rise time the ratio search finds: ``(kp, ki, figures)``."""
    best = (figures.rise_time_s, kp, ki, figures)
    start = _largest(cascade, ki / kp, kp, constraints)
    if start[0] is not None and start[1].rise_time_s < best[0]:
        best = (start[1].rise_time_s, start[0], start[0] * ki / kp, start[1])
    factor = _FIRST_FACTOR
    while factor > RATIO_TOLERANCE:
        ratio = best[2] / best[1]
        moved = False
        for r in (ratio / factor, ratio * factor):
            found, fig = _largest(cascade, r, best[1], constraints)
            if found is not None and fig.rise_time_s < best[0]:
                best = (fig.rise_time_s, found, found * r, fig)
                moved = True
                break
        if not moved:
            factor = math.sqrt(factor)
    return best[1], best[2], best[3]
