"""The levels of a hierarchy of ADNs (docs/hierarchy.md): each level's config on the bus, the
agent a level runs for an id, and the levels file ``adnmesh up`` hands its agent processes.

Every level runs its config's agents, but for three (:func:`hierarchy_agent`, the same for the
in-process run of :mod:`adnmesh.sim.hierarchy_run` and for the processes of ``adnmesh up``):

- the upper grid's DER of ADN ``a`` is the ADN's site agent
  (:class:`~adnmesh.control.adn_site.AdnSite`), which needs the ADN's exchange at its operating
  point;
- an ADN's measurement also sends its exchange to that site agent;
- the upper CPFC applies the rule for the ADNs' own gain switches
  (:class:`~adnmesh.cascade.switches.LowerSwitchRule`).

An ADN runs on the bus as grid ``<its id>``, without its own steps of P_ref unless the hierarchy
file keeps them (:func:`on_bus`).

**The levels file** (JSON, :class:`LevelsFile`) is what an agent process of a hierarchy's run
needs beyond its own config: every level's config file and table (for the topology of the
whole hierarchy, :func:`~adnmesh.sim.hierarchy_topology.hierarchy_topology`), each ADN's offset
link delay, operating-point exchange and, for the upper CPFC's rule, its loop as the upper
table was certified on it (the fields of the ADN's ``adn_actuator`` announcement), its
``C_i g_i`` and inter-site delay. :func:`load_levels` reads it back into :class:`Levels`; a
file that is not one is a :class:`~adnmesh.errors.ConfigError` in one line.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import msgspec

from adnmesh.config import Config, load_config
from adnmesh.errors import ConfigError
from adnmesh.names import der_agent_id, der_id_of

__all__ = ["AdnLevel", "Levels", "LevelsFile", "LoopFields", "hierarchy_agent", "load_levels",
           "on_bus", "save_levels"]

MAX_LEVELS_BYTES = 4 * 1024 * 1024
"""The largest levels file read, bytes (a hierarchy of the most ADNs is a few hundred kB)."""


def on_bus(config: Config, adn_id: str, keep_steps: bool) -> Config:
    """ADN ``adn_id``'s config as it runs in its hierarchy: on grid ``<adn_id>``, without its
    own steps of P_ref unless ``keep_steps`` (its availability changes stay)."""
    scenario = config.scenario if keep_steps else \
        config.scenario.model_copy(update={"p_ref_steps": ()})
    return config.model_copy(update={"grid": adn_id, "scenario": scenario})


def hierarchy_agent(agent_id: str, config: Config, upper: Config,
                    p_ip0_w: Mapping[str, float], make: Callable[[], object],
                    lower_switch_rule=None):
    """The state machine of ``agent_id`` of the level with ``config`` (``upper``: the upper
    level's; ``p_ip0_w``: each ADN's exchange at its operating point, W): the site agent, the
    ADN's measurement with its exchange, or ``make()`` -- for the upper CPFC with a copy of
    ``lower_switch_rule`` applied (see the module docstring)."""
    from adnmesh.control.adn_site import AdnSite
    from adnmesh.control.measurement_point import Measurement

    if config.grid == upper.grid:
        adn = der_id_of(agent_id)
        if adn in p_ip0_w:
            (der,) = upper.ders_by_id([adn])
            return AdnSite(der, upper, p_ip0_w[adn])
        agent = make()
        if agent_id == "cpfc" and lower_switch_rule is not None:
            getattr(agent, "p", agent).lower_switch_rule = copy.deepcopy(lower_switch_rule)
        return agent
    if agent_id == "measurement":
        return Measurement(config, exchange=True)
    return make()


class GroupFields(msgspec.Struct, forbid_unknown_fields=True):
    """One actuator group of an ADN's loop (as in ``adn_actuator``): delay and time constant,
    s, model, gain, W."""

    t_delay_s: float
    t_lag_s: float
    model: str
    gain_w: float


class LoopFields(msgspec.Struct, forbid_unknown_fields=True):
    """An ADN's closed loop as its CPFC announces it (the fields of ``adn_actuator`` that
    :func:`adnmesh.cascade.lower_adn.announced` reads): PI gains, 1/W and 1/(W s), delays, s,
    capacity, W, groups."""

    kp: float
    ki: float
    t_com_s: float
    t_meas_s: float
    capacity_w: float
    groups: list[GroupFields]

    @classmethod
    def of(cls, lower) -> LoopFields:
        """The fields of :class:`~adnmesh.cascade.lower_adn.LowerAdn` ``lower``."""
        plant = lower.plant
        return cls(float(lower.kp), float(lower.ki), float(plant.t_com_s),
                   float(plant.t_meas_s), float(lower.capacity_w),
                   [GroupFields(float(a.t_delay_s), float(a.t_lag_s), a.model, float(g))
                    for a, g in zip(plant.actuators, plant.gains_w.tolist())])


class AdnLevel(msgspec.Struct, forbid_unknown_fields=True):
    """One ADN of the levels file: its config and table files, whether it keeps its own steps,
    its offset link delay, s, its exchange at its operating point, W, its ``C_i g_i``, W, its
    inter-site delay, s, and its loop as the upper table was certified on it."""

    config: str
    table: str | None
    keep_steps: bool
    offset_delay_s: float
    p_ip0_w: float
    gain_w: float
    t_com_s: float
    loop: LoopFields


class LevelsFile(msgspec.Struct, forbid_unknown_fields=True):
    """The levels file (see the module docstring): the upper config and table files, the ADNs
    by id in file order."""

    upper_config: str
    upper_table: str
    adns: dict[str, AdnLevel]


def save_levels(path: Path, levels: LevelsFile) -> Path:
    """Write ``levels`` to ``path`` (JSON, atomically); return the path."""
    from adnmesh.files import write_atomic
    write_atomic(path, msgspec.json.format(msgspec.json.encode(levels)))
    return path


@dataclass
class Levels:
    """A levels file read back: every level's config on the bus and what its agents need.

    Attributes
    ----------
    file : LevelsFile
    upper : Config
        The upper level's config.
    adns : dict
        ADN id -> its config on the bus (:func:`on_bus`).
    originals : dict
        ADN id -> its config as its file has it (its table was tuned for it).
    """

    file: LevelsFile
    upper: Config
    adns: dict[str, Config]
    originals: dict[str, Config]
    _schedules: dict = field(default_factory=dict, repr=False)

    def config(self, grid: str) -> Config:
        """The config of the level on grid ``grid``.

        Raises
        ------
        ConfigError
            No level is on that grid.
        """
        if grid == self.upper.grid:
            return self.upper
        if grid not in self.adns:
            raise ConfigError(f"no level of the hierarchy is on grid {grid!r} (known: "
                              f"{', '.join([self.upper.grid, *self.adns])})")
        return self.adns[grid]

    @cached_property
    def topology(self):
        """Who talks to whom across every level (qualified agent names)."""
        from adnmesh.sim.hierarchy_topology import hierarchy_topology
        return hierarchy_topology(self.upper, self.adns, self.offset_delay_s)

    @property
    def offset_delay_s(self) -> dict[str, float]:
        return {a: level.offset_delay_s for a, level in self.file.adns.items()}

    @property
    def p_ip0_w(self) -> dict[str, float]:
        return {a: level.p_ip0_w for a, level in self.file.adns.items()}

    def site_members(self, adn: str) -> tuple[str, ...]:
        """The agents behind ADN ``adn``'s site router, as the topology names them: its own
        and the upper level's site agent of it (``<grid>:<agent id>``)."""
        from adnmesh.sim.hierarchy_topology import qualified
        return tuple(a for a in self.topology.agents if a.startswith(f"{adn}:")) + (
            qualified(self.upper.grid, der_agent_id(adn)),)

    def schedule(self, grid: str):
        """The gain schedule of the level's CPFC: its table (tuned for the config of its file;
        none: tuned on demand)."""
        from adnmesh.control.cpfc_controller import GainSchedule
        from adnmesh.tuning.table import load_table

        if grid not in self._schedules:
            config = self.config(grid)
            if grid == self.upper.grid:
                table = load_table(self.file.upper_table, config)
            else:
                path = self.file.adns[grid].table
                table = None if path is None else load_table(path, self.originals[grid])
            self._schedules[grid] = GainSchedule(config, table)
        return self._schedules[grid]

    def lower_switch_rule(self):
        """The upper CPFC's rule for the ADNs' own gain switches, from the ADNs' loops as the
        upper table was certified on them."""
        from adnmesh.cascade.lower_adn import announced
        from adnmesh.cascade.switches import LowerSwitchRule

        adns = self.file.adns
        return LowerSwitchRule({a: announced(a, level.loop) for a, level in adns.items()},
                               {a: level.gain_w for a, level in adns.items()},
                               {a: level.t_com_s for a, level in adns.items()},
                               self.upper.t_meas_s, self.upper.constraints)

    def agent(self, grid: str, agent_id: str, make: Callable[[], object]):
        """The state machine of ``agent_id`` of the level on ``grid`` (:func:`hierarchy_agent`;
        the upper CPFC with the rule)."""
        rule = self.lower_switch_rule() if (grid, agent_id) == (self.upper.grid, "cpfc") \
            else None
        return hierarchy_agent(agent_id, self.config(grid), self.upper, self.p_ip0_w, make,
                               rule)


def load_levels(path: str | Path, load: Callable[[str], Config] = load_config) -> Levels:
    """Read the levels file at ``path`` and every config it names (with ``load``).

    Raises
    ------
    ConfigError
        An unreadable or malformed file, or a config that does not load.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_LEVELS_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the levels file: {exc.strerror or exc}") \
            from None
    if len(data) > MAX_LEVELS_BYTES:
        raise ConfigError(f"{path}: a levels file is at most {MAX_LEVELS_BYTES} bytes")
    try:
        file = msgspec.json.decode(data, type=LevelsFile)
    except msgspec.DecodeError as exc:
        raise ConfigError(f"{path}: not a levels file of adnmesh up ({exc})") from None
    upper = load(file.upper_config)
    originals = {a: load(level.config) for a, level in file.adns.items()}
    adns = {a: on_bus(originals[a], a, level.keep_steps) for a, level in file.adns.items()}
    return Levels(file, upper, adns, originals)
