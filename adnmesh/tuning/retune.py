"""A subset tuned again at run time, certified over the uncertainty set a step's fit implies
(the model watch's ``retune``, docs/method.md#model-watch).

The set (:func:`widened_set`) holds the config's own set, if it has one, and per fitted DER
type the configured model and the fit's 95 % intervals (the rule of ``adnmesh identify
--robust-out``: :func:`~adnmesh.identify.implied_set.implied_set`). The subset is then tuned
on demand over it (:class:`~adnmesh.tuning.ondemand.OnDemandTuner`: every check covers the
set's members, the entry is certified over the set, docs/tuning.md#robust-tables).
"""
from __future__ import annotations

from typing import Sequence

from adnmesh.config import RobustSet
from adnmesh.identify.implied_set import implied_set
from adnmesh.tuning.ondemand import OnDemandTuner
from adnmesh.tuning.table import SchedulingTable, TableEntry

__all__ = ["retune", "widened_set"]


def widened_set(config, ders: Sequence[str], fits: dict) -> RobustSet:
    """``constraints.robust`` covering the config's set and ``fits`` (DER type ->
    :class:`~adnmesh.identify.model_fit.ModelFit`) for the DERs ``ders`` of those types."""
    found = implied_set(config, [(d.id, fits[d.type]) for d in config.ders_by_id(ders)
                                 if d.type in fits])
    own = config.constraints.robust
    if own is None:
        return RobustSet.model_validate(found)
    types = {}
    for t in dict.fromkeys(d.type for d in config.ders):
        u, f = own.of_type(t), found["types"].get(t)
        lag, delay = list(u.lag_scale), list(u.delay_add_s)
        if f is not None:
            lag = [min(lag[0], f["lag_scale"][0]), max(lag[1], f["lag_scale"][1])]
            delay = [min(delay[0], f["delay_add_s"][0]), max(delay[1], f["delay_add_s"][1])]
        types[t] = {"lag_scale": lag, "delay_add_s": delay}
    return RobustSet.model_validate({"models": list(dict.fromkeys((*own.models,
                                                                   *found["models"]))),
                                     "types": types})


def retune(config, table: SchedulingTable | None, ders: Sequence[str],
           fits: dict) -> tuple[TableEntry, RobustSet]:
    """The entry of subset ``ders`` certified over :func:`widened_set` (warm-started from
    ``table``), and that set."""
    robust = widened_set(config, ders, fits)
    constraints = config.constraints.model_copy(update={"robust": robust})
    wide = config.model_copy(update={"constraints": constraints})
    return OnDemandTuner(wide, table).tune(list(ders)), robust
