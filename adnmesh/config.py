"""Load and validate an adnmesh configuration file (YAML) into frozen dataclasses.

The accepted format is described once, by the schema tables below (``_DER``, ``_CONFIG``, ...),
and checked by one walker (:mod:`adnmesh.schema`); relations between values (unique ids, known
DER ids, event times inside the scenario) are checked afterwards by :func:`_check_relations`.
The first problem found is raised as a :class:`~adnmesh.errors.ConfigError` whose message is one
line naming the file and the key path, e.g.
``configs/x.yaml: ders[3].p_inst_w: must be a positive number, got -2``.

Every key that is not in the schema is rejected (with the closest valid key suggested). Units
are in the key names: ``_w`` watts, ``_s`` seconds, ``_pct`` percent.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import yaml

from adnmesh.errors import ConfigError
from adnmesh.schema import (
    Field,
    Flag,
    ListOf,
    Number,
    Record,
    SchemaError,
    Text,
    at_index,
    at_key,
)

__all__ = [
    "DER_TYPES",
    "PT1_RISE_TIME_FACTOR",
    "AvailabilityChange",
    "Config",
    "Constraints",
    "DER",
    "PRefStep",
    "Scenario",
    "load_config",
]

DER_TYPES = ("WT", "CHP", "PV")
"""Accepted DER types: wind turbine, combined heat and power plant, photovoltaic plant."""

PT1_RISE_TIME_FACTOR = math.log(9.0)
"""10 %→90 % rise time of a first-order lag in units of its time constant: ln(0.9/0.1) = 2.1972.

