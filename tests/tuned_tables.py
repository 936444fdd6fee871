"""Test helper: the gain table ``adnmesh up`` tunes for a config that has none."""

from __future__ import annotations

from adnmesh.config import Config
from adnmesh.tuning.subset_selection import scenario_subsets
from adnmesh.tuning.table import SchedulingTable


def tuned_table(config: Config) -> SchedulingTable:
    """The scenario's subsets (the directional ones included, docs/method.md#directional-
    availability), tuned on demand as ``up`` tunes them; no static controller."""
    from adnmesh.tuning.ondemand import OnDemandTuner

    tuner = OnDemandTuner(config)
    table = SchedulingTable(config.sha256, config.constraints.model_dump(), "on-demand",
                            config.der_ids())
    for subset in scenario_subsets(config):
        table.add(tuner.tune(list(subset)))
    return table
