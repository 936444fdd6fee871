"""Load and validate an adnmesh configuration file (YAML) into frozen pydantic models.

The format is the models below: one class per section, one field per key. A field's docstring
(with its unit) documents it here and is its description in the JSON Schema that
``adnmesh schema config`` prints. Checks within a section are that section's validators;
relations across sections (known DER ids, event times inside the scenario) are
:class:`ConfigFile`'s. The first problem found is raised as a :class:`~adnmesh.errors.ConfigError`
whose message is one line naming the file and the key path, e.g.
``configs/x.yaml: ders[3].p_inst_w: must be a positive number, got -2``.

Every key that is not a field is rejected (with the closest valid key suggested). Units are in
the key names: ``_w`` watts, ``_s`` seconds, ``_pct`` percent. To add a section, derive its
model from :class:`Section` and add one field of that type where it belongs (e.g. to
:class:`ConfigFile`); its validators and JSON Schema come with it.
"""

from __future__ import annotations

import difflib
import hashlib
import math
import re
from collections.abc import Callable, Hashable, Iterable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, get_args

import yaml
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field
from pydantic import ValidationError, model_validator
from pydantic_core import ErrorDetails, PydanticCustomError

from adnmesh.errors import ConfigError
from adnmesh.files import FileRefused, read_regular, unreadable
from adnmesh.names import (AGENT_PATTERN, FAULT_KINDS, ICT_LINKS, ID_PATTERN, PER_DER_KIND,
                           SINGLE_AGENT_KINDS, der_id_of)

__all__ = [
    "DER_TYPES", "PT1_RISE_TIME_FACTOR", "AvailabilityChange", "Config", "ConfigFile",
    "Constraints", "DER", "DeviceTLS", "Fault", "IEC104Plant", "SunSpecPlant", "GridLimits", "GridModel", "Guard", "TapChanger", "LinkSettings", "Links", "Outage",
    "MAX_CONFIG_BYTES", "MAX_DELAY_PER_LAG", "MAX_IN_FLIGHT", "MAX_SPAN_PER_DELAY", "PRefStep",
    "CAPABILITY_PRESETS", "QRefStep", "QU", "Reactive", "Runtime", "VoltageStep",
    "Scenario", "Section", "Study", "Maintenance", "MinOutputShare", "json_schema", "load_config",
    "Hierarchy", "HierarchyAdn", "HierarchyConstraints", "HierarchyFile", "HvGrid", "MAX_ADNS",
    "SiteRestart",
    "hierarchy_json_schema", "is_hierarchy_file", "load_hierarchy",
]

DERType = Literal["WT", "CHP", "PV", "HYDRO", "GEN"]
DER_TYPES: tuple[str, ...] = get_args(DERType)
"""Accepted DER types: wind turbine, combined heat and power plant (biomass), photovoltaic
plant, hydro plant, generator of another kind (docs/models.md#der-types)."""

PT1_RISE_TIME_FACTOR = math.log(9.0)
"""10 %→90 % rise time of a first-order lag in units of its time constant: ln(0.9/0.1) = 2.1972.

The paper writes ``T_d = T_rise,d / 2.197``: this number rounded (docs/method.md#reference-model).
"""

# --- value types: bounds a user would expect (sim time is int64 ns: 1e6 s is far inside) --------

_MAX_W, _MAX_DELAY_S, _MAX_TIME_S, _MAX_DERS, _MAX_EVENTS = 1e10, 3600.0, 1e6, 1000, 100_000

MAX_DELAY_PER_LAG = 500
"""The loop's longest delay (``t_com_s`` with the sampled PI's hold plus the largest
``t_delay_s``, or ``t_meas_s``) may be at most this many times the fastest DER's time constant.

The step responses of tuning and analysis (:mod:`adnmesh.loopmodel.step_response`) step at
half the fastest time constant (or finer) and hold every delay in a ring of samples: at the
limit a ring of 1,000 samples per candidate, and a SimBench table takes ~7x as long to tune as
the reference case (measured: a 22 s CHP reaction time, 111 s; a PV rise time of 5 ms, 88 s;
1.3x the limit (a 60 s reaction time) 189 s; 5x (a 1 ms rise time) over 240 s; ``t_rise_s:
1e-12`` ran out of memory)."""

MAX_IN_FLIGHT = 1000
"""At most this many messages of one key may be on their way on a link at once: its delay plus
jitter (plus the largest ``link_delay`` fault on it) over the period of the messages (P_Y:
``pi_period_s`` on ``cpfc_to_der``; P_IP: ``measurement_period_s`` on ``measurement_to_cpfc``;
heartbeats: ``heartbeat_period_s`` on ``der_to_availability``). A receiver holds every message
until its delivery time and takes at most 4,096 per key (:data:`adnmesh.wire.gate.HELD_MAX`,
against a flood); the reference case holds 10. ``pi_period_s: 1e-6`` with ``t_com_s: 0.1``
(100,000 on their way) stalled the run."""

MAX_SPAN_PER_DELAY = 2500
"""The slowest DER's time constant plus the loop delay (``t_com_s`` with the hold, the largest
``t_delay_s`` and ``t_meas_s``) may be at most this many times the shortest forward delay
(``t_com_s`` with the hold plus the smallest ``t_delay_s``).

A step response is simulated for at least 4 x the slowest time constant plus delay, with steps
that grow at most to the shortest forward delay: at the limit ~10,000 steps per candidate
(measured: a CHP rise time of 600 s, 1.0x the limit, tunes SimBench in 61 s; 1,260 s, 2x, in
335 s; 3,600 s, 6x, over 240 s)."""
_IDENTIFIER = rf"^{ID_PATTERN}$"
_AGENT = rf"^{AGENT_PATTERN}$"
_SUNSPEC_POINT = r"^[0-9]{1,5}\.[A-Za-z][A-Za-z0-9_]{0,39}$"
_HOST = r"^[A-Za-z0-9]([A-Za-z0-9.:-]*[A-Za-z0-9])?$"
_ISO_TIME = r"^\d{4}-\d{2}-\d{2}([T ]\d{2}:\d{2})?$"
_PATTERNS = {
    _IDENTIFIER: "an identifier (letters, digits, '_', '-'; starting with a letter)",
    _AGENT: f"{', '.join(SINGLE_AGENT_KINDS)} or {PER_DER_KIND}/<id>",
    _ISO_TIME: "a date (2016-06-01) or a time (2016-06-01T12:00), without a time zone",
    _SUNSPEC_POINT: "MODEL.POINT of a SunSpec model (704.WSet)",
    _HOST: "a host name or IP address",
}
"""How a pattern reads in an error message: ``must be <words>, got ...``."""


def _nonzero(value: float) -> float:
    if value == 0:
        raise PydanticCustomError("nonzero", "must be a non-zero number")
    return value