SPEC §2 writes ``T_d = T_rise,d / 2.197``; 2.197 is this number rounded.
"""


@dataclass(frozen=True)
class DER:
    """One distributed energy resource used as an actuator.

    Parameters
    ----------
    id : str
        Identifier, unique in the config; also a bus key segment (``adn/<grid>/der/<id>/...``).
    type : str
        One of :data:`DER_TYPES`.
    p_inst_w : float
        Installed active power ``P_inst,d`` in W (> 0); the controller's ``C_d``.
    t_delay_s : float
        Reaction time ``T_delay,d`` in s (>= 0).
    t_rise_s : float
        10 %→90 % rise time ``T_rise,d`` of the active power response in s (> 0).
    sgen : str
        Name of the static generator in the SimBench grid that this DER drives.
    p_sched_w : float
        Scheduled active power ``P_sched,d`` in W, 0 <= p_sched_w <= p_inst_w; the DER falls
        back to it when it loses contact with the CPFC.
    """

    id: str
    type: str
    p_inst_w: float
    t_delay_s: float
    t_rise_s: float
    sgen: str
    p_sched_w: float = 0.0

    @property
    def t_lag_s(self) -> float:
        """Time constant ``T_d`` of the reference PT1 model in s: ``t_rise_s / ln(9)``."""
        return self.t_rise_s / PT1_RISE_TIME_FACTOR


@dataclass(frozen=True)
class Constraints:
    """Design constraints every lookup-table entry must satisfy (SPEC §2).

    Parameters
    ----------
    disk_margin_min : float
        Lowest acceptable balanced disk margin α (dimensionless, 0 < α < 2).
    overshoot_max_pct : float
        Overshoot of the closed-loop step response must stay below this, in % of the final value.
    settling_band_pct : float
        Band for the settling time, in % of the final value.
    """

    disk_margin_min: float = 1.5
    overshoot_max_pct: float = 1.0
    settling_band_pct: float = 5.0


@dataclass(frozen=True)
class PRefStep:
    """A step of the reference ``P_ref`` at the interconnection point.

    Parameters
    ----------
    t_s : float
        Time of the step in s from the start of the scenario.
    delta_w : float
        Change of ``P_ref`` in W (non-zero; positive raises the reference).
    """

    t_s: float
    delta_w: float


@dataclass(frozen=True)
class AvailabilityChange:
    """DERs becoming available or unavailable.

    Parameters
    ----------
    t_s : float
        Time of the change in s from the start of the scenario.
    ders : tuple of str
        Ids of the DERs concerned.
    available : bool
        Their new availability.
    """

    t_s: float
    ders: tuple[str, ...]
    available: bool


@dataclass(frozen=True)
class Scenario:
    """A time-domain run: duration and events (all DERs are available at t = 0).

    Parameters
    ----------
    duration_s : float
        Length of the run in s.
    p_ref_steps : tuple of PRefStep
        Reference steps in chronological order.
    availability : tuple of AvailabilityChange
        Availability changes in chronological order.
    """

    duration_s: float
    p_ref_steps: tuple[PRefStep, ...] = ()
    availability: tuple[AvailabilityChange, ...] = ()


@dataclass(frozen=True)
class Config:
    """A validated configuration.

    Parameters
    ----------
    path : Path
        The file it was loaded from.
    grid : str
        Name of the grid, used as the ``<grid>`` segment of bus keys (``adn/<grid>/...``).
    simbench_code : str
        SimBench code of the grid, e.g. ``"1-MV-rural--0-no_sw"``.
    ders : tuple of DER
        The actuators, in file order.
    t_com_s : float
        Communication delay CPFC → DERs ``T_com`` in s.
    t_meas_s : float
        Measurement delay ``T_meas`` in s.
    constraints : Constraints
        Tuning constraints.
    scenario : Scenario
        The time-domain scenario.
    sha256 : str
        SHA-256 of the file's bytes (hex), to tie results to the exact file.
    """

    path: Path
    grid: str
    simbench_code: str
    ders: tuple[DER, ...]
    t_com_s: float
    t_meas_s: float
    constraints: Constraints
    scenario: Scenario
    sha256: str

    def der_ids(self) -> tuple[str, ...]:
        """Return the DER ids in file order."""
        return tuple(der.id for der in self.ders)

    def ders_by_id(self, ids: Iterable[str]) -> tuple[DER, ...]:
        """Return the DERs with the given ids, in the order given.

        Raises
        ------
        ConfigError
            If an id is not in the config.
        """
        known = {der.id: der for der in self.ders}
        result = []
        for der_id in ids:
            if der_id not in known:
                raise ConfigError(
                    f"unknown DER id '{der_id}' (known: {', '.join(self.der_ids())})"
                )
            result.append(known[der_id])
        return tuple(result)


# --- the format: one table per section -----------------------------------------------------

_IDENTIFIER = r"[A-Za-z][A-Za-z0-9_-]*"
_IDENTIFIER_WHAT = "an identifier (letters, digits, '_', '-'; starting with a letter)"
_POSITIVE = Number("a positive number", low=0.0, low_open=True)
_NON_NEGATIVE = Number("a non-negative number", low=0.0)

_DER = Record(
    {
        "id": Field(Text(_IDENTIFIER_WHAT, pattern=_IDENTIFIER)),
        "type": Field(Text(f"one of {', '.join(DER_TYPES)}", choices=DER_TYPES)),
        "p_inst_w": Field(_POSITIVE),
        "t_delay_s": Field(_NON_NEGATIVE),
        "t_rise_s": Field(_POSITIVE),
        "sgen": Field(Text()),
        "p_sched_w": Field(_NON_NEGATIVE, required=False),
    },
    build=DER,
)

_CONSTRAINTS = Record(
    {
        "disk_margin_min": Field(
            Number("a number in (0, 2)", low=0.0, high=2.0, low_open=True, high_open=True),
            required=False,
        ),
        "overshoot_max_pct": Field(
            Number("a number in (0, 100]", low=0.0, high=100.0, low_open=True), required=False
        ),
        "settling_band_pct": Field(
            Number("a number in (0, 50]", low=0.0, high=50.0, low_open=True), required=False
        ),
    },
    build=Constraints,
)

_P_REF_STEP = Record(
    {"t_s": Field(_NON_NEGATIVE), "delta_w": Field(Number("a non-zero number", nonzero=True))},
    build=PRefStep,
)

_AVAILABILITY_CHANGE = Record(
    {
        "t_s": Field(_NON_NEGATIVE),
        "ders": Field(ListOf(Text(_IDENTIFIER_WHAT, pattern=_IDENTIFIER), min_len=1)),
        "available": Field(Flag()),
    },
    build=AvailabilityChange,
)

_SCENARIO = Record(
    {
        "duration_s": Field(_POSITIVE),
        "p_ref_steps": Field(ListOf(_P_REF_STEP), required=False),
        "availability": Field(ListOf(_AVAILABILITY_CHANGE), required=False),
    },
    build=Scenario,
)

_CONFIG = Record(
    {
        "grid": Field(Text(_IDENTIFIER_WHAT, pattern=_IDENTIFIER)),
        "simbench_code": Field(Text()),
        "t_com_s": Field(_POSITIVE),
        "t_meas_s": Field(_POSITIVE),
        "constraints": Field(_CONSTRAINTS, required=False),
        "ders": Field(ListOf(_DER, min_len=1)),
        "scenario": Field(_SCENARIO),
    }
)


# --- relations between values ----------------------------------------------------------------


def _check_unique(values: Iterable[str], path_of, what: str) -> None:
    """Raise SchemaError at the second occurrence of a value; ``path_of(i)`` is its key path."""
    first: dict[str, int] = {}
    for i, value in enumerate(values):
        if value in first:
            raise SchemaError(
                path_of(i), f"duplicate {what} '{value}' (also {path_of(first[value])})"
            )
        first[value] = i


def _check_chronological(events, path: str, duration_s: float) -> None:
    """Raise SchemaError unless event times are non-decreasing and inside the scenario."""
    previous = 0.0
    for i, event in enumerate(events):
        where = at_key(at_index(path, i), "t_s")
        if event.t_s > duration_s:
            raise SchemaError(
                where, f"must not exceed scenario.duration_s ({duration_s:g}), got {event.t_s:g}"
            )
        if event.t_s < previous:
            raise SchemaError(
                where, f"must not be earlier than the previous event ({previous:g}), "
                f"got {event.t_s:g}",
            )
        previous = event.t_s


def _check_relations(values: dict) -> None:
    """Check what the per-value schema cannot: uniqueness, references, ordering."""
    ders: tuple[DER, ...] = values["ders"]
    _check_unique((d.id for d in ders), lambda i: f"ders[{i}].id", "DER id")
    _check_unique((d.sgen for d in ders), lambda i: f"ders[{i}].sgen", "sgen")
    for i, der in enumerate(ders):
        if der.p_sched_w > der.p_inst_w:
            raise SchemaError(
                f"ders[{i}].p_sched_w",
                f"must not exceed p_inst_w ({der.p_inst_w:g}), got {der.p_sched_w:g}",
            )
    scenario: Scenario = values["scenario"]
    _check_chronological(scenario.p_ref_steps, "scenario.p_ref_steps", scenario.duration_s)
    _check_chronological(scenario.availability, "scenario.availability", scenario.duration_s)
    known = [d.id for d in ders]
    for i, change in enumerate(scenario.availability):
        path = f"scenario.availability[{i}].ders"
        _check_unique(change.ders, lambda j, path=path: f"{path}[{j}]", "DER id")
        for j, der_id in enumerate(change.ders):
            if der_id not in known:
                raise SchemaError(
                    f"{path}[{j}]", f"unknown DER id '{der_id}' (known: {', '.join(known)})"
                )


# --- reading the file ---------------------------------------------------------------------------


class _Loader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads ``2e6`` / ``2.0e6`` as floats.

    (YAML 1.1, which PyYAML implements, reads a float exponent without a sign as a string.)
    """

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
            except TypeError:  # unhashable key; let PyYAML report it
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key '{key}'", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_FLOAT_TAG = "tag:yaml.org,2002:float"
_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != _FLOAT_TAG]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(
        r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
            |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
            |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
            |[-+]?\.(?:inf|Inf|INF)
            |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _parse_yaml(path: Path, text: str) -> object:
    """Parse YAML text; raise ConfigError with the line and column of a syntax error."""
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - _Loader is a SafeLoader
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" line {mark.line + 1}, column {mark.column + 1}:" if mark else ""
        problem = _one_line(exc.problem or exc.context or "syntax error")
        raise ConfigError(f"{path}:{where} invalid YAML: {problem}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {_one_line(exc)}") from None


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a config file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None


def load_config(path: str | Path) -> Config:
    """Load, validate and return the configuration in ``path``.

    Parameters
    ----------
    path : str or Path
        A YAML file in the format of ``configs/simbench.yaml``.

    Returns
    -------
    Config
        The validated configuration.

    Raises
    ------
    ConfigError
        For the first problem found; the message is one line naming the file and the key path.
    """
    path = Path(path)
    data = _read(path)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    document = _parse_yaml(path, text)
    if document is None:
        keys = ", ".join(_CONFIG.fields)
        raise ConfigError(f"{path}: empty config (expected a mapping with keys: {keys})")
    try:
        values = _CONFIG.check(document, "")
        _check_relations(values)
    except SchemaError as exc:
        raise ConfigError(f"{path}: {exc.path or 'top level'}: {exc.problem}") from None
    return Config(
        path=path,
        grid=values["grid"],
        simbench_code=values["simbench_code"],
        ders=values["ders"],
        t_com_s=values["t_com_s"],
        t_meas_s=values["t_meas_s"],
        constraints=values.get("constraints", Constraints()),
        scenario=values["scenario"],
        sha256=hashlib.sha256(data).hexdigest(),
    )
