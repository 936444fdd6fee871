"""From recorded messages to named time series and events: the one table to adjust.

:data:`SERIES` maps key patterns to the numbers taken from each message on a matching key;
:data:`EVENTS` maps key patterns to the text events derived from them; :data:`AVAILABILITY_KEYS`
names the keys of the availability vector SI. ``adnmesh replay``, ``adnmesh plot`` and
``adnmesh inspect`` all read a recording through :func:`extract`, so a renamed key or field is
fixed here, once. The keys and fields are those of :mod:`adnmesh.runtime.messages`.

Key patterns are bus keys with placeholders: ``{name}`` matches one key level and captures it
(``{der}`` is the DER id; series names may use it), ``*`` matches one level, ``**`` the rest.
A payload's fields are looked up in the payload itself, or in its ``body`` object if it has
one. Every value is placed at the message's **send time** (``publish_time``: the instant the
sender sampled or decided it), on the ``sim_time`` axis in seconds from ``t0``.

Numbers on keys that no pattern matches are kept too, as series named ``<key>/<field>`` with
role ``"other"`` (except on :data:`QUIET_KEYS`), so nothing numeric is invisible.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from adnmesh.recording.reader import Recording

__all__ = [
    "AVAILABILITY_KEYS",
    "ENVELOPE_FIELDS",
    "EVENTS",
    "Event",
    "Field",
    "QUIET_KEYS",
    "RunData",
    "SERIES",
    "Series",
    "available_ders",
    "extract",
    "match_key",
]

ENVELOPE_FIELDS = frozenset({"v", "type", "src", "seq", "t_send_ns", "t_deliver_ns"})
"""Fields of the message envelope (not plotted, not shown in event texts)."""


@dataclass(frozen=True)
class Field:
    """Take the number ``field`` of a payload as one sample of the series ``name``.

    Attributes
    ----------
    field : str
        Payload field (a number; booleans become 0/1).
    name : str
        Series name; ``{der}`` and other key captures are filled in.
    role : str
        What the series is, for plots and layouts: ``p_ref``, ``p_ip``, ``p_y``, ``kp``,
        ``ki``, ``entry``, ``der_infeed``, ``der_setpoint``, ``availability``,
        ``available_count`` or ``other``.
    unit : str
        Unit of the value (SI; ``"1"`` for dimensionless).
    step : bool
        The value holds until the next sample (drawn as steps).
    color : tuple of int, optional
        RGB colour of the line in Rerun (default: Rerun's choice).
    """

    field: str
    name: str
    role: str
    unit: str = "W"
    step: bool = False
    color: tuple[int, int, int] | None = None


SERIES: dict[str, tuple[Field, ...]] = {
    "adn/{grid}/scenario/p_ref": (Field("p_ref_w", "P_ref", "p_ref", step=True,
                                        color=(255, 160, 0)),),
    "adn/{grid}/measurement/p_ip": (Field("p_ip_w", "P_IP", "p_ip", color=(60, 150, 255)),),
    "adn/{grid}/cpfc/p_y": (
        Field("p_y", "P_Y", "p_y", unit="1", color=(40, 180, 80)),
        Field("kp", "K_P", "kp", unit="1/W", step=True, color=(170, 100, 220)),
        Field("ki", "K_I", "ki", unit="1/(W s)", step=True, color=(255, 130, 40)),
        Field("entry", "table entry", "entry", unit="1", step=True),
    ),
    "adn/{grid}/der/{der}/state": (
        Field("p_w", "{der} infeed", "der_infeed"),
        Field("setpoint_w", "{der} setpoint", "der_setpoint", step=True),
    ),
    "adn/{grid}/measurement/grid": (
        Field("v_min_pu", "lowest bus voltage", "grid_v_min", unit="p.u.", step=True,
              color=(200, 60, 60)),
        Field("v_max_pu", "highest bus voltage", "grid_v_max", unit="p.u.", step=True,
              color=(60, 60, 200)),
        Field("line_loading_max_pct", "highest line loading", "grid_line_loading", unit="%",
              step=True),
        Field("trafo_loading_max_pct", "highest transformer loading", "grid_trafo_loading",
              unit="%", step=True),
        Field("q_ip_var", "Q_IP", "q_ip", unit="var", step=True),
    ),
}
"""Key pattern -> the series taken from each message on a matching key."""

AVAILABILITY_KEYS = ("adn/{grid}/availability/si",)
"""Keys whose messages carry the availability vector SI (see :func:`available_ders`): each
gives a 0/1 step series per DER (role ``availability``), the count of available DERs (role
``available_count``) and an event whenever the set of available DERs changes."""

QUIET_KEYS = ("adn/{grid}/clock/**", "adn/{grid}/alive/**", "adn/{grid}/der/{der}/heartbeat")
"""Keys whose numbers are not kept as series of role ``other`` (sim-clock traffic,
liveliness, heartbeats); they are still counted by ``adnmesh inspect``."""


@dataclass(frozen=True)
class Event:
    """Something that happened: a gain switch, an availability change, a fault, a DER mode change,
    a DER's heartbeat flag change, the run's start.

    ``t_ns`` is the send time; ``data`` holds the details (e.g. ``available`` for an availability
    change, ``active`` for a fault that has a start and an end, ``switch`` for a gain switch
    that carries the CPFC's switch record, ``end_ns`` for the run's start).
    """

    t_ns: int
    kind: str
    level: str
    text: str
    topic: str
    data: dict = field(default_factory=dict)


def _gain_switch(body: dict, previous: dict | None, captures: dict) -> tuple[str, str, dict] | None:
    """A p_y message with a ``switch`` object, or whose gains differ from the previous one's."""
    kp, ki = body.get("kp"), body.get("ki")
    switch = body.get("switch")
    if isinstance(switch, Mapping):
        before = switch
    elif previous is not None and (previous.get("kp"), previous.get("ki")) != (kp, ki):
        before = {"kp_before": previous.get("kp"), "ki_before": previous.get("ki"),
                  "p_y_before": previous.get("p_y")}
    else:
        return None
    weights = body.get("w")
    active = sorted(d for d, w in weights.items() if w) if isinstance(weights, Mapping) else []
    entry = f" to entry {body['entry']}" if "entry" in body else ""
    text = (f"gain switch{entry}: K_P {_g(before.get('kp_before'))} -> {_g(kp)} 1/W, "
            f"K_I {_g(before.get('ki_before'))} -> {_g(ki)} 1/(W s)")
    if isinstance(switch, Mapping):
        text += f", P_Y {_g(before.get('p_y_before'))} -> {_g(body.get('p_y'))}"
    if active:
        text += f"; DERs: {', '.join(active)}"
    return "INFO", text, {"kp": kp, "ki": ki, "entry": body.get("entry"), "active": active,
                          "switch": isinstance(switch, Mapping)}


def _der_mode(body: dict, previous: dict | None, captures: dict) -> tuple[str, str, dict] | None:
    """A DER whose mode (control, schedule, watchdog) differs from its previous state's."""
    mode, old = body.get("mode"), (previous or {}).get("mode")
    if mode is None or old is None or mode == old:
        return None
    der = captures.get("der", "?")
    return ("WARN" if mode == "watchdog" else "INFO", f"{der}: mode {old} -> {mode}",
            {"der": der, "mode": mode})


def _der_available(body: dict, previous: dict | None,
                   captures: dict) -> tuple[str, str, dict] | None:
    """A DER heartbeat whose ``available`` flag differs from the DER's previous heartbeat's
    (a DER counts as available before its first heartbeat)."""
    flag = body.get("available")
    old = True if previous is None else previous.get("available")
    if not isinstance(flag, bool) or flag == old:
        return None
    der = captures.get("der", "?")
    return ("INFO", f"{der}: heartbeat says {'available' if flag else 'unavailable'}",
            {"der": der, "available": flag})


def _run_start(body: dict, previous: dict | None, captures: dict) -> tuple[str, str, dict] | None:
    """The sim clock's start message: the clock mode and the run's end (``end_ns``)."""
    end = body.get("end_ns")
    if not isinstance(end, int) or isinstance(end, bool):
        return None
    clock = body.get("clock", "?")
    return "INFO", f"run starts: {clock} clock, ends at {end / 1e9:g} s", {"end_ns": end,
                                                                          "clock": clock}


def _fault(body: dict, previous: dict | None, captures: dict) -> tuple[str, str, dict] | None:
    """An injected fault (``up``'s ``faults`` messages): its window ``[start_ns, end_ns)``."""
    if not isinstance(body.get("start_ns"), int) or "fault_id" not in body:
        return None
    details = {k: v for k, v in body.items() if k not in ENVELOPE_FIELDS}
    target = next((str(details[k]) for k in ("link", "der", "agent") if details.get(k)),
                  "all ICT")
    end = details.get("end_ns")
    text = (f"fault {details['fault_id']}: {details.get('kind')} of {target} from "
            f"{details['start_ns'] / 1e9:g} s" + ("" if end is None else f" to {end / 1e9:g} s"))
    return "WARN", text, details


_LEVELS = {"DEBUG": "DEBUG", "INFO": "INFO", "WARNING": "WARN", "ERROR": "ERROR"}


def _agent_event(body: dict, previous: dict | None,
                 captures: dict) -> tuple[str, str, dict] | None:
    """What an agent (or ``up``) noticed or did: its event message, as it says it."""
    text = body.get("text")
    if not isinstance(text, str):
        return None
    return (_LEVELS.get(body.get("level"), "INFO"), f"{body.get('src', '?')}: {text}",
            {k: body[k] for k in ("kind", "subject", "fault_id") if k in body})


EventRule = Callable[[dict, "dict | None", dict], "tuple[str, str, dict] | None"]

EVENTS: dict[str, tuple[str, EventRule]] = {
    "adn/{grid}/cpfc/p_y": ("gain_switch", _gain_switch),
    "adn/{grid}/der/{der}/state": ("der_mode", _der_mode),
    "adn/{grid}/der/{der}/heartbeat": ("der_available", _der_available),
    "adn/{grid}/faults": ("fault", _fault),
    "adn/{grid}/event/**": ("event", _agent_event),
    "adn/{grid}/clock/start": ("run_start", _run_start),
}
"""Key pattern -> (event kind, rule). A rule gets the payload body, the body of the previous
message on the same key (None for the first) and the key's captures, and returns
(level, text, data) or None. Availability changes come from :data:`AVAILABILITY_KEYS`."""


def available_ders(body: Mapping) -> tuple[set[str], set[str]]:
    """Return (available, known) DER ids of an SI message.

    Accepted forms: ``{"available": [ids]}`` (optionally with ``"der_ids"``: all ids),
    ``{"si": {id: bool}}`` / ``{"available": {id: bool}}``, or ``{"si": [bool], "der_ids": [ids]}``.
    """
    ids = [str(i) for i in body.get("der_ids") or ()]
    for key in ("available", "si"):
        value = body.get(key)
        if isinstance(value, Mapping):
            return {str(k) for k, v in value.items() if v}, {str(k) for k in value} | set(ids)
        if isinstance(value, list) and value and all(isinstance(v, bool) for v in value):
            return {i for i, v in zip(ids, value) if v}, set(ids)
        if isinstance(value, list):
            return {str(v) for v in value}, {str(v) for v in value} | set(ids)
    return set(), set(ids)


@lru_cache(maxsize=None)
def _compile(pattern: str) -> re.Pattern:
    parts = []
    for level in pattern.split("/"):
        if level == "**":
            parts.append(r"(?:[^/]+(?:/[^/]+)*)")
        elif level == "*":
            parts.append(r"[^/]+")
        else:
            parts.append(re.sub(r"\\\{(\w+)\\\}", r"(?P<\1>[^/]+)", re.escape(level)))
    return re.compile("^" + "/".join(parts) + "$")


def match_key(pattern: str, key: str) -> dict[str, str] | None:
    """Return the captures if ``key`` matches ``pattern`` (see the module doc), else None."""
    found = _compile(pattern).match(key)
    return None if found is None else found.groupdict()


@dataclass
class Series:
    """One named time series.

    Attributes
    ----------
    name : str
        E.g. ``P_IP``, ``SGen1 infeed``.
    entity_path : str
        ``/<key>/<field>``: the Rerun entity path (before escaping).
    role, unit, step, color : str, str, bool, tuple or None
        See :class:`Field`.
    topic : str
        The key the values came from.
    t_ns : numpy.ndarray of int64
        Send times, ns (raw, not shifted by t0).
    log_time_ns : numpy.ndarray of int64
        Delivery times, ns.
    values : numpy.ndarray of float64
    """

    name: str
    entity_path: str
    role: str
    unit: str
    step: bool
    color: tuple[int, int, int] | None
    topic: str
    t_ns: np.ndarray
    log_time_ns: np.ndarray
    values: np.ndarray


@dataclass
class RunData:
    """Everything :func:`extract` takes from a recording.

    Attributes
    ----------
    series : dict of str to Series
        By entity path, in order of first appearance.
    events : list of Event
        In time order.
    der_ids : list of str
        DERs seen (on DER keys or in SI), sorted.
    t0_ns : int
        Origin of the ``sim_time`` axis, ns: the run metadata's ``t0_ns``, else 0 (message times
        count from the run's start in both clock modes).
    """

    series: dict[str, Series]
    events: list[Event]
    der_ids: list[str]
    t0_ns: int

    def by_role(self, role: str) -> list[Series]:
        """Return the series of ``role``, in order of first appearance."""
        return [s for s in self.series.values() if s.role == role]

    def one(self, role: str) -> Series | None:
        """Return the first series of ``role``, or None."""
        found = self.by_role(role)
        return found[0] if found else None

    def seconds(self, t_ns: np.ndarray | int) -> np.ndarray | float:
        """Convert send times in ns to seconds on the ``sim_time`` axis."""
        return (np.asarray(t_ns, dtype=np.int64) - self.t0_ns) / 1e9

    def availability_spans(self) -> list[tuple[int, int | None, frozenset[str]]]:
        """Return (start ns, end ns or None, available DER ids) for every availability state."""
        changes = [e for e in self.events if e.kind == "availability"]
        return [(e.t_ns, nxt.t_ns if nxt else None, frozenset(e.data["available"]))
                for e, nxt in zip(changes, changes[1:] + [None])]

    def fault_spans(self) -> list[tuple[int, int | None, str]]:
        """Return (start ns, end ns or None, description) per injected fault (a fault sent
        again to a restarted agent counts once; a kill without restart is an instant)."""
        spans: dict[int, tuple[int, int | None, str]] = {}
        for event in (e for e in self.events if e.kind == "fault"):
            data = event.data
            if data["fault_id"] not in spans:
                end = data.get("end_ns")
                if data.get("kind") == "kill" and end is None:
                    end = data["start_ns"]
                spans[data["fault_id"]] = (data["start_ns"], end, event.text)
        return sorted(spans.values())


def _body(payload: object) -> dict:
    if not isinstance(payload, dict):
        return {}
    inner = payload.get("body")
    return {**payload, **inner} if isinstance(inner, dict) else payload


def _number(value: object) -> float | None:
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)) and np.isfinite(value):
        return float(value)
    return None