_Identifier = Annotated[str, Field(pattern=_IDENTIFIER, max_length=64)]
_Name = Annotated[str, Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$")]
_Power = Annotated[float, Field(gt=0, le=_MAX_W)]
_PowerOrZero = Annotated[float, Field(ge=0, le=_MAX_W)]
_Balance = Annotated[float, Field(ge=-_MAX_W, le=_MAX_W)]
_Change = Annotated[_Balance, AfterValidator(_nonzero),
                    Field(json_schema_extra={"not": {"const": 0}})]
_Delay = Annotated[float, Field(ge=0, le=_MAX_DELAY_S)]
_Lag = Annotated[float, Field(gt=0, le=_MAX_DELAY_S)]
_Period = Annotated[float, Field(ge=1e-6, le=_MAX_DELAY_S)]
_Time = Annotated[float, Field(ge=0, le=_MAX_TIME_S)]
_Duration = Annotated[float, Field(gt=0, le=_MAX_TIME_S)]
_CosPhi = Annotated[float, Field(ge=0.5, le=1.0)]
_PerUnitVoltage = Annotated[float, Field(gt=0, le=2)]
CapabilityPreset = Literal["cos_phi_0.95", "cos_phi_0.925", "cos_phi_0.90", "unity"]
CAPABILITY_PRESETS: dict[str, tuple[float, float]] = {
    "cos_phi_0.95": (0.95, 0.95), "cos_phi_0.925": (0.925, 0.925),
    "cos_phi_0.90": (0.90, 0.90), "unity": (1.0, 1.0)}
"""Preset -> (least cos phi under-excited, least cos phi over-excited), both taken at P_inst
(docs/models.md#reactive-power-capability): ``cos_phi_0.95`` is the MV connection rules' usual
range (VDE-AR-N 4110: Q from -0.33 to +0.33 P_inst), the wider ones what HV connections and
many inverters offer, ``unity`` no reactive power."""
_T = TypeVar("_T")
_Events = Annotated[tuple[_T, ...], Field(strict=False, max_length=_MAX_EVENTS)]
"""A YAML list of at most 100,000 items, read as a tuple."""


def _problem(at: tuple, message: str) -> PydanticCustomError:
    """An error at key path ``at`` below the value being validated; ``message`` is one line."""
    return PydanticCustomError("adnmesh", "{message}", {"message": message, "at": at})


def _not_after(t_s: float, duration_s: float, at: tuple) -> None:
    if t_s > duration_s:
        raise _problem(at, f"must not exceed scenario.duration_s ({duration_s:g}), got {t_s:g}")


def _one_line_descriptions(schema: dict[str, Any], _: type) -> None:
    """Join the lines of docstrings in a model's JSON Schema (one paragraph each)."""
    for entry in (schema, *schema.get("properties", {}).values()):
        if "description" in entry:
            entry["description"] = " ".join(entry["description"].split())


class Section(BaseModel):
    """Base of every config section: frozen and hashable; numbers finite, booleans not numbers;
    an unknown key is an error naming the closest valid one."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False,
                              use_attribute_docstrings=True,
                              field_title_generator=lambda name, _: name,
                              json_schema_extra=_one_line_descriptions)

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        for key in data if isinstance(data, dict) else ():
            if key not in cls.model_fields:
                close = difflib.get_close_matches(str(key), list(cls.model_fields), n=1)
                hint = (f"did you mean '{close[0]}'?" if close
                        else f"valid keys: {', '.join(cls.model_fields)}")
                raise _problem((str(key),), f"unknown key ({hint})")
        return data


_Host = Annotated[str, Field(min_length=1, max_length=253, pattern=_HOST)]
_Port = Annotated[int, Field(ge=1, le=65535)]
_SunSpecPoint = Annotated[str, Field(pattern=_SUNSPEC_POINT)]
_Ioa = Annotated[int, Field(ge=1, le=16_777_215)]
_DeviceTimeout = Annotated[float, Field(ge=0.01, le=60.0)]


class DeviceTLS(Section):
    """TLS on the link to a plant device (Modbus/TCP Security for SunSpec, IEC 62351-3 for
    104); paths relative to the config file."""

    ca: _Name
    """The CA certificate (PEM) the device's certificate must chain to."""
    cert: _Name | None = None
    """The gateway's own certificate (PEM), if the device asks for one."""
    key: _Name | None = None
    """The gateway's private key (PEM), with cert."""
    server_cert: _Name | None = None
    """The device simulator's certificate (PEM; ``adnmesh device`` and up's simulators)."""
    server_key: _Name | None = None
    """The device simulator's private key (PEM), with server_cert."""

    @model_validator(mode="after")
    def _pairs(self) -> DeviceTLS:
        for cert, key in (("cert", "key"), ("server_cert", "server_key")):
            if (getattr(self, cert) is None) != (getattr(self, key) is None):
                raise _problem((key if getattr(self, key) is None else cert,),
                               f"{cert} and {key} come together")
        return self


class SunSpecPointNames(Section):
    """Which SunSpec points the gateway uses, as ``model.point`` of the SunSpec DER
    information models (checked against the model definitions by ``check`` and ``up``)."""

    p_set: _SunSpecPoint = "704.WSet"
    """Active power set-point, W."""
    q_set: _SunSpecPoint = "704.VarSet"
    """Reactive power set-point, var."""
    p_meas: _SunSpecPoint = "701.W"
    """Measured active power, W."""
    q_meas: _SunSpecPoint = "701.Var"
    """Measured reactive power, var."""
    status: _SunSpecPoint = "701.ConnSt"
    """Connection status (1: connected)."""
    stamp: _SunSpecPoint | None = "122.Tms"
    """Time stamp of the measurement, s (null: the device has none; no staleness check)."""


class IEC104Addresses(Section):
    """Information object addresses of the DER's points on its RTU."""

    p_set: _Ioa = 100
    """Active power set-point command (C_SE_NC_1, short float, W)."""
    q_set: _Ioa = 101
    """Reactive power set-point command (C_SE_NC_1, short float, var)."""
    p_meas: _Ioa = 200
    """Measured active power (M_ME_TF_1, short float with time tag, W)."""
    q_meas: _Ioa = 201
    """Measured reactive power (M_ME_TF_1, var)."""
    status: _Ioa = 300
    """Connected and operating (M_SP_TB_1, single point with time tag)."""

    @model_validator(mode="after")
    def _distinct(self) -> IEC104Addresses:
        seen: dict[int, str] = {}
        for name, address in self.model_dump().items():
            if address in seen:
                raise _problem((name,), f"duplicate information object address {address} "
                                        f"(also {seen[address]})")
            seen[address] = name
        return self


class _Device(Section):
    """What every plant device link has (see SunSpecPlant, IEC104Plant)."""

    host: _Host = "127.0.0.1"
    """Host name or IP address of the device."""
    port: _Port
    """TCP port of the device."""
    timeout_s: _DeviceTimeout = 0.5
    """Longest wait for one answer of the device, s: beyond it the device counts as silent."""
    poll_period_s: _Period | None = None
    """How often the gateway reads the measurement, s (default runtime.measurement_period_s)."""
    write_interval_s: _Delay = 0.0
    """Shortest time between two set-point writes, s (0: each new set-point at once). Newer
    set-points that come sooner are held and the newest is written when the interval has
    passed: at most this much delay, to spare a device that cannot take a write per
    pi_period_s."""
    write_deadband_pct: Annotated[float, Field(ge=0, le=10)] = 0.0
    """A new set-point pair is not written while P and Q both stay within this percentage of
    the DER's p_inst_w of the pair last written (the device runs within the dead band of it)."""
    stale_after_s: _Duration = 2.0
    """The measurement counts as stale when its time stamp has not advanced for this long, s."""
    retry_s: _Duration = 1.0
    """After an error, the gateway tries the device again this often, s."""
    simulator: bool = False
    """adnmesh up starts ``adnmesh device`` for this DER on host:port (a device simulator
    running the DER's model in real time) before the agents, and ends it after them."""
    tls: DeviceTLS | None = None
    """TLS on the link (see DeviceTLS)."""


class SunSpecPlant(_Device):
    """A plant device on Modbus TCP with the SunSpec DER models (docs/devices.md)."""

    protocol: Literal["sunspec"]
    """Modbus TCP with the SunSpec DER information models 701/704."""
    unit_id: Annotated[int, Field(ge=0, le=255)] = 1
    """Modbus unit id of the device."""
    points: SunSpecPointNames = SunSpecPointNames()
    """The points used (see SunSpecPointNames)."""


class IEC104Plant(_Device):
    """A plant device (an RTU) on IEC 60870-5-104 (docs/devices.md)."""

    protocol: Literal["iec104"]
    """IEC 60870-5-104."""
    common_address: Annotated[int, Field(ge=1, le=65534)] = 1
    """Common address (station) of the DER's points."""
    addresses: IEC104Addresses = IEC104Addresses()
    """Information object addresses (see IEC104Addresses)."""

    @model_validator(mode="after")
    def _no_tls(self) -> IEC104Plant:
        if self.tls is not None:
            raise _problem(("tls",), "not supported for iec104: the IEC 104 library (c104 "
                                     "2.2) cannot verify a server over TLS; keep the link on a "
                                     "trusted network (docs/devices.md#security)")
        return self


DevicePlant = Annotated[SunSpecPlant | IEC104Plant, Field(discriminator="protocol")]


def _simulated_is_none(value: Any) -> Any:
    """``plant: simulated`` is the default, no device; a mapping must name its protocol."""
    if value == "simulated" or value is None:
        return None
    if not isinstance(value, dict):
        raise _problem((), f"must be simulated or a device (a mapping with protocol: sunspec "
                           f"or iec104), got {value!r:.60}")
    if value.get("protocol") not in ("sunspec", "iec104"):
        raise _problem(("protocol",), f"must be sunspec or iec104, got "
                                      f"{value.get('protocol')!r:.60}")
    return value


class DER(Section):
    """One distributed energy resource used as an actuator."""

    id: _Identifier
    """Identifier, unique in the config; also a bus key segment (adn/<grid>/der/<id>/...)."""
    type: DERType
    """WT (wind turbine), CHP (combined heat and power plant, biomass), PV (photovoltaic plant),
    HYDRO (hydro plant) or GEN (another kind); picks the detailed model (docs/models.md)."""
    p_inst_w: _Power
    """Installed active power P_inst,d, W; the controller's C_d."""
    t_delay_s: _Delay
    """Reaction time T_delay,d, s."""
    t_rise_s: _Lag
    """10 %-90 % rise time T_rise,d of the active power response, s."""
    sgen: _Name
    """Name of the static generator in the SimBench grid that this DER drives."""
    p_sched_w: _PowerOrZero = 0.0
    """Scheduled active power P_sched,d, W, at most p_inst_w: the DER falls back to it when it
    loses contact with the CPFC, and P_Y adds to it (p_avail - p_sched is its upward reserve)."""
    s_inst_va: _Power | None = None
    """Apparent power rating S_inst,d, VA (default p_inst_w): P^2 + Q^2 stays within its
    square; reactive.priority says which gives way when it binds."""
    q_capability: CapabilityPreset | None = None
    """Its reactive power range by a named preset (default reactive.capability; see
    docs/models.md#reactive-power-capability)."""
    cos_phi_under: _CosPhi | None = None
    """Override of the preset: the least cos phi under-excited (absorbing Q), taken at p_inst_w:
    Q_min = -p_inst_w tan(acos(cos_phi_under)); 1 allows no absorption."""
    cos_phi_over: _CosPhi | None = None
    """Override of the preset: the least cos phi over-excited (injecting Q), taken at p_inst_w:
    Q_max = p_inst_w tan(acos(cos_phi_over)); 1 allows no injection."""
    t_delay_q_s: _Delay | None = None
    """Reaction time of the reactive power T_delay,d^Q, s (default by type: docs/models.md)."""
    t_rise_q_s: _Lag | None = None
    """10 %-90 % rise time of the reactive power T_rise,d^Q, s (default by type)."""
    q_sched_var: _Balance = 0.0
    """Scheduled reactive power Q_sched,d, var (generator convention: positive injects,
    over-excited): its fallback and what Q_Y adds to."""
    plant: Annotated[DevicePlant | None, BeforeValidator(_simulated_is_none)] = None
    """Where the DER's power comes from: ``simulated`` (the default: its model, in the DER
    agent) or a device behind a real protocol, reached by the DER agent as its gateway (a
    mapping with ``protocol: sunspec`` or ``protocol: iec104``; wall clock only: ``up --clock
    realtime``; docs/devices.md)."""
    model: Annotated[dict[Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$", max_length=40)],
                          Annotated[float, Field(ge=-_MAX_W, le=_MAX_W)]] | None,
                     Field(strict=False)] = None
    """Overrides of the detailed model's parameters (runtime.der_models: detailed), named as
    they are there, in W, s and W/s, e.g. {t_lag_s: 0.2, ramp_up_w_per_s: 5.0e+5}; see
    adnmesh analyze CONFIG --der-models."""

    @model_validator(mode="after")
    def _schedule_within_rating(self) -> DER:
        if self.p_sched_w > self.p_inst_w:
            raise _problem(("p_sched_w",), f"must not exceed p_inst_w ({self.p_inst_w:g}), "
                                           f"got {self.p_sched_w:g}")
        if self.s_inst_va is not None and self.s_inst_va < self.p_inst_w:
            raise _problem(("s_inst_va",), f"must be at least p_inst_w ({self.p_inst_w:g}), "
                                           f"got {self.s_inst_va:g}")
        return self

    @property
    def apparent_va(self) -> float:
        """S_inst,d, VA (``s_inst_va``, else ``p_inst_w``)."""
        return self.p_inst_w if self.s_inst_va is None else self.s_inst_va


class GridLimits(Section):
    """The band a grid sample must stay in (the summary flags any sample outside it)."""

    v_min_pu: Annotated[float, Field(gt=0, le=2)] = 0.9
    """Lowest bus voltage, p.u."""
    v_max_pu: Annotated[float, Field(gt=0, le=2)] = 1.1
    """Highest bus voltage, p.u."""
    loading_max_pct: Annotated[float, Field(gt=0, le=1000)] = 100.0
    """Highest line and transformer loading, %."""

    @model_validator(mode="after")
    def _a_band(self) -> GridLimits:
        if self.v_min_pu >= self.v_max_pu:
            raise _problem(("v_min_pu",), f"must be less than v_max_pu ({self.v_max_pu:g}), "
                                          f"got {self.v_min_pu:g}")
        return self


class Guard(Section):
    """The grid guard (docs/method.md#grid-guard): when a bus voltage or a line or transformer
    loading comes within a margin of its limit, the DERs whose movement in a direction would
    worsen it (by their sensitivities) are blocked for that direction; the CPFC uses the table
    entry of the DERs still usable that way."""

    mode: Literal["directional", "block", "off"] = "directional"
    """directional: block DERs per direction (P and Q) by their sensitivity; block: hold the
    whole control (output and integrator) while a limit is violated, the practice of waiting
    for the tap changer to restore the band; off: watch and count only."""
    v_margin_pu: Annotated[float, Field(ge=0, le=0.2)] = 0.01
    """A voltage within this of its limit engages the guard, p.u."""
    loading_margin_pct: Annotated[float, Field(ge=0, le=100)] = 5.0
    """A loading within this of its limit engages the guard, %."""
    v_release_pu: Annotated[float, Field(gt=0, le=0.2)] = 0.005
    """Hysteresis: a voltage is released this far inside the engaging level, p.u."""
    loading_release_pct: Annotated[float, Field(gt=0, le=100)] = 5.0
    """Hysteresis: a loading is released this far below the engaging level, %."""
    release_s: _Period = 2.0
    """A limit stays engaged until it has been inside its release level this long, s."""
    share: Annotated[float, Field(gt=0, le=1)] = 0.2
    """A DER is blocked when its sensitivity worsens the limit by at least this fraction of the
    most sensitive DER's (dimensionless)."""
    refresh_s: _Period = 1.0
    """The sensitivities of an engaged limit are refreshed this often as the operating point
    moves, s."""
    clip_references: bool = True
    """A P_ref (Q_ref) beyond what the DERs can reach within the grid limits and their
    capability (the feasible region's extent, computed when the CPFC starts) is clipped to it
    and said, not chased into wind-up; also in mode off."""


class TapChanger(Section):
    """The on-load tap changer of the HV/MV transformer (docs/models.md#tap-changer): it keeps
    the voltage of its MV busbar (or the grid's extreme voltages) within a band, one tap step
    after the voltage has been outside for delay_s. Tap range and step come from the net's
    data."""

    regulates: Literal["busbar", "extremes"] = "busbar"
    """busbar: its MV busbar's voltage within v_set_pu +- dead_band_pu (the usual regulator);
    extremes: every bus voltage within the limits less extremes_margin_pu (wide-area control
    from feeder measurements)."""
    v_set_pu: _PerUnitVoltage | None = None
    """The busbar voltage it keeps, p.u. (default: the study case's, so it starts at rest)."""
    extremes_margin_pu: Annotated[float, Field(ge=0, le=0.2)] = 0.01
    """regulates extremes: the band is the voltage limits moved inwards by this, p.u."""
    dead_band_pu: Annotated[float, Field(gt=0, le=0.2)] = 0.015
    """Half width of its dead band, p.u. (more than half a tap step, or it hunts)."""
    delay_s: _Period = 30.0
    """The voltage must be outside the band this long before a tap step, s (and again before
    each further step)."""
    trafo: Annotated[int, Field(ge=0, le=100_000)] | None = None
    """The transformer (pandapower trafo index) whose tap it moves (default: the one at the
    interconnection point)."""


class GridModel(Section):
    """The AC power flow behind P_IP — of the SimBench grid (simbench_code) or of a pandapower
    net file (pandapower_net): the measurement agent solves it at every sample, the DERs'
    sgens set to their infeeds."""

    pandapower_net: _Name | None = None
    """A pandapower net file (as pandapower.to_json writes it, or to_sqlite: .sqlite, .sqlite3,
    .db), relative to the config, instead of the SimBench grid; its content's hash keys the grid
    cache."""
    study_case: Annotated[str, Field(pattern=r"^[A-Za-z0-9]+$", max_length=16)] = "lW"
    """Study case of the loads, the other generators and the slack voltage (a row of the net's
    loadcases table: hL, n1, hW, hPV, lW, lPV); also the DERs' available power. A pandapower
    net without a loadcases table is used as saved (leave study_case out)."""
    time_step: Annotated[int, Field(ge=0, le=10**6)] | None = None
    """Instead of a study case: this quarter hour of the net's year of profiles (0 = 1 January
    00:00; SimBench: 0 to 35135), for the loads, the other generators and the DERs' available
    power; the slack voltage as saved."""
    load_model: Literal["impedance", "power"] = "impedance"
    """Loads as constant impedances (docs/method.md#reference-case) or constant power."""
    report_period_s: _Period = 1.0
    """The grid's extremes (voltages, loadings, Q_IP) are sent this often, s."""
    limits: GridLimits = GridLimits()
    """The band of voltages and loadings."""
    guard: Guard = Guard()
    """The grid guard: how the control keeps to the limits."""
    tap_changer: TapChanger | None = None
    """The HV/MV transformer's on-load tap changer in the loop (none: its tap stays)."""

    @model_validator(mode="after")
    def _levels_apart(self) -> GridModel:
        lim, g = self.limits, self.guard
        reach = 2 * (g.v_margin_pu + g.v_release_pu)
        if lim.v_max_pu - lim.v_min_pu <= reach:
            raise _problem(("guard", "v_margin_pu"), (
                f"the voltage band {lim.v_min_pu:g} to {lim.v_max_pu:g} p.u. is too narrow for "
                f"a margin of {g.v_margin_pu:g} and a release of {g.v_release_pu:g} p.u. on "
                "each side: the guard would block both ways for good"))
        if lim.loading_max_pct <= g.loading_margin_pct + g.loading_release_pct:
            raise _problem(("guard", "loading_margin_pct"), (
                f"a margin of {g.loading_margin_pct:g} % and a release of "
                f"{g.loading_release_pct:g} % leave no loading below the {lim.loading_max_pct:g}"
                " % limit to release at"))
        tap = self.tap_changer
        if tap is not None and tap.regulates == "extremes" and \
                lim.v_max_pu - lim.v_min_pu <= 2 * tap.extremes_margin_pu:
            raise _problem(("tap_changer", "extremes_margin_pu"), (
                f"{tap.extremes_margin_pu:g} p.u. inside both limits of the band "
                f"{lim.v_min_pu:g} to {lim.v_max_pu:g} p.u. leaves no band"))
        return self

    @model_validator(mode="after")
    def _one_operating_point(self) -> GridModel:
        if self.time_step is not None and "study_case" in self.model_fields_set:
            raise _problem(("time_step",), "give a study_case or a time_step, not both")
        return self


_Scale = Annotated[float, Field(gt=0, le=100)]
_Shift = Annotated[float, Field(ge=-_MAX_DELAY_S, le=_MAX_DELAY_S)]
_ScaleRange = Annotated[tuple[_Scale, _Scale], Field(strict=False)]
_ShiftRange = Annotated[tuple[_Shift, _Shift], Field(strict=False)]


def _ordered(pair: tuple, what: str) -> tuple:
    if pair[0] > pair[1]:
        raise _problem((what,), f"the low end {pair[0]:g} is above the high end {pair[1]:g}")
    return pair


class TypeUncertainty(Section):
    """How far one DER type's dynamics may stray from its configured reference model."""

    lag_scale: _ScaleRange = (1.0, 1.0)
    """``[b_lo, b_hi]``: every time constant of the type's DERs times one factor ``b`` in this
    interval (dimensionless; ``[1, 1]``: as configured)."""
    delay_add_s: _ShiftRange = (0.0, 0.0)
    """``[lo, hi]``: added to every dead time of the type's DERs (s; a dead time never goes
    below 0)."""

    @model_validator(mode="after")
    def _intervals(self) -> TypeUncertainty:
        _ordered(self.lag_scale, "lag_scale")
        _ordered(self.delay_add_s, "delay_add_s")
        return self


class RobustSet(Section):
    """The uncertainty set every table entry is certified over (docs/tuning.md#robust-tables):
    the actuator structures, and per DER type an interval of the time-constant factor ``b`` and
    of added dead time. DERs of one type share one ``b`` and one added dead time; types vary
    independently of each other."""

    models: Annotated[tuple[Literal["pt1", "pt2", "rhpz"], ...],
                      Field(strict=False, min_length=1, max_length=3)] = ("pt1",)
    """Actuator structures (docs/method.md#model-uncertainty), each with the type's time
    constant."""
    lag_scale: _ScaleRange = (1.0, 1.0)
    """``[b_lo, b_hi]`` for every type not under ``types``."""
    delay_add_s: _ShiftRange = (0.0, 0.0)
    """Added dead time ``[lo, hi]`` for every type not under ``types``, s."""
    types: dict[DERType, TypeUncertainty] = {}
    """Per DER type, its own intervals (replacing the two above for it)."""

    @model_validator(mode="after")
    def _intervals(self) -> RobustSet:
        _ordered(self.lag_scale, "lag_scale")
        _ordered(self.delay_add_s, "delay_add_s")
        if len(set(self.models)) != len(self.models):
            raise _problem(("models",), "name each structure once")
        return self

    def __hash__(self) -> int:                  # a frozen section is hashable: its dict too
        return hash((self.models, self.lag_scale, self.delay_add_s,
                     tuple(sorted(self.types.items()))))

    def of_type(self, der_type: str) -> TypeUncertainty:
        """The intervals of ``der_type``."""
        return self.types.get(der_type) or TypeUncertainty(lag_scale=self.lag_scale,
                                                           delay_add_s=self.delay_add_s)


class Constraints(Section):
    """Design constraints every table entry must satisfy (docs/method.md#design-constraints)."""

    disk_margin_min: Annotated[float, Field(gt=0, lt=2)] = 1.5
    """Lowest acceptable balanced disk margin alpha (dimensionless, 0 < alpha < 2)."""
    overshoot_max_pct: Annotated[float, Field(gt=0, le=100)] = 1.0
    """Overshoot of the closed-loop step response must stay below this, % of the final value."""
    settling_band_pct: Annotated[float, Field(gt=0, le=50)] = 5.0
    """Band for the settling time, % of the final value."""
    sampled_pi: bool = True
    """Design for the sampled PI of the runtime: its zero-order hold delays P_Y by half a
    sampling period on average, so the design loop's T_com is t_com_s + runtime.pi_period_s /
    2 (false: the continuous PI of the paper, T_com = t_com_s)."""
    robust: RobustSet | None = None
    """Certify every entry over this uncertainty set as well as on the reference model (none:
    the reference model alone)."""


class PRefStep(Section):
    """A step of the reference P_ref at the interconnection point."""

    t_s: _Time
    """Time of the step, s from the start of the scenario."""
    delta_w: _Change
    """Change of P_ref, W (non-zero; positive raises the reference)."""


class QRefStep(Section):
    """A step of the reactive power reference Q_ref at the interconnection point."""

    t_s: _Time
    """Time of the step, s from the start of the scenario."""
    delta_var: _Change
    """Change of Q_ref, var (non-zero; positive: more reactive power into the upper grid)."""


class VoltageStep(Section):
    """The voltage at the interconnection point's upper side from a time on (the input of the
    Q(U) characteristic)."""

    t_s: _Time
    """Time of the change, s from the start of the scenario."""
    u_pu: _PerUnitVoltage
    """The voltage from then on, p.u."""


class AvailabilityChange(Section):
    """DERs becoming available or unavailable."""

    t_s: _Time
    """Time of the change, s from the start of the scenario."""
    ders: Annotated[tuple[_Identifier, ...], Field(strict=False, min_length=1,
                                                   max_length=_MAX_DERS)]
    """Ids of the DERs concerned."""
    available: bool
    """Their new availability."""


class Scenario(Section):
    """A time-domain run: duration and events (all DERs are available at t = 0)."""

    duration_s: _Duration
    """Length of the run, s."""
    p_ref_steps: _Events[PRefStep] = ()
    """Reference steps in chronological order."""
    availability: _Events[AvailabilityChange] = ()
    """Availability changes in chronological order."""
    q_ref_steps: _Events[QRefStep] = ()
    """Reactive power reference steps in chronological order (reactive.mode q)."""
    u_hv_steps: _Events[VoltageStep] = ()
    """The upper side's voltage over the run (reactive.mode q_u; before the first: the Q(U)
    characteristic's u_ref_pu), chronological."""

    @model_validator(mode="after")
    def _chronological(self) -> Scenario:
        for key in ("p_ref_steps", "availability", "q_ref_steps", "u_hv_steps"):
            previous = 0.0
            for i, event in enumerate(getattr(self, key)):
                _not_after(event.t_s, self.duration_s, (key, i, "t_s"))
                if event.t_s < previous:
                    raise _problem((key, i, "t_s"), "must not be earlier than the previous "
                                                    f"event ({previous:g}), got {event.t_s:g}")
                previous = event.t_s
        return self


# --- the runtime section (optional; how `adnmesh up` runs the scenario) ----------------------


class Outage(Section):
    """A window in which an ICT link loses every message sent."""

    t_s: _Time
    """Start of the outage, s of scenario time."""
    duration_s: _Duration
    """Length of the outage, s; messages sent in [t_s, t_s + duration_s) are lost."""


class LinkSettings(Section):
    """The ICT channel model of one logical link (sender side decides every message's fate)."""

    delay_s: _Delay = None  # type: ignore[assignment]  # None: not set (default, not an input)
    """Fixed delay, s; None (not set) for the links whose delay is the config's t_com_s
    (CPFC -> DERs) and t_meas_s (measurement -> CPFC); 0.1 s for the others unless set."""
    jitter_s: _Delay = 0.0
    """Extra delay drawn uniformly from [0, jitter_s) per message, s."""
    loss: Annotated[float, Field(ge=0, lt=1)] = 0.0
    """Probability that a message is lost, in [0, 1)."""
    fifo: bool = True
    """Keep the send order (a message is never delivered before an earlier one on the link)."""
    outages: _Events[Outage] = ()
    """Windows in which every message is lost."""


def _link(delay: str | float) -> Any:
    """LinkSettings whose delay is the config key ``delay`` (str; ``delay_s`` only as null, as
    :meth:`~pydantic.BaseModel.model_dump` writes it) or defaults to ``delay`` s (float)."""

    def before(value: Any) -> Any:
        if not isinstance(value, dict):
            return value
        if isinstance(delay, float):
            return {"delay_s": delay, **value}
        if value.get("delay_s") is not None:
            raise _problem(("delay_s",), f"unknown key (this link's delay is {delay})")
        return {key: v for key, v in value.items() if key != "delay_s"}

    extra = {} if isinstance(delay, float) else {"properties": {"delay_s": False}}
    return Annotated[LinkSettings, BeforeValidator(before), Field(json_schema_extra=extra)]


_ComLink, _MeasLink, _MonitorLink = _link("t_com_s"), _link("t_meas_s"), _link(0.1)


class Links(Section):
    """ICT links of the runtime; the DER -> measurement path is physical (no delay, no loss)."""

    cpfc_to_der: _ComLink = LinkSettings()
    """P_Y and weights from the CPFC to the DERs (delay t_com_s)."""
    measurement_to_cpfc: _MeasLink = LinkSettings()
    """P_IP from the measurement to the CPFC (delay t_meas_s)."""
    der_to_availability: _MonitorLink = LinkSettings(delay_s=0.1)
    """Heartbeats from the DERs to the availability monitor (delay 0.1 s unless set)."""
    availability_to_cpfc: _MonitorLink = LinkSettings(delay_s=0.1)
    """The availability vector SI to the CPFC (delay 0.1 s unless set)."""


FaultKind = Literal[FAULT_KINDS]
LinkName = Literal[ICT_LINKS]
_FAULT_TARGET = {"link_outage": "link", "link_loss": "link", "link_delay": "link",
                 "der_offline": "der", "kill": "agent", "ict_outage": None}


class Fault(Section):
    """An injected fault (the same kinds ``adnmesh fault`` injects into a running run)."""

    kind: FaultKind
    """link_outage, link_loss, link_delay (of one link), der_offline (one DER cut off from the
    ICT both ways), ict_outage (every ICT link), kill (SIGKILL of an agent's process)."""
    t_s: _Time
    """Start, s of scenario time (a kill: when)."""
    duration_s: _Duration | None = None
    """Length, s (not for a kill; without it the fault lasts to the end)."""
    link: LinkName | None = None
    """The link of a link fault."""
    der: _Identifier | None = None
    """The DER of der_offline."""
    agent: Annotated[str, Field(pattern=_AGENT, max_length=68)] | None = None
    """The agent a kill ends: cpfc, measurement, availability or der/<id>."""
    probability: Annotated[float, Field(ge=0, le=1)] | None = None
    """link_loss: probability that a message sent in the window is lost."""
    delay_s: _Delay | None = None
    """link_delay: extra delay of every message sent in the window, s."""
    restart_after_s: _Duration | None = None
    """kill: a new process of the agent starts this long after the kill, s (none: never)."""

    @model_validator(mode="after")
    def _fields_of_its_kind(self) -> Fault:
        needed = _FAULT_TARGET[self.kind]
        wanted = {needed} - {None}
        wanted |= {"link_loss": {"probability"}, "link_delay": {"delay_s"}}.get(self.kind, set())
        allowed = wanted | ({"restart_after_s"} if self.kind == "kill" else {"duration_s"})
        for name in ("link", "der", "agent", "probability", "delay_s", "duration_s",
                     "restart_after_s"):
            if name in wanted and getattr(self, name) is None:
                raise _problem((name,), f"required for a {self.kind} fault")
            if name not in allowed and getattr(self, name) is not None:
                raise _problem((name,), f"not a key of a {self.kind} fault")
        return self


class Runtime(Section):
    """How ``adnmesh up`` runs the scenario (the optional ``runtime:`` section)."""

    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] = 0
    """Seed of the random streams of the ICT channel model."""
    pi_period_s: _Period = 0.01
    """Sampling period of the CPFC's PI controller, s."""
    measurement_period_s: _Period = 0.01
    """Sampling period of P_IP (the DERs report their infeed at the same instants), s."""
    rest_of_grid_w: _Balance = 0.0
    """Constant part of P_IP besides the DER infeeds (loads, other generators), W. The initial
    reference is rest_of_grid_w + sum(p_sched_w), the operating point with P_Y = 0."""
    heartbeat_period_s: _Period = 1.0
    """Period of the DERs' heartbeats, s."""
    heartbeat_timeout_s: _Period = 2.5
    """The availability monitor marks a DER unavailable after this long without a heartbeat, s
    (more than heartbeat_period_s + der_to_availability.jitter_s)."""
    watchdog_timeout_s: _Period = 1.0
    """A DER falls back to P_sched after this long without a valid command, s (more than
    pi_period_s + cpfc_to_der.jitter_s)."""
    weights_period_s: _Period = 1.0
    """The CPFC repeats the weights W with P_Y this often (besides on every switch), s."""
    der_models: Literal["reference", "detailed"] = "reference"
    """The DERs' dynamics in a run: the reference model (the PT1 tuning and analyses use) or the
    detailed models (WT Type 4B-like, CHP, PV; docs/method.md#detailed-der-models), limited to the
    available power."""
    measurement_timeout_s: _Period = 0.25
    """The CPFC holds output and integrator after this long without a measurement, s (more than
    measurement_period_s + measurement_to_cpfc.jitter_s)."""
    realtime_tolerance_s: Annotated[float, Field(gt=0, le=_MAX_DELAY_S)] | None = None
    """On the realtime clock, an event (message or timer) processed more than this late is an
    overrun (the machine does not keep up with --speed), s of sim time; the measurement, whose
    inputs have no delay, also processes each instant this much later. Default: 5 % of the
    shortest ICT link delay."""
    ders_per_process: Annotated[int, Field(ge=1, le=1000)] = 1
    """How many DER agents ``adnmesh up`` runs in one process (scale mode, open profile only):
    1, the default, gives every DER its own process, as a plant has its own controller; more
    hosts up to that many DERs, in config order, on one Zenoh session per process, for
    hundreds of DERs on one machine. The messages and the recording are the same either way;
    a process is then a failure domain: an internal error in one DER's code ends its
    process and every DER in it (an injected kill still ends one DER only)."""
    agent_start: Literal["fork", "exec"] = "fork"
    """How ``adnmesh up`` starts the agent processes on its host: ``fork``, from one
    interpreter that has imported the agent programs and loaded this config once
    (docs/runtime.md#how-agents-start: start-up in a fraction of the time, the imported pages
    shared); ``exec``, each as its own ``python -m adnmesh.agents.<kind>`` program. The
    agents' messages and the recording are the same either way."""
    model_watch: Literal["off", "event", "retune"] = "off"
    """After each step of P_ref, the CPFC compares P_IP's response with what its table entry
    was certified for (docs/method.md#model-watch): ``event`` says a step over its design on
    ``event/cpfc`` (kind ``model_mismatch``: which entry and DERs, each figure against its
    design); ``retune`` also fits each DER type's dynamics to that step and tunes the subset
    again, certified over the uncertainty set the fit implies, and switches to that entry."""
    links: Links = Links()
    """ICT channel model per link."""
    faults: _Events[Fault] = ()
    """Faults injected into the run (see Fault)."""

    @model_validator(mode="after")
    def _timeouts_exceed_periods(self) -> Runtime:
        for timeout, period, link in (("heartbeat_timeout_s", "heartbeat_period_s",
                                       "der_to_availability"),
                                      ("watchdog_timeout_s", "pi_period_s", "cpfc_to_der"),
                                      ("measurement_timeout_s", "measurement_period_s",
                                       "measurement_to_cpfc")):
            slack = getattr(self, period) + getattr(self.links, link).jitter_s
            if getattr(self, timeout) <= slack:
                raise _problem((timeout,), f"must exceed {period} + {link}.jitter_s "
                                           f"({slack:g}), got {getattr(self, timeout):g}")
        return self


