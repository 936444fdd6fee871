"""The gain table's entry for each subset the year goes through, and its figures.

:class:`EntryFigures` asks the CPFC's own gain schedule
(:class:`adnmesh.control.cpfc_controller.GainSchedule`) for a subset's entry, so the study
uses the entry the CPFC would: the table's (``adnmesh tune``'s, if there is one) where it is
feasible, else one tuned on demand (:class:`adnmesh.tuning.ondemand.OnDemandTuner`,
warm-started from the table; certified like a table entry), once per subset. A subset's
figures are those of the as-deployed loop (weights applied): rise time, settling time,
overshoot, disk margin, and the weights that share a step among its DERs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Figures", "EntryFigures", "NONE"]


@dataclass(frozen=True)
class Figures:
    """A subset's entry as the study uses it.

    Attributes
    ----------
    feasible : bool
        The entry meets the constraints (False for the empty subset).
    rise_s, settling_s, overshoot_pct, disk_margin : float
        Step figures and disk margin of the as-deployed loop, s, s, % and 1 (NaN: none).
    share : ndarray, shape (n,)
        The part of a step each DER of the config delivers in steady state,
        ``w_d P_inst,d / Σ w P_inst`` over the subset (0 outside it).
    tuned : bool
        Whether the entry was tuned on demand (the table lacked it).
    """

    feasible: bool
    rise_s: float
    settling_s: float
    overshoot_pct: float
    disk_margin: float
    share: np.ndarray
    tuned: bool = False


NONE = float("nan")


class EntryFigures:
    """Figures of subsets (bool masks over the config's DERs), cached.

    Parameters
    ----------
    config : adnmesh.config.Config
    table : adnmesh.tuning.table.SchedulingTable or None
    """

    def __init__(self, config, table=None) -> None:
        from adnmesh.control.cpfc_controller import GainSchedule

        self.ids = config.der_ids()
        self.p_inst = np.array([d.p_inst_w for d in config.ders], dtype=float)
        self._schedule = GainSchedule(config, table)
        self._cache: dict[bytes, Figures] = {}

    @property
    def subsets(self) -> int:
        """Distinct subsets asked for so far."""
        return len(self._cache)

    @property
    def tuned(self) -> int:
        """Of them, those tuned on demand (the table lacked them or had no feasible entry)."""
        return sum(f.tuned for f in self._cache.values())

    def __call__(self, mask: np.ndarray) -> Figures:
        key = np.packbits(mask).tobytes()
        out = self._cache.get(key)
        if out is None:
            out = self._cache[key] = self._figures(mask)
        return out

    def _figures(self, mask: np.ndarray) -> Figures:
        n = len(self.ids)
        if not mask.any():
            return Figures(False, NONE, NONE, NONE, NONE, np.zeros(n))
        entry, source = self._schedule.lookup(
            frozenset(d for d, m in zip(self.ids, mask) if m))
        tuned = source == "tuned"
        f = entry.figures
        weights = np.array([entry.w.get(d, 0.0) if m else 0.0
                            for d, m in zip(self.ids, mask)], dtype=float)
        power = weights * self.p_inst
        share = power / power.sum() if power.sum() > 0 else np.zeros(n)

        def number(key: str) -> float:
            value = f.get(key)
            return NONE if value is None else float(value)

        return Figures(bool(entry.feasible), number("rise_time_s"), number("settling_time_s"),
                       number("overshoot_pct"), number("disk_margin"), share, tuned)
