"""The run of a hierarchy of ADNs: its levels from the configs and tables, the in-process run
on the sim clock, and what a person reads of it (docs/hierarchy.md).

:func:`hierarchy_levels` makes the levels :func:`adnmesh.sim.hierarchy_run.run_hierarchy` runs:
the upper config and table ``adnmesh cascade`` wrote, and each ADN's config on the bus as grid
``<its id>`` with its own table (gains tuned on demand where it has none). An ADN's own steps of
P_ref are its standalone scenario and are left out unless the hierarchy file keeps them
(``keep_steps``); its availability changes stay. :func:`simulate` runs it and gives the upper
level's steps (:func:`~adnmesh.loopmodel.step_figures.reference_step_figures` of the sum of the
exchanges against its reference) and every level's series.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from adnmesh.config import Config, Hierarchy, load_config
from adnmesh.loopmodel.step_figures import ReferenceStep, reference_step_figures
from adnmesh.results.design_check import DesignCheck, design_checks
from adnmesh.results.summary import note_entry
from adnmesh.sim.hierarchy_levels import AdnLevel, LevelsFile, LoopFields, on_bus
from adnmesh.sim.hierarchy_run import HierarchyRun, Level, run_hierarchy
from adnmesh.wire.envelope import decode
from adnmesh.wire.keys import Keys, route

__all__ = ["HierarchyResult", "hierarchy_levels", "level_series", "levels_file", "simulate"]


def _adn_level(hierarchy: Hierarchy, adn, path=None) -> Level:
    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.tuning.table import default_table_path, load_table

    config = load_config(hierarchy.config_path(adn))
    path = Path(path or default_table_path(config))
    table = load_table(path, config) if path.exists() else None
    level = on_bus(config, adn.id, adn.keep_steps)
    return Level(level, GainSchedule(level, table))


def hierarchy_levels(hierarchy: Hierarchy, upper: Config, upper_table, sites, tables=None
                     ) -> tuple[Level, dict[str, Level], dict[str, float]]:
    """The upper level (``upper`` with ``upper_table``, its CPFC applying the rule for the
    ADNs' gain switches from their loops as certified -- as an ``adn_actuator`` announcement
    carries them, :class:`~adnmesh.sim.hierarchy_levels.LoopFields`), each ADN's level (its
    table ``tables[adn id]``, default its config's own) and its offset link delay, s (its
    inter-site delay less the upper ``t_com_s``; ``sites``: the
    :class:`~adnmesh.cascade.upper_table.Site` of each ADN)."""
    from adnmesh.cascade.lower_adn import announced
    from adnmesh.cascade.switches import LowerSwitchRule
    from adnmesh.control.cpfc_controller import GainSchedule

    adns = {adn.id: _adn_level(hierarchy, adn, (tables or {}).get(adn.id))
            for adn in hierarchy.adns}
    delays = {s.id: round(s.t_com_s - upper.t_com_s, 6) for s in sites}
    gains = {s.id: s.grid_gain for s in sites}
    rule = LowerSwitchRule({s.id: announced(s.id, LoopFields.of(s.adn)) for s in sites},
                           {d.id: d.p_inst_w * gains[d.id] for d in upper.ders},
                           {s.id: s.t_com_s for s in sites}, upper.t_meas_s, upper.constraints)
    return Level(upper, GainSchedule(upper, upper_table), rule), adns, delays


def levels_file(hierarchy: Hierarchy, levels, upper_table_path: Path, tables=None
                ) -> LevelsFile:
    """The levels file of the run of ``levels`` (:func:`hierarchy_levels`) as processes: the
    upper config and ``upper_table_path``, each ADN's config and table (``tables[adn id]``,
    default its config's own if it has one), its offset link delay, operating-point exchange
    and its part of the upper CPFC's rule."""
    from adnmesh.control.operating_point import initial_p_ip_w
    from adnmesh.tuning.table import default_table_path

    upper, adns, delays = levels
    rule = upper.lower_switch_rule
    found = {}
    for adn in hierarchy.adns:
        path = (tables or {}).get(adn.id) or default_table_path(load_config(
            hierarchy.config_path(adn)))
        found[adn.id] = str(Path(path).resolve()) if Path(path).exists() else None
    return LevelsFile(str(Path(upper.config.path).resolve()), str(upper_table_path.resolve()), {
        adn.id: AdnLevel(str(hierarchy.config_path(adn)), found[adn.id], adn.keep_steps,
                         delays[adn.id], initial_p_ip_w(adns[adn.id].config),
                         rule.gain_w[adn.id], rule.t_com_s[adn.id],
                         LoopFields.of(rule.lowers[adn.id]))
        for adn in hierarchy.adns})