class QU(Section):
    """The Q(U) characteristic at the interconnection point: Q_ref from the upper side's
    voltage, a dead band around u_ref_pu and a slope beyond it, limited."""

    u_ref_pu: _PerUnitVoltage = 1.0
    """Voltage at the centre of the dead band, p.u."""
    dead_band_pu: Annotated[float, Field(ge=0, le=0.5)] = 0.01
    """Half width of the dead band, p.u.: no change of Q_ref within u_ref_pu +- this."""
    slope_var_per_pu: Annotated[float, Field(ge=0, le=_MAX_W * 100)] = 1.0e+8
    """Q_ref falls by this much per p.u. above the band (injection lowers, absorption raises the
    voltage) and rises by it below, var per p.u."""
    q_max_var: _PowerOrZero = 1.0e+6
    """The characteristic's reactive power at most, either way, var (above Q_ref's start)."""


class Reactive(Section):
    """Reactive power at the interconnection point: a second gain-scheduled PI (Q) beside the
    one of P (the optional ``reactive:`` section; docs/method.md#reactive-power)."""

    capability: CapabilityPreset = "cos_phi_0.95"
    """The DERs' reactive power range unless a DER names its own (see CAPABILITY_PRESETS)."""
    priority: Literal["p", "q"] = "p"
    """When a DER's apparent power limit binds: p keeps its active power (Q gives way), q its
    reactive power (P gives way)."""
    mode: Literal["q", "q_u", "cos_phi"] = "q"
    """What Q_ref follows: q its start plus scenario.q_ref_steps; q_u the Q(U) characteristic
    of scenario.u_hv_steps; cos_phi the power factor cos_phi at the interface (Q_ref from
    P_ref)."""
    q_u: QU = QU()
    """The Q(U) characteristic (mode q_u)."""
    cos_phi: _CosPhi = 1.0
    """Power factor at the interconnection point (mode cos_phi)."""
    cos_phi_q_with_p: bool = True
    """mode cos_phi: Q flows the way P flows (into the upper grid when P does); false: against."""
    rest_of_grid_var: _Balance = 0.0
    """Constant part of Q_IP besides the DERs' reactive infeeds without a grid model, var."""


