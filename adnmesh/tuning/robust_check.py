"""The worst member of the uncertainty set for given loops: the robust certificate
(docs/tuning.md#robust-tables).

For M loops (group gains, PI pairs) and a problem's :class:`~.robust_set.UncertaintyBox`, per
structure:

1. **corners and centre** of the box, each one batched evaluation of all M loops (certified
   disk margin; step response until it settles, exact delays);
2. **pattern search**: for every loop whose worst value there is within :data:`REFINE_DM` of
   the disk-margin limit (or above :data:`REFINE_OS` of the overshoot limit), a compass search
   from its worst point, for the lowest disk margin and for the highest overshoot separately:
   steps of 1/4, 1/8, ... :data:`FINEST` of the box along every coordinate of the DER types
   the loop has, moving while a step finds a worse member. The points lie on one dyadic
   lattice, so loops at the same point share each probe's evaluation (one batch per distinct
   probe).

Each member's figures are exact (the same evaluation as every table entry's); what is searched
is where in the box the worst member lies. A worst member in a region no compass step reaches
could be missed: the tests compare the certificate with dense sampling of the box.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.tuning.robust_set import Member

__all__ = ["WorstCase", "worst_members", "REFINE_DM", "REFINE_OS", "FIRST", "FINEST"]

#: a loop is refined when its lowest corner/centre disk margin is below the limit plus this
REFINE_DM = 0.05
#: ... or its highest overshoot above this fraction of the limit
REFINE_OS = 0.5
#: the compass search's first and last step, fractions of the box per coordinate
FIRST = 0.25
FINEST = 1.0 / 64
#: moves per step size, at most
MOVES = 8


@dataclass
class WorstCase:
    """Per loop (arrays of shape (M,)): the lowest disk margin and the highest overshoot
    found over the set and where; ``settled`` False where a member was unstable or did not
    settle (then the overshoot is inf)."""

    disk_margin: np.ndarray
    disk_margin_at: list
    overshoot_pct: np.ndarray
    overshoot_at: list
    settled: np.ndarray

    def meets(self, disk_margin_min: float, overshoot_max_pct: float) -> np.ndarray:
        """Both constraints hold for every member found."""
        return (self.settled & (self.disk_margin >= disk_margin_min)
                & (self.overshoot_pct < overshoot_max_pct))


def _figures(problem, member: Member, gains, kp, ki, time_domain: bool = True):
    """(disk margin, overshoot %, settled) of loops on one member; unstable: (0, inf, False)."""
    f = evaluate(problem.member_plant(member, gains), kp, ki, band_pct=problem.band_pct,
                 classical=False, time_domain=time_domain)
    settled = f.stable & np.isfinite(f.settling_time_s) if time_domain else f.stable
    over = np.where(settled, np.nan_to_num(f.overshoot_pct, nan=np.inf), np.inf)
    return np.where(f.stable, f.disk_margin, 0.0), over, settled


def worst_members(problem, gains, kp, ki) -> WorstCase:
    """The worst member of ``problem.box`` for M loops (``gains`` (M, G) in W, ``kp`` 1/W,
    ``ki`` 1/(W s), shape (M,)); see the module docstring."""
    box = problem.box
    gains = np.atleast_2d(np.asarray(gains, float))
    kp, ki = np.asarray(kp, float), np.asarray(ki, float)
    m = kp.size
    dm, over = np.full(m, np.inf), np.full(m, -np.inf)
    settled = np.ones(m, bool)
    dm_at, os_at = [None] * m, [None] * m
    for member in dict.fromkeys(box.vertices() + box.centres()):
        d, o, s = _figures(problem, member, gains, kp, ki)
        settled &= s
        for i in np.nonzero(d < dm)[0]:
            dm_at[i] = member
        dm = np.minimum(dm, d)
        for i in np.nonzero(o > over)[0]:
            os_at[i] = member
        over = np.maximum(over, o)
    if box.dimension:
        # the coordinates each loop has (its DER types with a gain)
        types = [problem.types_in(row) for row in gains]
        has = np.array([[c.der_type in t for c in box.coordinates] for t in types])
        rows = np.nonzero(settled & (dm < problem.disk_margin_min + REFINE_DM))[0]
        _compass(problem, gains, kp, ki, rows, dm, dm_at, has, worse=-1.0)
        rows = np.nonzero(settled & (over > REFINE_OS * problem.overshoot_max_pct))[0]
        _compass(problem, gains, kp, ki, rows, over, os_at, has, worse=1.0)
    return WorstCase(dm, dm_at, over, os_at, settled)


def _compass(problem, gains, kp, ki, rows, value, at, has, worse: float) -> None:
    """Compass search (module docstring) in place on ``value``/``at`` for ``rows``: towards
    lower disk margin (``worse`` -1) or higher overshoot (+1)."""
    time_domain = worse > 0
    step = FIRST
    while step >= FINEST and rows.size:
        active = rows
        for _ in range(MOVES):
            probes: dict = {}
            for i in active:
                x0 = at[i].x
                for d in np.nonzero(has[i])[0]:
                    for sign in (-1.0, 1.0):
                        x = list(x0)
                        x[d] = min(1.0, max(0.0, x0[d] + sign * step))
                        if x[d] != x0[d]:
                            probes.setdefault(Member(at[i].model, tuple(x)), []).append(i)
            moved = set()
            for member, idx in probes.items():
                idx = np.array(idx)
                d, o, s = _figures(problem, member, gains[idx], kp[idx], ki[idx],
                                   time_domain=time_domain)
                v = o if time_domain else d
                for j, i in enumerate(idx):
                    if worse * (v[j] - value[i]) > 0:
                        value[i], at[i] = v[j], member
                        moved.add(i)
            if not moved:
                break
            active = np.array(sorted(moved))       # only loops that moved can move again
        step /= 2.0