@dataclass(frozen=True)
class HierarchyResult:
    """A hierarchy's run and its figures.

    Attributes
    ----------
    run : HierarchyRun
        Every message and node.
    wall_s : float
        Wall time of the run, s.
    end_s : float
        Its length in sim time, s.
    steps : tuple of ReferenceStep
        The upper level's steps: its P_IP after each step of its reference.
    checks : tuple of DesignCheck
        Each step against what the upper entry in use was certified for on the cascade
        (:func:`adnmesh.results.design_check.design_checks`, from the upper CPFC's ``p_y``).
    window_ends_ns : tuple of int
        The instants that end a step's window: every level's gain switches and availability
        changes, ns.
    """

    run: HierarchyRun
    wall_s: float
    end_s: float
    steps: tuple[ReferenceStep, ...]
    checks: tuple[DesignCheck, ...]
    window_ends_ns: tuple[int, ...] = ()

    @property
    def speed(self) -> float:
        """Sim seconds per wall second."""
        return self.end_s / self.wall_s if self.wall_s > 0 else float("inf")


def level_series(run: HierarchyRun, key: str, field: str) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns, values)`` of ``field`` of every message on ``key``, by the time it was sent
    (a measurement's sampling instant)."""
    messages = [decode(key, payload) for payload in run.payloads(key)]
    t = np.asarray([m.t_send_ns for m in messages], dtype=np.int64)
    order = np.argsort(t, kind="stable")
    return t[order], np.asarray([getattr(m, field) for m in messages], dtype=float)[order]


def _window_ends(run: HierarchyRun) -> list[int]:
    """Instants that end a step's window in the upper level: a gain switch of any level's
    CPFC (the upper one's, or an ADN's that changes the loop under it); :func:`simulate` adds
    every level's availability changes."""
    return sorted(decode(k, payload).t_send_ns for k in run.keys if k.endswith("/cpfc/p_y")
                  for payload in run.payloads(k) if b'"switch"' in payload)


def simulate(upper: Level, adns: dict[str, Level], offset_delay_s: dict[str, float],
             end_s: float | None = None, on_progress=None) -> HierarchyResult:
    """Run the hierarchy in this process on the sim clock and take the upper level's steps
    (``on_progress``: see :func:`~adnmesh.sim.hierarchy_run.run_hierarchy`)."""
    config = upper.config
    end_s = config.scenario.duration_s if end_s is None else end_s
    t0 = time.perf_counter()
    run = run_hierarchy(upper, adns, offset_delay_s, end_s=end_s, on_progress=on_progress)
    wall = time.perf_counter() - t0
    keys = Keys(config.grid)
    t_ip, p_ip = level_series(run, keys.of("p_ip"), "p_ip_w")
    t_ref, p_ref = level_series(run, keys.of("p_ref"), "p_ref_w")
    ends = _window_ends(run) + [int(round(c.t_s * 1e9)) for level in (upper, *adns.values())
                                for c in level.config.scenario.availability]
    steps = reference_step_figures(t_ip, p_ip, t_ref, p_ref, sorted(ends),
                                   int(round(end_s * 1e9)),
                                   band_pct=config.constraints.settling_band_pct)
    return HierarchyResult(run, wall, end_s, steps, design_checks(steps, _entries(run, keys)),
                           tuple(sorted(ends)))


def _entries(run: HierarchyRun, keys: Keys) -> list[dict]:
    """The upper CPFC's entries as its ``p_y`` messages announce them (with design figures)."""
    entries = []
    for payload in run.payloads(keys.of("p_y")):
        note_entry(entries, msgspec.json.decode(payload))
    return entries


class _Times(msgspec.Struct):
    """The two times of an envelope (its other fields are not decoded)."""

    t_send_ns: int
    t_deliver_ns: int


_TIMES = msgspec.json.Decoder(_Times)


def recorded(run: HierarchyRun):
    """``(key, type, payload, t_send_ns, t_deliver_ns)`` of every message, by delivery time
    (the order a recording keeps)."""
    rows = []
    for key in run.keys:
        kind = route(key).type
        for payload in run.payloads(key):
            times = _TIMES.decode(payload)
            rows.append((key, kind, payload, times.t_send_ns, times.t_deliver_ns))
    rows.sort(key=lambda r: r[4])
    return rows