_IsoTime = Annotated[str, Field(pattern=_ISO_TIME)]
"""A date (``2016-06-01``) or a time (``2016-06-01T12:00``), in the profiles' local time (the
config loader reads YAML dates as text: they are checked here, not by the YAML parser)."""


class Maintenance(Section):
    """A maintenance window: the DERs are out of service (no infeed, not available) from start
    (inclusive) to end (exclusive)."""

    ders: Annotated[tuple[_Identifier, ...], Field(strict=False, min_length=1,
                                                   max_length=_MAX_DERS)]
    """The DERs in maintenance."""
    start: _IsoTime
    """First day or time of the window (a date is its 00:00)."""
    end: _IsoTime
    """Day or time the window ends (exclusive; a date is its 00:00)."""

    @model_validator(mode="after")
    def _order(self) -> "Maintenance":
        import datetime
        times = {}
        for key in ("start", "end"):
            text = getattr(self, key)
            try:
                times[key] = datetime.datetime.fromisoformat(text.replace(" ", "T"))
            except ValueError:
                raise _problem((key,), f"must be a date or time that exists, got {text}") \
                    from None
        if times["end"] <= times["start"]:
            raise _problem(("end",), f"must be after start ({self.start}), got {self.end}")
        return self


_Share = Annotated[float, Field(ge=0, lt=1)]


