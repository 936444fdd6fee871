"""Which gains of a table the CPFC could use are not certified stable.

A table file is data: it may have been edited, made for other constraints, or damaged, and it
passes as long as it parses and names the config. ``adnmesh up`` therefore checks, before it
starts anything, the loops the CPFC would run with it (the reference loop of
:func:`adnmesh.loopmodel.evaluation.evaluate`, the design's ``T_com`` with the sampled PI's hold,
each entry's weights as deployed), by the certified Nyquist argument
(:mod:`adnmesh.loopmodel.stability`):

- every feasible entry of the table (the CPFC takes only those; all of them, not only the
  scenario's: a fault may take the run to any of them);
- the static controller (unit weights) on the subsets it stands in for first: the scenario's,
  the table's own, and each of these less one DER (a DER lost, or gone quiet, takes the run
  there, and an on-demand tuning of the new set starts from the static pair).

One evaluation of every loop at once (stability and disk margin only, no step responses):
0.21 s for the SimBench table ``up`` tunes (2 entries and the static pair on 18 subsets: 20
loops), 0.9 s the first time in a process (the compiled kernels load). A loop whose stability
the argument cannot certify counts as unstable (the verdict ``certified = False`` of
:class:`~adnmesh.loopmodel.stability.NyquistData`); so do gains that are not finite and
positive. See docs/tuning.md#the-table-up-runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.table import SchedulingTable

__all__ = ["UnstableGains", "unstable_gains"]


@dataclass(frozen=True)
class UnstableGains:
    """A loop of the table that is not certified stable.

    ``what`` is ``entry`` or ``static``; ``ders`` the subset (config order); ``poles`` the
    closed-loop poles in the right half-plane (-1: not certified either way)."""

    what: str
    ders: tuple[str, ...]
    kp: float
    ki: float
    poles: int

    def describe(self) -> str:
        """One line, e.g. ``entry SGen5, SGen6 (K_P 2e-06 1/W, K_I 1e-06 1/(W s)): 2 closed-loop
        poles in the right half-plane``."""
        names = ", ".join(self.ders) if len(self.ders) <= 6 else \
            f"{', '.join(self.ders[:5])}, ... ({len(self.ders)} DERs)"
        verdict = ("not certified stable (the Nyquist argument cannot decide it)"
                   if self.poles < 0 else
                   f"{self.poles} closed-loop pole(s) in the right half-plane"
                   if self.poles > 0 else "gains not finite and positive")
        return (f"{'the static controller on' if self.what == 'static' else 'entry'} {names} "
                f"(K_P {self.kp:.4g} 1/W, K_I {self.ki:.4g} 1/(W s)): {verdict}")


def _loops(config, table: SchedulingTable, subsets) -> list[tuple[str, tuple, float, float,
                                                                    dict]]:
    """(what, subset in config order, K_P, K_I, weights) of every loop to check."""
    order = {d: i for i, d in enumerate(config.der_ids())}
    known = set(order)

    def ordered(ders) -> tuple[str, ...]:
        return tuple(sorted(ders, key=order.__getitem__))

    loops = []
    for entry in table.entries.values():
        if entry.feasible and entry.ders and set(entry.ders) <= known:
            ders = ordered(entry.ders)
            loops.append(("entry", ders, entry.kp, entry.ki,
                          {d: float(entry.w.get(d, 1.0)) for d in ders}))
    static = table.static
    if static is not None:
        bases = {frozenset(s) for s in subsets} | {frozenset(e.ders) for e in
                                                   table.entries.values()}
        sets = set()
        for base in (b for b in bases if b and b <= known):
            sets.add(base)
            sets.update(base - {d} for d in base if len(base) > 1)
        for s in sorted(sets, key=lambda s: (len(s), ordered(s))):
            ders = ordered(s)
            loops.append(("static", ders, static.kp, static.ki, dict.fromkeys(ders, 1.0)))
    return loops


def unstable_gains(config, table: SchedulingTable, subsets=()) -> list[UnstableGains]:
    """The loops of ``table`` the CPFC could run that are not certified stable (see the module
    docstring), in the order entries, then the static controller by subset size.

    Parameters
    ----------
    config : adnmesh.config.Config
    table : SchedulingTable
    subsets : iterable of iterables of DER ids
        The sets of available DERs the scenario goes through.
    """
    loops = _loops(config, table, subsets)
    if not loops:
        return []
    bad = [not (math.isfinite(kp) and math.isfinite(ki) and kp > 0 and ki > 0)
           for _, _, kp, ki, _ in loops]
    problem = TuningProblem(config)
    rows = [i for i, b in enumerate(bad) if not b]
    poles = np.zeros(len(loops), dtype=int)
    stable = np.zeros(len(loops), dtype=bool)
    if rows:
        gains = np.array([problem.group_power(loops[i][1], loops[i][4]) for i in rows])
        figures = evaluate(problem.plant(gains), np.array([loops[i][2] for i in rows]),
                           np.array([loops[i][3] for i in rows]), classical=False,
                           time_domain=False)
        stable[rows] = figures.stable & figures.certified
        poles[rows] = np.where(figures.certified, figures.unstable_poles, -1)
    return [UnstableGains(what, ders, float(kp), float(ki), 0 if bad[i] else int(poles[i]))
            for i, (what, ders, kp, ki, _) in enumerate(loops) if not stable[i]]
