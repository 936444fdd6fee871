"""On-demand tuning of one subset a table lacks, warm-started from the table's nearest plant.

Neighbouring normalised plants have nearly the same optimum (the plants of a config form a
low-dimensional family: the power fractions per dynamics class). So an unseen subset starts
from the normalised gains of the table entry whose fractions are nearest (L1 distance), and
one batch of candidates along that pair's ray (``RAY_FACTORS`` times it) is screened for the
disk margin, and the largest candidates that pass are checked on the exact model (step
response); the feasible one with the lowest rise time is taken. Find W, the back-off and the
as-deployed figures then follow exactly as for a table entry
(:func:`~adnmesh.tuning.certify.certified_entries`), so the entry is certified: both
constraints re-checked on the exact loop with W applied.

Without a table, when the nearest plant is farther than :data:`NEAR_L1`, or when no candidate
of the ray is feasible, the global search decides (:func:`tune_subset`, about a second). Every
entry the global search tunes becomes a starting point for the next; one found on a ray does
not (chained rays drift off the optimum: without a table, the SimBench year's 9-DER plant came
out at 74 s of rise time instead of 2.4 s).

**Large configs.** When DERs' dynamics are spread per DER, every DER is its own dynamics class
and the searches would run on plants with as many groups as DERs. Beyond
:data:`~adnmesh.tuning.problem.MAX_EXACT_CLASSES` classes the searches run on a *design*
plant with one group per DER type (the installed-power-weighted mean delay and lag of its
DERs; :meth:`~adnmesh.tuning.problem.TuningProblem.design`); Find W, the back-off and the
as-deployed check still run on the exact plant, so the entry is certified all the same. A
subset of more than ``MAX_DERS`` DERs is refused (:class:`~adnmesh.errors.UsageError`, one
line) instead of tuned for minutes.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from adnmesh.errors import UsageError
from adnmesh.tuning.certify import PlantGroup, certified_entries
from adnmesh.tuning.global_search import tune_global
from adnmesh.tuning.paper import initial_values
from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.table import SchedulingTable, TableEntry

__all__ = ["OnDemandTuner", "tune_subset", "RAY_FACTORS", "SIMULATED", "MAX_DERS", "NEAR_L1"]

#: largest subset tuned on demand
MAX_DERS = 300

#: the largest L1 distance of power fractions at which a plant starts from its neighbour; a
#: farther plant is tuned by the global search. A complete SimBench table's plants lie within
#: 0.01 (p90) and 0.027 (p99) of their nearest; at 0.5 (one WT with three CHPs as the start of
#: six WTs with them) the ray's best was 24 s of rise time against the optimum's 2.4 s.
NEAR_L1 = 0.1

#: candidates along the neighbour's ray, times its normalised pair
RAY_FACTORS = np.geomspace(0.6, 1.25, 16)
#: candidates of the ray (the largest meeting the disk margin) whose step response is simulated
SIMULATED = 3


class OnDemandTuner:
    """Tunes subsets on demand for one config, warm-started from ``table``, with a cache.

    Parameters
    ----------
    config : Config
    table : SchedulingTable, optional
        Entries to start from (feasible ones only).
    constraints : dict, optional
        ``disk_margin_min`` / ``overshoot_max_pct`` overriding the config's.
    """

    def __init__(self, config, table: SchedulingTable | None = None,
                 constraints: dict | None = None):
        self.config = config
        self.constraints = constraints
        self.problem = TuningProblem(config, **(constraints or {}))
        self.design = self.problem.design()
        self.cache: dict[frozenset, TableEntry] = {}
        self._fractions = np.zeros((0, len(self.design.actuators)))
        self._gains = np.zeros((0, 2))
        if table is not None:
            self.add_table(table)

    def add_table(self, table: SchedulingTable, exclude=None) -> None:
        """Use the feasible entries of ``table`` as starting points (``exclude``: plant keys
        to leave out, e.g. to test on unseen plants)."""
        fr, gains = [], []
        for e in table.entries.values():
            if not e.feasible:
                continue
            f, total = self.design.fractions(e.ders)
            if exclude is not None and self.design.key(f) in exclude:
                continue
            back = e.figures.get("gain_back_off") or 1.0
            fr.append(f)
            gains.append((e.kp / back * total, e.ki / back * total))
        if fr:
            self._fractions = np.vstack([self._fractions, np.array(fr)])
            self._gains = np.vstack([self._gains, np.array(gains)])

    def tune(self, der_ids: Sequence[str]) -> TableEntry:
        """The certified entry of subset ``der_ids`` (cached)."""
        key = frozenset(der_ids)
        if key not in self.cache:
            if len(key) > MAX_DERS:
                raise UsageError(f"a subset of {len(key)} DERs is too large to tune on demand "
                                 f"(at most {MAX_DERS}); 'adnmesh tune {self.config.path} "
                                 "--subsets scenario' makes a table with it (--table)")
            entry = self.cache[key] = self._tune(der_ids)
            if entry.feasible:
                self._learn(entry)
        return self.cache[key]

    def _learn(self, entry: TableEntry) -> None:
        """Use an entry the global search tuned as a starting point for the next subsets (an
        entry found on a ray is as good as its start at best: chained, they drift off the
        optimum)."""
        if not str(entry.figures.get("tuned_by", "")).startswith("global"):
            return
        f, total = self.design.fractions(entry.ders)
        back = entry.figures.get("gain_back_off") or 1.0
        self._fractions = np.vstack([self._fractions, f])
        self._gains = np.vstack([self._gains, [(entry.kp / back * total,
                                                entry.ki / back * total)]])

    def __call__(self, config, der_ids: Sequence[str]) -> TableEntry:
        """``tune(config, der_ids)``, the signature :class:`GainSchedule` expects."""
        return self.tune(der_ids)

    def _best_on_ray(self, f: np.ndarray, kp: np.ndarray, ki: np.ndarray):
        """(index, rise time s) of the fastest feasible candidate on the ray; None if none is
        feasible.

        The disk margin screens the whole ray at once (frequency domain only); step
        responses are simulated for the ``SIMULATED`` largest candidates that pass it (rise
        time falls as the gains grow along the ray), then for the rest if none of those is
        feasible.
        """
        gains = np.broadcast_to(f, (kp.size, f.size))
        screen = self.design.check(gains, kp, ki, simulate=np.zeros(kp.size, bool))
        passing = np.nonzero(screen.reason == "")[0][::-1]          # largest first
        for part in (passing[:SIMULATED], passing[SIMULATED:]):
            if part.size == 0:
                continue
            chk = self.design.check(gains[part], kp[part], ki[part])
            if chk.feasible.any():
                i = int(np.nanargmin(np.where(chk.feasible, chk.rise_time_s, np.nan)))
                return int(part[i]), float(chk.rise_time_s[i])
        return None

    def _tune(self, der_ids: Sequence[str]) -> TableEntry:
        ders = tuple(d for d in self.config.der_ids() if d in set(der_ids))
        if len(ders) != len(set(der_ids)):
            self.config.ders_by_id(der_ids)      # raises ConfigError naming the unknown id
        f, _ = self.design.fractions(ders)
        if not self._fractions.shape[0]:
            return self._global(ders, f)
        distance = np.abs(self._fractions - f).sum(axis=1)
        near = int(np.argmin(distance))
        if distance[near] > NEAR_L1:
            return self._global(ders, f)
        kp = self._gains[near, 0] * RAY_FACTORS
        ki = self._gains[near, 1] * RAY_FACTORS
        found = self._best_on_ray(f, kp, ki)
        if found is None:
            return self._global(ders, f)
        best, rise = found
        exact, _ = self.problem.fractions(ders)
        entry = certified_entries(self.problem, [PlantGroup(exact, (ders,))], kp[[best]],
                                  ki[[best]], np.array([True]), [None], np.array([np.nan]),
                                  np.array([rise]), ["on demand (nearest table plant)"])[0]
        if not entry.feasible:
            return self._global(ders, f)
        return entry

    def _global(self, ders: tuple[str, ...], f: np.ndarray) -> TableEntry:
        """The global search's entry (on the design plant; certified on the exact one)."""
        if self.design is self.problem:
            return tune_subset(self.config, ders, self.constraints)
        kp0, ki0 = initial_values(self.design, f[None])
        glob = tune_global(self.design, f[None], kp0, ki0)
        exact, _ = self.problem.fractions(ders)
        reasons = [None if glob.feasible[0] else "no feasible pair on the global grid"]
        return certified_entries(self.problem, [PlantGroup(exact, (ders,))], glob.kp, glob.ki,
                                 glob.feasible, reasons, glob.rise_time_s, glob.rise_time_s,
                                 ["global (per-type design plant)"])[0]


def tune_subset(config, der_ids: Sequence[str], constraints: dict | None = None) -> TableEntry:
    """Tune one subset on demand by the global search (one vectorised batch, ~1 s), with
    weights: what :class:`OnDemandTuner` falls back on without a table or a feasible ray.

    Used by the CPFC when it meets a subset its table lacks.
    """
    problem = TuningProblem(config, **(constraints or {}))
    ders = tuple(d for d in config.der_ids() if d in set(der_ids))
    if len(ders) != len(set(der_ids)):
        config.ders_by_id(der_ids)          # raises ConfigError naming the unknown id
    fractions, _ = problem.fractions(ders)
    kp0, ki0 = initial_values(problem, fractions)
    glob = tune_global(problem, fractions, kp0, ki0)
    reasons = [None if glob.feasible[0] else "no feasible pair on the global grid"]
    group = PlantGroup(fractions, (ders,))
    return certified_entries(problem, [group], glob.kp, glob.ki, glob.feasible, reasons,
                             glob.rise_time_s, glob.rise_time_s, ["global"])[0]