class MinOutputShare(Section):
    """The least available power at which a DER counts as available, per type, as a share of
    its p_inst_w (below it a wind turbine is near cut-in, a PV plant near dark)."""

    WT: _Share = 0.01
    """Wind turbines."""
    CHP: _Share = 0.01
    """Combined heat and power plants."""
    PV: _Share = 0.01
    """Photovoltaic plants."""
    HYDRO: _Share = 0.01
    """Hydro plants."""
    GEN: _Share = 0.01
    """Generators of another kind."""


class Study(Section):
    """How ``adnmesh study`` reads a year of profiles (docs/study.md): which DERs are
    available, at which schedule, and the service it checks."""

    min_output_share: MinOutputShare = MinOutputShare()
    """Per DER type: a DER is available only while its available power exceeds this share of
    its p_inst_w."""
    maintenance: _Events[Maintenance] = ()
    """Maintenance windows (a calendar)."""
    ict_availability: Annotated[float, Field(gt=0, le=1)] = 1.0
    """Probability that a DER's link to the CPFC works in an interval (independent draws from
    runtime.seed; 1: always)."""
    schedule: Literal["share", "config"] = "share"
    """A DER's schedule in an interval: share - the share of its available power that its
    p_sched_w is at the config's operating point; config - its p_sched_w (at most what it can
    deliver)."""
    service_w: _Power = 1.0e+6
    """Size of the service checked both ways (a step of P_ref up and one down), W."""
    service_s: _Lag = 10.0
    """Within this time (the step's settling time), s."""


