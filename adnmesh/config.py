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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from adnmesh.errors import ConfigError
from adnmesh.schema import (
    Field,
    Flag,
    ListOf,
    Number,
    Record,
    SchemaError,
    Spec,
    Text,
    at_index,
    at_key,
    show,
)

__all__ = [
    "DER_TYPES",
    "PT1_RISE_TIME_FACTOR",
    "AgentCrash",
    "AvailabilityChange",
    "Config",
    "Constraints",
    "DER",
    "DEROffline",
    "Faults",
    "LinkSettings",
    "Links",
    "Outage",
    "PRefStep",
    "Runtime",
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


# --- the runtime section (optional; how `adnmesh up` runs the scenario) ----------------------

@dataclass(frozen=True)
class Outage:
    """A window in which an ICT link loses every message sent.

    Parameters
    ----------
    t_s : float
        Start of the outage in s of scenario time.
    duration_s : float
        Length of the outage in s (> 0); messages sent in ``[t_s, t_s + duration_s)`` are lost.
    """

    t_s: float
    duration_s: float


@dataclass(frozen=True)
class LinkSettings:
    """The ICT channel model of one logical link (sender side decides every message's fate).

    Parameters
    ----------
    delay_s : float or None
        Fixed delay in s. ``None`` for the two links whose delay is the config's ``t_com_s``
        (CPFC → DERs) and ``t_meas_s`` (measurement → CPFC).
    jitter_s : float
        Extra delay drawn uniformly from ``[0, jitter_s)`` per message, s.
    loss : float
        Probability that a message is lost, in [0, 1).
    fifo : bool
        Keep the send order (a message is never delivered before an earlier one on the link).
    outages : tuple of Outage
        Windows in which every message is lost.
    """

    delay_s: float | None = None
    jitter_s: float = 0.0
    loss: float = 0.0
    fifo: bool = True
    outages: tuple[Outage, ...] = ()


@dataclass(frozen=True)
class Links:
    """ICT links of the runtime; the DER → measurement path is physical (no delay, no loss).

    Parameters
    ----------
    cpfc_to_der : LinkSettings
        ``P_Y`` and weights from the CPFC to the DERs (delay ``t_com_s``).
    measurement_to_cpfc : LinkSettings
        ``P_IP`` from the measurement to the CPFC (delay ``t_meas_s``).
    der_to_availability : LinkSettings
        Heartbeats from the DERs to the availability monitor (default delay 0.1 s).
    availability_to_cpfc : LinkSettings
        The availability vector SI to the CPFC (default delay 0.1 s).
    """

    cpfc_to_der: LinkSettings = LinkSettings()
    measurement_to_cpfc: LinkSettings = LinkSettings()
    der_to_availability: LinkSettings = LinkSettings(delay_s=0.1)
    availability_to_cpfc: LinkSettings = LinkSettings(delay_s=0.1)


@dataclass(frozen=True)
class DEROffline:
    """An ICT fault at one DER: it neither receives commands nor sends heartbeats for a while.

    Parameters
    ----------
    der : str
        DER id.
    t_s, duration_s : float
        Start and length of the fault, s.
    """

    der: str
    t_s: float
    duration_s: float


@dataclass(frozen=True)
class AgentCrash:
    """An injected crash: the agent's process exits abruptly (exit code 70) at sim time ``t_s``.

    Parameters
    ----------
    agent : str
        ``cpfc``, ``measurement``, ``availability`` or ``der/<id>``.
    t_s : float
        When, s.
    """

    agent: str
    t_s: float


@dataclass(frozen=True)
class Faults:
    """Faults injected into a run (see :class:`DEROffline`, :class:`AgentCrash`)."""

    der_offline: tuple[DEROffline, ...] = ()
    crash: tuple[AgentCrash, ...] = ()


@dataclass(frozen=True)
class Runtime:
    """How ``adnmesh up`` runs the scenario (the optional ``runtime:`` section).

    Parameters
    ----------
    seed : int
        Seed of the random streams of the ICT channel model (>= 0).
    pi_period_s : float
        Sampling period of the CPFC's PI controller, s.
    measurement_period_s : float
        Sampling period of ``P_IP`` (the DERs report their infeed at the same instants), s.
    rest_of_grid_w : float
        Constant part of ``P_IP`` besides the DER infeeds (loads, other generators), W. The
        initial reference is ``rest_of_grid_w + sum(p_sched_w)``, the operating point with
        ``P_Y = 0``.
    heartbeat_period_s : float
        Period of the DERs' heartbeats, s.
    heartbeat_timeout_s : float
        The availability monitor marks a DER unavailable after this long without a heartbeat, s.
    watchdog_timeout_s : float
        A DER falls back to ``P_sched`` after this long without a valid command, s.
    weights_period_s : float
        The CPFC repeats the weights W with ``P_Y`` this often (besides on every switch), s.
    links : Links
        ICT channel model per link.
    faults : Faults
        Injected faults.
    """

    seed: int = 0
    pi_period_s: float = 0.01
    measurement_period_s: float = 0.01
    rest_of_grid_w: float = 0.0
    heartbeat_period_s: float = 1.0
    heartbeat_timeout_s: float = 2.5
    watchdog_timeout_s: float = 1.0
    weights_period_s: float = 1.0
    measurement_timeout_s: float = 0.25
    links: Links = Links()
    faults: Faults = Faults()


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
    runtime : Runtime
        How the distributed runtime runs the scenario (optional section, defaults).
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
    runtime: Runtime = field(default_factory=Runtime)

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



@dataclass(frozen=True)
class _Count(Spec):
    """A non-negative integer (YAML int, not a boolean)."""

    what: str = "a non-negative integer"

    def check(self, value: Any, path: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise SchemaError(path, f"must be {self.what}, got {show(value)}")
        return value


_PERIOD = Number("a number in [1e-6, 3600]", low=1e-6, high=3600.0)
_PROBABILITY = Number("a probability in [0, 1)", low=0.0, high=1.0, high_open=True)
_OUTAGE = Record({"t_s": Field(_NON_NEGATIVE), "duration_s": Field(_POSITIVE)}, build=Outage)
_LINK_FIELDS = {
    "jitter_s": Field(_NON_NEGATIVE, required=False),
    "loss": Field(_PROBABILITY, required=False),
    "fifo": Field(Flag(), required=False),
    "outages": Field(ListOf(_OUTAGE), required=False),
}


def _link(default_delay_s: float | None) -> Record:
    """A link record; with a default delay, ``delay_s`` may be set too."""
    if default_delay_s is None:
        return Record(_LINK_FIELDS, build=LinkSettings)
    return Record(
        {"delay_s": Field(_NON_NEGATIVE, required=False), **_LINK_FIELDS},
        build=lambda **kw: LinkSettings(**{"delay_s": default_delay_s, **kw}),
    )


_LINKS = Record(
    {
        "cpfc_to_der": Field(_link(None), required=False),
        "measurement_to_cpfc": Field(_link(None), required=False),
        "der_to_availability": Field(_link(0.1), required=False),
        "availability_to_cpfc": Field(_link(0.1), required=False),
    },
    build=Links,
)

_AGENT_NAME = r"(?:cpfc|measurement|availability|der/" + _IDENTIFIER + r")"
_FAULTS = Record(
    {
        "der_offline": Field(
            ListOf(
                Record(
                    {
                        "der": Field(Text(_IDENTIFIER_WHAT, pattern=_IDENTIFIER)),
                        "t_s": Field(_NON_NEGATIVE),
                        "duration_s": Field(_POSITIVE),
                    },
                    build=DEROffline,
                )
            ),
            required=False,
        ),
        "crash": Field(
            ListOf(
                Record(
                    {
                        "agent": Field(
                            Text(
                                "cpfc, measurement, availability or der/<id>",
                                pattern=_AGENT_NAME,
                            )
                        ),
                        "t_s": Field(_NON_NEGATIVE),
                    },
                    build=AgentCrash,
                )
            ),
            required=False,
        ),
    },
    build=Faults,
)

_RUNTIME = Record(
    {
        "seed": Field(_Count(), required=False),
        "pi_period_s": Field(_PERIOD, required=False),
        "measurement_period_s": Field(_PERIOD, required=False),
        "rest_of_grid_w": Field(Number("a number"), required=False),
        "heartbeat_period_s": Field(_PERIOD, required=False),
        "heartbeat_timeout_s": Field(_PERIOD, required=False),
        "watchdog_timeout_s": Field(_PERIOD, required=False),
        "weights_period_s": Field(_PERIOD, required=False),
        "measurement_timeout_s": Field(_PERIOD, required=False),
        "links": Field(_LINKS, required=False),
        "faults": Field(_FAULTS, required=False),
    },
    build=Runtime,
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
        "runtime": Field(_RUNTIME, required=False),
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
    if "runtime" in values:
        _check_runtime(values["runtime"], known, scenario.duration_s)


def _check_runtime(runtime: Runtime, known: list[str], duration_s: float) -> None:
    """Check the runtime section against itself, the DERs and the scenario."""
    links = runtime.links
    slack = runtime.heartbeat_period_s + links.der_to_availability.jitter_s
    if runtime.heartbeat_timeout_s <= slack:
        raise SchemaError(
            "runtime.heartbeat_timeout_s",
            f"must exceed heartbeat_period_s + der_to_availability.jitter_s ({slack:g}), "
            f"got {runtime.heartbeat_timeout_s:g}",
        )
    slack = runtime.pi_period_s + links.cpfc_to_der.jitter_s
    if runtime.watchdog_timeout_s <= slack:
        raise SchemaError(
            "runtime.watchdog_timeout_s",
            f"must exceed pi_period_s + cpfc_to_der.jitter_s ({slack:g}), "
            f"got {runtime.watchdog_timeout_s:g}",
        )
    for i, fault in enumerate(runtime.faults.der_offline):
        if fault.der not in known:
            raise SchemaError(
                f"runtime.faults.der_offline[{i}].der",
                f"unknown DER id '{fault.der}' (known: {', '.join(known)})",
            )
    for i, crash in enumerate(runtime.faults.crash):
        where = f"runtime.faults.crash[{i}]"
        if crash.agent.startswith("der/") and crash.agent[4:] not in known:
            raise SchemaError(
                f"{where}.agent", f"unknown DER id '{crash.agent[4:]}' (known: {', '.join(known)})"
            )
        if crash.t_s > duration_s:
            raise SchemaError(
                f"{where}.t_s",
                f"must not exceed scenario.duration_s ({duration_s:g}), got {crash.t_s:g}",
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
        runtime=values.get("runtime", Runtime()),
    )