def _g(value: object) -> str:
    return f"{value:.4g}" if isinstance(value, (int, float)) else str(value)


def _t0(recording: Recording) -> int:
    value = recording.run.get("t0_ns", "").strip()
    return int(value) if value.isdigit() else 0


def extract(recording: Recording, *, series_rules: Mapping[str, Iterable[Field]] = SERIES,
            event_rules: Mapping[str, tuple[str, EventRule]] = EVENTS) -> RunData:
    """Turn a recording's messages into named series and events, using the tables above.

    Messages whose payload is not a JSON object are skipped.
    """
    columns: dict[str, tuple[Field | None, str, str, list, list, list]] = {}
    events: list[Event] = []
    previous: dict[str, dict] = {}  # the last body per key, for the event rules
    ders: set[str] = set()
    last_available: frozenset[str] | None = None
    availability: list[tuple[int, int, str, frozenset[str]]] = []

    def add(path: str, spec: Field | None, name: str, topic: str, m, value: float) -> None:
        entry = columns.get(path)
        if entry is None:
            entry = columns[path] = (spec, name, topic, [], [], [])
        entry[3].append(m.publish_time_ns)
        entry[4].append(m.log_time_ns)
        entry[5].append(value)

    plans: dict[str, tuple[list, bool, list, bool]] = {}

    def plan(topic: str) -> tuple[list, bool, list, bool]:
        """Which series rules (with captures), whether SI, which event rules apply to topic."""
        specs = []
        for pattern, fields in series_rules.items():
            captures = match_key(pattern, topic)
            if captures is not None:
                specs.append((captures, fields))
                if "der" in captures:
                    ders.add(captures["der"])
        is_si = any(match_key(p, topic) is not None for p in AVAILABILITY_KEYS)
        rules = [(kind, rule, captures) for p, (kind, rule) in event_rules.items()
                 if (captures := match_key(p, topic)) is not None]
        quiet = bool(specs or is_si or rules) or any(
            match_key(p, topic) is not None for p in QUIET_KEYS)
        return specs, is_si, rules, quiet

    for m in sorted(recording.messages, key=lambda m: m.publish_time_ns):  # stable
        try:
            body = _body(json.loads(m.data))
        except ValueError:
            continue
        if not body:
            continue
        if m.topic not in plans:
            plans[m.topic] = plan(m.topic)
        specs, is_si, rules, quiet = plans[m.topic]
        for captures, fields in specs:
            for spec in fields:
                value = _number(body.get(spec.field))
                if value is not None:
                    add(f"/{m.topic}/{spec.field}", spec, spec.name.format(**captures), m.topic,
                        m, value)
        if is_si:
            available, known = available_ders(body)
            ders.update(known)
            availability.append((m.publish_time_ns, m.log_time_ns, m.topic, frozenset(available)))
            add(f"/{m.topic}/available_count", _COUNT, _COUNT.name, m.topic, m,
                float(len(available)))
            if frozenset(available) != last_available:
                last_available = frozenset(available)
                text = f"availability: {len(available)} available: {', '.join(sorted(available))}"
                events.append(Event(m.publish_time_ns, "availability", "INFO", text, m.topic,
                                    {"available": sorted(available)}))
        for kind, rule, captures in rules:
            found = rule(body, previous.get(m.topic), captures)
            if found is not None:
                level, text, data = found
                events.append(Event(m.publish_time_ns, kind, level, text, m.topic, data))
        if rules:
            previous[m.topic] = body
        if not quiet:
            for name, raw in body.items():
                value = None if name in ENVELOPE_FIELDS or isinstance(raw, bool) else _number(raw)
                if value is not None:
                    add(f"/{m.topic}/{name}", None, f"{m.topic}/{name}", m.topic, m, value)

    # one 0/1 step series per DER from SI, now that every DER id is known
    for t_ns, log_ns, topic, available in availability:
        for der in sorted(ders):
            add(f"/{topic}/available/{der}",
                Field("available", f"{der} available", "availability", unit="1", step=True),
                f"{der} available", topic, _Stamp(t_ns, log_ns), float(der in available))

    series = {}
    for path, (spec, name, topic, t_ns, log_ns, values) in columns.items():
        spec = spec or Field(path.rsplit("/", 1)[-1], name, "other", unit="")
        series[path] = Series(name=name, entity_path=path, role=spec.role, unit=spec.unit,
                              step=spec.step, color=spec.color, topic=topic,
                              t_ns=np.asarray(t_ns, dtype=np.int64),
                              log_time_ns=np.asarray(log_ns, dtype=np.int64),
                              values=np.asarray(values, dtype=np.float64))
    events.sort(key=lambda e: e.t_ns)
    return RunData(series=series, events=events, der_ids=sorted(ders), t0_ns=_t0(recording))


_COUNT = Field("available_count", "DERs available", "available_count", unit="1", step=True)


@dataclass(frozen=True)
class _Stamp:
    publish_time_ns: int
    log_time_ns: int