class ConfigFile(Section):
    """An adnmesh configuration: the content of a config file (YAML)."""

    model_config = ConfigDict(title="adnmesh config")

    grid: _Identifier
    """Name of the grid, used as the <grid> segment of bus keys (adn/<grid>/...)."""
    simbench_code: _Name | None = None
    """SimBench code of the grid, e.g. 1-MV-rural--0-no_sw (the grid model's net unless
    grid_model.pandapower_net names another)."""
    t_com_s: _Lag
    """Communication delay CPFC -> DERs T_com, s."""
    t_meas_s: _Lag
    """Measurement delay T_meas, s."""
    constraints: Constraints = Constraints()
    """Tuning constraints."""
    ders: Annotated[tuple[DER, ...], Field(strict=False, min_length=1, max_length=_MAX_DERS)]
    """The actuators, in file order."""
    scenario: Scenario
    """The time-domain scenario."""
    runtime: Runtime = Runtime()
    """How the distributed runtime runs the scenario."""
    grid_model: GridModel | None = None
    """The power flow behind P_IP; without it P_IP = runtime.rest_of_grid_w + the infeeds."""
    reactive: Reactive | None = None
    """Control Q_IP too (docs/method.md#reactive-power); without it every DER runs at its
    q_sched_var."""
    study: Study = Study()
    """How the year study reads the profiles (adnmesh study)."""
    t_rise_is: Literal["rise_time", "time_constant"] = "rise_time"
    """What the DERs' t_rise_s is: their 10-90 % rise time (the reference model's time constant
    is then t_rise_s / ln 9, as the paper has it) or the time constant itself."""
    extends: _Name | None = None
    """A config this one is a variant of (a file name relative to this file): its keys are
    taken, and this file's keys replace them (mappings merged key by key, lists and values
    replaced). File names in either are relative to this file."""

    @property
    def design_t_com_s(self) -> float:
        """T_com of the loop tuning and the analyses use, s (see constraints.sampled_pi)."""
        hold = self.runtime.pi_period_s / 2 if self.constraints.sampled_pi else 0.0
        return self.t_com_s + hold

    def t_lag_s(self, der: DER) -> float:
        """Time constant ``T_d`` of the reference PT1 model of ``der``, s (see ``t_rise_is``)."""
        return der.t_rise_s / self.rise_per_lag

    @property
    def rise_per_lag(self) -> float:
        """``t_rise_s`` over the reference model's time constant: ln 9, or 1."""
        return PT1_RISE_TIME_FACTOR if self.t_rise_is == "rise_time" else 1.0

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
        known, ids = {der.id: der for der in self.ders}, list(ids)
        for der_id in ids:
            if der_id not in known:
                raise ConfigError(f"unknown DER id '{der_id}' (known: {_listing(known)})")
        return tuple(known[der_id] for der_id in ids)

    @model_validator(mode="after")
    def _numerics(self) -> ConfigFile:
        """The two relations of delays and time constants the loop numerics need (see
        :data:`MAX_DELAY_PER_LAG` and :data:`MAX_SPAN_PER_DELAY`)."""
        lags = [self.t_lag_s(d) for d in self.ders]
        delays = [d.t_delay_s for d in self.ders]
        fast, slow = lags.index(min(lags)), lags.index(max(lags))
        late, early = delays.index(max(delays)), delays.index(min(delays))
        t_com = self.design_t_com_s
        com = "t_com_s" + (" + runtime.pi_period_s / 2" if t_com != self.t_com_s else "")
        forward = t_com + delays[late]
        longest, what = ((forward, f"{com} + ders[{late}].t_delay_s")
                         if forward >= self.t_meas_s else (self.t_meas_s, "t_meas_s"))
        unit = "t_rise_s / ln 9" if self.t_rise_is == "rise_time" else "t_rise_s"
        if longest > MAX_DELAY_PER_LAG * lags[fast]:
            least = longest / MAX_DELAY_PER_LAG * self.rise_per_lag
            raise _problem(("ders", fast, "t_rise_s"),
                           f"too fast for the loop's delays: its time constant ({unit}) "
                           f"{lags[fast]:.4g} s is less than 1/{MAX_DELAY_PER_LAG} of the "
                           f"longest delay, {what} = {longest:.4g} s, more than the step "
                           f"responses of tuning and analysis can hold; at least {least:.4g} "
                           f"(or shorter delays), got {self.ders[fast].t_rise_s:g}")
        shortest = t_com + delays[early]
        loop = forward + self.t_meas_s
        if lags[slow] + loop > MAX_SPAN_PER_DELAY * shortest:
            room = MAX_SPAN_PER_DELAY * shortest - loop
            where = f"{com} + ders[{early}].t_delay_s = {shortest:.4g} s"
            if room <= 0:
                raise _problem(("t_com_s",),
                               f"too short for the loop's other delays: the shortest forward "
                               f"delay, {where}, is less than 1/{MAX_SPAN_PER_DELAY} of the "
                               f"loop delay {loop:.4g} s, too many steps for the step responses "
                               f"of tuning and analysis, got {self.t_com_s:g}")
            raise _problem(("ders", slow, "t_rise_s"),
                           f"too slow for the shortest forward delay: its time constant "
                           f"({unit}) {lags[slow]:.4g} s plus the loop delay {loop:.4g} s is "
                           f"more than {MAX_SPAN_PER_DELAY} times {where}, too many steps for "
                           f"the step responses of tuning and analysis; at most "
                           f"{room * self.rise_per_lag:.4g} (or longer delays), got "
                           f"{self.ders[slow].t_rise_s:g}")
        return self

    @model_validator(mode="after")
    def _in_flight(self) -> ConfigFile:
        """At most :data:`MAX_IN_FLIGHT` messages of one key on their way on a link."""
        links, rt = self.runtime.links, self.runtime
        for period, link, delay in (("pi_period_s", "cpfc_to_der", self.t_com_s),
                                    ("measurement_period_s", "measurement_to_cpfc",
                                     self.t_meas_s),
                                    ("heartbeat_period_s", "der_to_availability",
                                     links.der_to_availability.delay_s)):
            extra = max((f.delay_s for f in rt.faults
                         if f.kind == "link_delay" and f.link == link), default=0.0)
            span = delay + getattr(links, link).jitter_s + extra
            if span > MAX_IN_FLIGHT * getattr(rt, period):
                what = " + its largest link_delay fault" if extra else ""
                raise _problem(("runtime", period),
                               f"too short for {link}: {span:g} s of delay (with its jitter"
                               f"{what}) would hold {span / getattr(rt, period):.4g} messages "
                               f"of one key on their way, more than {MAX_IN_FLIGHT} (a "
                               f"receiver holds at most 4,096); at least "
                               f"{span / MAX_IN_FLIGHT:.4g}, got {getattr(rt, period):g}")
        return self

    @model_validator(mode="after")
    def _grid_source(self) -> ConfigFile:
        """A grid model names one net: a SimBench code or a pandapower net file."""
        model = self.grid_model
        if model is None:
            return self
        if model.pandapower_net is None and self.simbench_code is None:
            raise _problem(("grid_model",), "needs the net: simbench_code (a SimBench code) or "
                                            "grid_model.pandapower_net (a file)")
        if model.pandapower_net is not None and self.simbench_code is not None:
            raise _problem(("grid_model", "pandapower_net"),
                           "names a net beside simbench_code; keep one of the two")
        return self

    @model_validator(mode="after")
    def _relations(self) -> ConfigFile:
        _unique([d.id for d in self.ders], lambda i: ("ders", i, "id"), "DER id")
        _unique([d.sgen for d in self.ders], lambda i: ("ders", i, "sgen"), "sgen")
        known = dict.fromkeys(self.der_ids())
        for i, change in enumerate(self.scenario.availability):
            at = ("scenario", "availability", i, "ders")
            _unique(change.ders, lambda j, at=at: (*at, j), "DER id")
            for j, der_id in enumerate(change.ders):
                _known(der_id, known, (*at, j))
        for i, window in enumerate(self.study.maintenance):
            at = ("study", "maintenance", i, "ders")
            _unique(window.ders, lambda j, at=at: (*at, j), "DER id")
            for j, der_id in enumerate(window.ders):
                _known(der_id, known, (*at, j))
        simulated = [(i, f"{d.plant.host}:{d.plant.port}") for i, d in enumerate(self.ders)
                     if d.plant is not None and d.plant.simulator]
        _unique([a for _, a in simulated], lambda j: ("ders", simulated[j][0], "plant", "port"),
                "device simulator address")
        for i, fault in enumerate(self.runtime.faults):
            at = ("runtime", "faults", i)
            if fault.der is not None:
                _known(fault.der, known, (*at, "der"))
            if fault.agent is not None and der_id_of(fault.agent) is not None:
                _known(der_id_of(fault.agent), known, (*at, "agent"))
            _not_after(fault.t_s, self.scenario.duration_s, (*at, "t_s"))
        robust = self.constraints.robust
        types = dict.fromkeys(d.type for d in self.ders)
        for der_type in robust.types if robust is not None else ():
            if der_type not in types:
                raise _problem(("constraints", "robust", "types", der_type),
                               f"no DER of this type (the DERs' types: {', '.join(types)})")
        return self


class Config(ConfigFile):
    """A validated configuration and the file it came from (see :func:`load_config`)."""

    path: Path
    """The file it was loaded from."""
    sha256: str
    """SHA-256 of the file's bytes (hex), to tie results to the exact file."""
    quantity: Literal["P", "Q"] = "P"
    """The quantity the DERs' fields describe: P as written, Q in the reactive view
    (:func:`adnmesh.reactive.reactive_view`: each DER's reactive capability, dynamics and
    schedule in its P fields)."""

    @property
    def unit(self) -> str:
        """The unit of the quantity the DERs' fields describe: ``W`` (P) or ``var`` (Q)."""
        return "var" if self.quantity == "Q" else "W"

    def features(self) -> frozenset[str]:
        """The optional parts the run has, by the names the protocol table's ``feature`` uses:
        ``reactive`` (a reactive section), ``guard`` (a grid model whose guard is on)."""
        found = set()
        if self.reactive is not None:
            found.add("reactive")
        if self.grid_model is not None and self.grid_model.guard.mode != "off":
            found.add("guard")
        return frozenset(found)

    def pandapower_net_path(self) -> Path | None:
        """The grid model's pandapower net file, resolved next to the config (None if the
        grid model is SimBench's or there is none)."""
        if self.grid_model is None or self.grid_model.pandapower_net is None:
            return None
        return (Path(self.path).parent / self.grid_model.pandapower_net).resolve()


def _listing(ids: Iterable[str], most: int = 20) -> str:
    ids = list(ids)
    return ", ".join(ids[:most]) + (f", ... ({len(ids)} in all)" if len(ids) > most else "")


def _known(der_id: str, known: dict[str, None], at: tuple) -> None:
    if der_id not in known:
        raise _problem(at, f"unknown DER id '{der_id}' (known: {_listing(known)})")


def _unique(values: Sequence[str], path_of: Callable[[int], tuple], what: str) -> None:
    """Raise at the second occurrence of a value; ``path_of(i)`` is the key path of item i."""
    first: dict[str, int] = {}
    for i, value in enumerate(values):
        if value in first:
            also = _path(path_of(first[value]))
            raise _problem(path_of(i), f"duplicate {what} '{value}' (also {also})")
        first[value] = i


# --- pydantic's errors as one line: the key path and the problem -----------------------------

_PROBLEMS = {
    "missing": "required key is missing",
    "model_type": "must be a mapping, got {got}",
    "tuple_type": "must be a list, got {got}",
    "float_type": "must be a number, got {got}",
    "int_type": "must be an integer, got {got}",
    "bool_type": "must be true or false, got {got}",
    "string_type": "must be a string, got {got}",
    "string_too_short": "must not be empty",
    "string_too_long": "must have at most {max_length} characters, got {got}",
    "string_pattern_mismatch": "must be {pattern}, got {got}",
    "literal_error": "must be one of {expected}, got {got}",
    "too_short": "must have at least {min_length} item(s), got {actual_length}",
    "too_long": "must have at most {max_length} items, got {actual_length}",
    "greater_than": "must be greater than {gt}, got {got}",
    "greater_than_0": "must be a positive number, got {got}",
    "greater_than_equal": "must be at least {ge}, got {got}",
    "greater_than_equal_0": "must be a non-negative number, got {got}",
    "less_than": "must be less than {lt}, got {got}",
    "less_than_equal": "must be at most {le}, got {got}",
    "nonzero": "must be a non-zero number, got {got}",
    "whole_ms": "must be a whole number of milliseconds (the cascade takes every delay "
                "exactly), got {got}",
    "finite_number": "must be a finite number, got {got}",
}
"""Problem per pydantic error type (``_0``: bound zero); others: pydantic's text, one line."""


def _show(value: object) -> str:
    """Render a value read from a document for an error message (short, one line)."""
    if value is None or isinstance(value, bool):
        return {None: "nothing (null)", True: "true", False: "false"}[value]
    if isinstance(value, dict | list):
        return "a mapping" if isinstance(value, dict) else "a list"
    if isinstance(value, str):
        return repr(value if len(value) <= 40 else value[:37] + "...")
    text = repr(value) if isinstance(value, int | float) else type(value).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def _path(loc: Iterable[int | str]) -> str:
    """``("ders", 3, "p_inst_w")`` -> ``"ders[3].p_inst_w"``; ``"top level"`` for ``()``."""
    path = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")
    return path or "top level"


def _describe(error: ErrorDetails) -> str:
    """``<key path>: <problem>`` of one pydantic error."""
    ctx = dict(error.get("ctx", {}))
    if error["type"] == "adnmesh":
        return f"{_path((*error['loc'], *ctx['at']))}: {ctx['message']}"
    kind = error["type"]
    if kind in ("greater_than", "greater_than_equal") and next(iter(ctx.values())) == 0:
        kind += "_0"
    ctx = {k: f"{v:g}" if isinstance(v, float) else v for k, v in ctx.items()}
    if "pattern" in ctx:
        ctx["pattern"] = _PATTERNS.get(ctx["pattern"], f"matching {ctx['pattern']}")
    template = _PROBLEMS.get(kind, " ".join(error["msg"].split()) + ", got {got}")
    return f"{_path(error['loc'])}: {template.format(**ctx, got=_show(error['input']))}"


# --- reading the file ---------------------------------------------------------------------------


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser: 10x faster
    """SafeLoader that rejects duplicate keys and reads ``2e6`` / ``2.0e6`` as floats.

    (YAML 1.1, which PyYAML implements, reads a float exponent without a sign as a string.)
    """

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == _MERGE:
                continue
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable):  # PyYAML reports it
                break
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"duplicate key '{key}'",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_MERGE, _FLOAT = "tag:yaml.org,2002:merge", "tag:yaml.org,2002:float"
_TIMESTAMP = "tag:yaml.org,2002:timestamp"    # dates stay text: PyYAML's constructor raises a
                                              # traceback for 2016-13-01; the fields check them
_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_FLOAT, _TIMESTAMP)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(_FLOAT, re.compile(
    r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+ |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF) |\.(?:nan|NaN|NAN))$""", re.X), list("-+0123456789."))


def _one_line(text: object) -> str:
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


MAX_CONFIG_BYTES = 16 * 2**20
"""The largest config file read, bytes (16 MiB: the 1,000-DER example is 0.2 MiB; every event
list at its 100,000 entries, a few MiB each)."""


def _read(path: Path) -> bytes:
    try:
        return read_regular(path, MAX_CONFIG_BYTES)
    except FileRefused as exc:
        raise ConfigError(f"{path}: {exc.strerror}; a config must be a regular file of at most "
                          f"{MAX_CONFIG_BYTES // 2**20} MiB") from None
    except OSError as exc:
        raise ConfigError(unreadable(path, exc, "config file")) from None


MAX_EXTENDS = 8
"""The longest chain of configs extending one another."""


def _document(path: Path, chain: tuple[Path, ...]) -> tuple[object, bytes]:
    """The YAML document of ``path`` with the configs it extends merged in, and the bytes of
    every file read (the base's first), for the config's hash."""
    data = _read(path)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    document = _parse_yaml(path, text)
    if not isinstance(document, dict) or "extends" not in document:
        return document, data
    base = document.pop("extends")
    if base is None:
        return document, data
    if not isinstance(base, str) or not base.strip() or re.search(r"[\x00-\x1f\x7f]", base):
        raise ConfigError(f"{path}: extends: must be the file name of a config, got {base!r}")
    base_path = path.parent / base
    if base_path.resolve() in chain:
        raise ConfigError(f"{path}: extends: {base} leads back to this file (a circle)")
    if len(chain) > MAX_EXTENDS:
        raise ConfigError(f"{path}: extends: more than {MAX_EXTENDS} configs extend one "
                          "another")
    try:
        parent, parent_data = _document(base_path, (*chain, base_path.resolve()))
    except ConfigError as exc:
        raise ConfigError(f"{path}: extends {base}: {exc}") from None
    if not isinstance(parent, dict):
        raise ConfigError(f"{base_path}: a config extended by {path} must be a mapping")
    return _merged(parent, document), parent_data + data


def _base_of(path: Path):
    """The ``extends`` value of the config in ``path`` (read again: small, and only for an
    error message), None if it has none."""
    try:
        document = yaml.load(_read(path).decode("utf-8"), Loader=_Loader)  # noqa: S506
    except (ConfigError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return document.get("extends") if isinstance(document, dict) else None


def _merged(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys put in: mappings merged key by key, everything else
    (values, lists, a mapping over a non-mapping) replaced."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


def json_schema() -> dict[str, Any]:
    """Return the JSON Schema (draft 2020-12) of a config file, with units in the descriptions."""
    schema = ConfigFile.model_json_schema()
    required = schema.pop("required")       # a config that extends another may leave them out
    schema["if"] = {"not": {"required": ["extends"]}}
    schema["then"] = {"required": required}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


# --- a hierarchy: an upper controller over MV ADNs (docs/hierarchy.md) --------------------------

MAX_ADNS = 11
"""The most ADNs one upper controller drives (its table has 2^n - 1 entries)."""


def _whole_ms(value: float) -> float:
    if abs(value * 1000 - round(value * 1000)) > 1e-6:
        raise PydanticCustomError("whole_ms", "must be a whole number of milliseconds")
    return value


_MsDelay = Annotated[_Delay, AfterValidator(_whole_ms)]
_MsLag = Annotated[_Lag, AfterValidator(_whole_ms)]


class HierarchyAdn(Section):
    """One MV ADN as an actuator of the upper controller."""

    id: _Identifier
    """Its name at the upper level (the upper table's actuator id)."""
    config: _Name
    """Its own adnmesh config (a file name relative to this file)."""
    t_com_s: _MsDelay
    """Inter-site delay upper CPFC -> this ADN's CPFC, s (whole milliseconds)."""
    keep_steps: bool = False
    """In the hierarchy's run, keep the steps of P_ref of the ADN's own scenario as its
    schedule (default: its reference is its operating point plus the offset from above; the
    availability changes of its scenario always apply)."""
    hv_bus: _Name | None = None
    """With ``hv_grid``: the name of the HV bus the ADN is attached at (its HV/MV
    transformer's HV side)."""
    replaces: Annotated[tuple[_Name, ...], Field(strict=False, max_length=100)] | None = None
    """With ``hv_grid``: the loads and static generators (by name) at ``hv_bus`` that stood
    for this grid in the HV net and are taken out of it (default: those whose profile, or
    type, begins with ``mv_``: SimBench's stand-ins for its MV grids)."""


class SiteRestart(Section):
    """A site router killed and started again during ``adnmesh up`` (docs/hierarchy.md#sites):
    at sim time ``t_s`` (the sim clock holds the run there until the site is back; what the
    run sends is what it sends without the restart)."""

    adn: _Identifier
    """The ADN whose site router it is."""
    t_s: Annotated[float, Field(gt=0, le=_MAX_TIME_S)]
    """When, sim s."""
    down_s: Annotated[float, Field(ge=0, le=3)] = 1.0
    """How long the router stays down, wall s (its agents wait 10 s for it before they stop;
    its start and their reconnection take a few more)."""


class HierarchyConstraints(Section):
    """Design constraints of the upper table, checked on the exact cascade."""

    disk_margin_min: Annotated[float, Field(gt=0, lt=2)] = 1.5
    """Lowest acceptable balanced disk margin alpha of the upper loop (0 < alpha < 2)."""
    overshoot_max_pct: Annotated[float, Field(gt=0, le=100)] = 1.0
    """The upper step response's overshoot must stay below this, % of the final value."""
    settling_band_pct: Annotated[float, Field(gt=0, le=50)] = 5.0
    """Band for the settling time, % of the final value."""


class HvGrid(Section):
    """The HV grid the ADNs are attached to: its AC power flow is the upper level's plant
    (the upper P_IP is its exchange with the level above, the ADNs' exchanges injected at
    their HV buses)."""

    simbench_code: _Name | None = None
    """A SimBench HV code (e.g. ``1-HV-mixed--0-sw``)."""
    pandapower_net: _Name | None = None
    """Or a pandapower net file (relative to the hierarchy file)."""
    study_case: Annotated[str, Field(pattern=r"^[A-Za-z0-9]+$", max_length=16)] | None = None
    """The study case of its loads, generators and slack voltage (a row of the net's
    loadcases table; default: lW for a SimBench code, the net as saved for a file)."""
    load_model: Literal["impedance", "power"] = "impedance"
    """Its loads as constant impedances or constant power."""

    @model_validator(mode="after")
    def _one_net(self) -> HvGrid:
        if (self.simbench_code is None) == (self.pandapower_net is None):
            raise _problem(("simbench_code",), "give the HV net as simbench_code or as "
                                               "pandapower_net, one of the two")
        return self


class HierarchyFile(Section):
    """An upper controller over MV ADNs: the content of a hierarchy file (YAML)."""

    model_config = ConfigDict(title="adnmesh hierarchy")

    name: _Identifier
    """Name of the upper grid."""
    t_meas_s: _MsLag
    """Delay of the upper measurement (the exchange the upper controller acts on), s (whole
    milliseconds)."""
    constraints: HierarchyConstraints = HierarchyConstraints()
    """Design constraints of the upper table, checked on the exact cascade."""
    adns: Annotated[tuple[HierarchyAdn, ...], Field(strict=False, min_length=1,
                                                    max_length=MAX_ADNS)]
    """The ADNs the upper controller drives, in file order."""
    scenario: Scenario = Scenario(duration_s=600.0)
    """The upper level's run (``adnmesh cascade --run``): its duration, the steps of the
    reference of the sum of the ADNs' exchanges, ADNs leaving and returning (by id)."""
    faults: _Events[Fault] = ()
    """Faults of the upper level's run; ``der_offline`` of an ADN cuts its site off from the
    level above."""
    site_restarts: _Events[SiteRestart] = ()
    """``adnmesh up``: site routers killed and started again (by ADN id)."""
    hv_grid: HvGrid | None = None
    """The HV grid between the ADNs and the level above (default: none, the upper P_IP is the
    sum of the ADNs' exchanges); every ADN then names its ``hv_bus``."""

    @model_validator(mode="after")
    def _attached(self) -> HierarchyFile:
        for i, adn in enumerate(self.adns):
            if self.hv_grid is not None and adn.hv_bus is None:
                raise _problem(("adns", i, "hv_bus"), "is needed with hv_grid: the HV bus the "
                                                      "ADN is attached at")
            if self.hv_grid is None and (adn.hv_bus, adn.replaces) != (None, None):
                raise _problem(("adns", i, "hv_bus" if adn.hv_bus else "replaces"),
                               "needs hv_grid: the HV net it is part of")
        return self

    @model_validator(mode="after")
    def _distinct(self) -> HierarchyFile:
        _unique([a.id for a in self.adns], lambda i: ("adns", i, "id"), "ADN id")
        ids = [a.id for a in self.adns]
        for i, adn in enumerate(self.adns):
            if adn.id == self.name:
                raise _problem(("adns", i, "id"), f"must differ from the hierarchy's name "
                                                  f"{self.name!r} (each grid has its own keys)")
            if adn.t_com_s < 0.001:
                raise _problem(("adns", i, "t_com_s"), "must be at least 0.001 s (the upper "
                                                       f"level's shortest delay), got {adn.t_com_s:g}")
        named = [(("faults", i, "der"), f.der) for i, f in enumerate(self.faults)
                 if f.der is not None]
        named += [(("faults", i, "agent"), f.agent.removeprefix("der/"))
                  for i, f in enumerate(self.faults)
                  if f.agent is not None and f.agent.startswith("der/")]
        named += [(("site_restarts", i, "adn"), r.adn) for i, r in enumerate(self.site_restarts)]
        for i, restart in enumerate(self.site_restarts):
            _not_after(restart.t_s, self.scenario.duration_s, ("site_restarts", i, "t_s"))
        _unique([f"{r.adn} at {r.t_s:g} s" for r in self.site_restarts],
                lambda i: ("site_restarts", i), "site restart")
        named += [(("scenario", "availability", i, "ders", j), d)
                  for i, c in enumerate(self.scenario.availability) for j, d in enumerate(c.ders)]
        for at, adn in named:
            if adn not in ids:
                raise _problem(at, f"unknown ADN id {adn!r} (known: {', '.join(ids)})")
        return self


class Hierarchy(HierarchyFile):
    """A validated hierarchy file and the file it came from (see :func:`load_hierarchy`)."""

    path: Path
    """The file it was loaded from."""
    sha256: str
    """SHA-256 of the file's bytes (hex)."""

    def config_path(self, adn: HierarchyAdn) -> Path:
        """The ADN's config file, resolved next to the hierarchy file."""
        return (Path(self.path).parent / adn.config).resolve()

    def hv_net_path(self) -> Path | None:
        """The HV grid's pandapower net file, resolved next to the hierarchy file (None
        without one)."""
        if self.hv_grid is None or self.hv_grid.pandapower_net is None:
            return None
        return (Path(self.path).parent / self.hv_grid.pandapower_net).resolve()


def hierarchy_json_schema() -> dict[str, Any]:
    """Return the JSON Schema (draft 2020-12) of a hierarchy file."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **HierarchyFile.model_json_schema()}


def load_hierarchy(path: str | Path) -> Hierarchy:
    """Load and validate a hierarchy file (the ADNs' configs are not read).

    Raises
    ------
    ConfigError
        For the first problem found, one line naming the file and the key path.
    """
    return _loaded(Path(path), HierarchyFile, Hierarchy, "hierarchy file")


def load_config(path: str | Path) -> Config:
    """Load, validate and return the configuration in ``path``.

    Parameters
    ----------
    path : str or Path
        A YAML file in the format of ``configs/simbench.yaml`` (see :class:`ConfigFile`).

    Returns
    -------
    Config
        The validated configuration.

    Raises
    ------
    ConfigError
        For the first problem found; the message is one line naming the file and the key path.
    """
    return _loaded(Path(path), ConfigFile, Config, "config")


def is_hierarchy_file(path: str | Path) -> bool:
    """Whether the file at ``path`` reads as a hierarchy file (it names ``adns``, no ``ders``);
    False for anything else, a file that does not read included (its loader says why)."""
    try:
        document, _ = _document(Path(path), (Path(path).resolve(),))
    except (ConfigError, OSError):
        return False
    return isinstance(document, dict) and "adns" in document and "ders" not in document


def _not_the_other_kind(path: Path, document, content_type) -> None:
    """A hierarchy file given where a config is expected (it names ``adns``, no ``ders``), or
    the other way round, is said as such in one line (not as its first unknown key)."""
    if not isinstance(document, dict):
        return
    if content_type is ConfigFile and "adns" in document and "ders" not in document:
        raise ConfigError(f"{path}: a hierarchy file (it names adns), not an ADN's config: "
                          "'adnmesh cascade FILE' tunes and certifies it, 'adnmesh up FILE' "
                          "runs it")
    if content_type is HierarchyFile and "ders" in document and "adns" not in document:
        raise ConfigError(f"{path}: an ADN's config (it names ders), not a hierarchy file: a "
                          "hierarchy file names its ADNs' configs under adns (e.g. "
                          "configs/examples/hierarchy/hv.yaml)")


def _loaded(path: Path, content_type, loaded_type, what: str):
    """The file's document (with what it extends) validated as ``content_type`` and
    returned as ``loaded_type`` with its path and the sha256 of the bytes read."""
    document, data = _document(path, (path.resolve(),))
    if document is None:
        keys = ", ".join(content_type.model_fields)
        raise ConfigError(f"{path}: empty {what} (expected a mapping with keys: {keys})")
    _not_the_other_kind(path, document, content_type)
    try:
        content = content_type.model_validate(document)
    except ValidationError as exc:
        where = f"{path} (with what it extends)" if isinstance(_base_of(path), str) else path
        raise ConfigError(f"{where}: {_describe(exc.errors(include_url=False)[0])}") from None
    return loaded_type.model_construct(**dict(content), path=path,
                                       sha256=hashlib.sha256(data).hexdigest())
