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
from pathlib import Path

import msgspec
import numpy as np

from adnmesh.recording.foxglove_log import FOXGLOVE_LOG
from adnmesh.recording.reader import ChannelInfo, Recording
from adnmesh.recording.stream import MessageBatch, ScannedRecording, Sink, decode_fields, scan

__all__ = [
    "AVAILABILITY_KEYS",
    "ENVELOPE_FIELDS",
    "EVENTS",
    "Event",
    "EventRule",
    "Field",
    "LiveCollector",
    "QUIET_KEYS",
    "RunData",
    "RunFile",
    "SERIES",
    "Series",
    "available_ders",
    "extract",
    "feed_recording",
    "match_key",
    "read_run",
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


RuleFunction = Callable[[dict, "dict | None", dict], "tuple[str, str, dict] | None"]


@dataclass(frozen=True)
class EventRule:
    """How to find one kind of event in the messages on a key.

    Attributes
    ----------
    kind : str
        The event kind (:attr:`Event.kind`).
    rule : callable
        Gets the payload body, the body of the previous message on the same key (None for the
        first) and the key's captures; returns (level, text, data) or None.
    fields : tuple of str, optional
        The body fields ``rule`` reads (of both bodies); None: it may read any.
    watch, present : tuple of str
        Where ``fields`` is given, the rule is asked only about the first message and those
        in which a ``watch`` field differs from the previous message's or a ``present`` field
        is there (not null); empty both: about every message.
    """

    kind: str
    rule: RuleFunction
    fields: tuple[str, ...] | None = None
    watch: tuple[str, ...] = ()
    present: tuple[str, ...] = ()


EVENTS: dict[str, EventRule] = {
    "adn/{grid}/cpfc/p_y": EventRule("gain_switch", _gain_switch,
                                     ("kp", "ki", "p_y", "entry", "switch", "w"),
                                     watch=("kp", "ki"), present=("switch",)),
    "adn/{grid}/der/{der}/state": EventRule("der_mode", _der_mode, ("mode",), watch=("mode",)),
    "adn/{grid}/der/{der}/heartbeat": EventRule("der_available", _der_available,
                                                ("available",), watch=("available",)),
    "adn/{grid}/faults": EventRule("fault", _fault),
    "adn/{grid}/event/**": EventRule("event", _agent_event),
    "adn/{grid}/clock/start": EventRule("run_start", _run_start, ("end_ns", "clock")),
}
"""Key pattern -> its :class:`EventRule`. Availability changes come from
:data:`AVAILABILITY_KEYS`."""


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

    def end_ns(self) -> int | None:
        """End of the run, ns: the ``end_ns`` of its start message, else the last P_IP
        sample; None without either."""
        start = next((e for e in self.events if e.kind == "run_start"), None)
        if start is not None:
            return int(start.data["end_ns"])
        p_ip = self.one("p_ip")
        return int(p_ip.t_ns.max()) if p_ip is not None and p_ip.t_ns.size else None

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


class _Unordered(Exception):
    """A channel's messages are not in send-time order across chunks."""


@dataclass
class _Plan:
    """What :func:`extract` takes from the messages on one key."""

    specs: list[tuple[int, dict, Field]]            # (order, captures, field)
    is_si: bool
    rules: list[tuple[int, EventRule, dict]]        # (order, rule, captures)
    others: bool                                    # keep unmatched numbers too
    ders: set[str]

    @property
    def fields(self) -> tuple[str, ...] | None:
        """The payload fields to decode; None: the whole payload is needed."""
        if self.is_si or self.others or any(r.fields is None for _, r, _ in self.rules):
            return None
        names = [spec.field for _, _, spec in self.specs]
        names += [name for _, r, _ in self.rules for name in r.fields]
        return tuple(dict.fromkeys(names))

    @property
    def empty(self) -> bool:
        return not (self.specs or self.is_si or self.rules or self.others)


def _plan(topic: str, series_rules: Mapping[str, Iterable[Field]],
          event_rules: Mapping[str, EventRule]) -> _Plan:
    specs, ders = [], set()
    for pattern, fields in series_rules.items():
        captures = match_key(pattern, topic)
        if captures is not None:
            specs += [(0, captures, spec) for spec in fields]
            if "der" in captures:
                ders.add(captures["der"])
    specs = [(order, captures, spec) for order, (_, captures, spec) in enumerate(specs)]
    is_si = any(match_key(p, topic) is not None for p in AVAILABILITY_KEYS)
    rules = [(1 + order, rule, captures) for order, (p, rule) in enumerate(event_rules.items())
             if (captures := match_key(p, topic)) is not None]
    quiet = bool(specs or is_si or rules) or any(
        match_key(p, topic) is not None for p in QUIET_KEYS)
    return _Plan(specs, is_si, rules, not quiet, ders)


def _floats(values: list) -> np.ndarray:
    """Numbers as float64 (booleans 0/1), NaN for anything else."""
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        return np.asarray([np.nan if (v := _number(x)) is None else v for x in values],
                          dtype=np.float64)


class _Collector:
    """The series, events and DERs of a recording, channel by channel (see :func:`extract`)."""

    def __init__(self, series_rules, event_rules) -> None:
        self.series_rules, self.event_rules = series_rules, event_rules
        self.columns: dict[str, tuple[Field | None, str, str, list]] = {}
        self.first: dict[str, tuple] = {}
        self.events: list[tuple[tuple, Event]] = []
        self.ders: set[str] = set()
        self.availability: list[tuple[int, int, str, frozenset[str]]] = []
        self.last_available: frozenset[str] | None = None

    def sink_for(self, info) -> Sink | None:
        if info.schema_name == FOXGLOVE_LOG:   # the recorder's copy of the events
            return None
        plan = _plan(info.topic, self.series_rules, self.event_rules)
        if plan.empty:
            return None
        if plan.fields is None:
            return _WholeChannel(self, info.topic, plan)
        return _FieldChannel(self, info.topic, plan)

    def add(self, path: str, spec: Field | None, name: str, topic: str, t_ns, log_ns, values,
            first: tuple) -> None:
        """Append samples (arrays, in send-time order) to the series at ``path``."""
        if len(values) == 0:
            return
        entry = self.columns.get(path)
        if entry is None:
            entry = self.columns[path] = (spec, name, topic, _Samples())
            self.first[path] = first
        entry[3].append(t_ns, log_ns, values)

    def event(self, key: tuple, t_ns: int, kind: str, found, topic: str) -> None:
        level, text, data = found
        self.events.append((key, Event(t_ns, kind, level, text, topic, data)))

    def si(self, t_ns: int, log_ns: int, order: int, topic: str, body: dict) -> None:
        """One SI message: the count of available DERs and, on a change, an event."""
        available, known = available_ders(body)
        self.ders.update(known)
        self.availability.append((t_ns, log_ns, topic, frozenset(available)))
        self.add(f"/{topic}/available_count", _COUNT, _COUNT.name, topic, [t_ns], [log_ns],
                 [float(len(available))], (0, t_ns, order, 10_000))
        if frozenset(available) != self.last_available:
            self.last_available = frozenset(available)
            text = f"availability: {len(available)} available: {', '.join(sorted(available))}"
            self.events.append(((t_ns, order, 0), Event(t_ns, "availability", "INFO", text, topic,
                                                        {"available": sorted(available)})))

    def result(self, t0_ns: int) -> RunData:
        # one 0/1 step series per DER from SI, now that every DER id is known
        for number, (t_ns, log_ns, topic, available) in enumerate(self.availability):
            for der in sorted(self.ders):
                self.add(f"/{topic}/available/{der}",
                         Field("available", f"{der} available", "availability", unit="1",
                               step=True),
                         f"{der} available", topic, [t_ns], [log_ns], [float(der in available)],
                         (1, number))
        series, times = {}, {}
        for path in sorted(self.columns, key=self.first.__getitem__):
            spec, name, topic, pieces = self.columns.pop(path)   # one series' copy at a time
            spec = spec or Field(path.rsplit("/", 1)[-1], name, "other", unit="")
            t_ns, log_ns, values = pieces.arrays()
            shared = times.get(topic)          # series of one key mostly share their times
            if shared is not None and np.array_equal(shared[0], t_ns) and \
                    np.array_equal(shared[1], log_ns):
                t_ns, log_ns = shared
            else:
                times[topic] = (t_ns, log_ns)
            series[path] = Series(name=name, entity_path=path, role=spec.role, unit=spec.unit,
                                  step=spec.step, color=spec.color, topic=topic, t_ns=t_ns,
                                  log_time_ns=log_ns, values=values)
        self.events.sort(key=lambda item: item[0])
        return RunData(series=series, events=[e for _, e in self.events],
                       der_ids=sorted(self.ders), t0_ns=t0_ns)


class _Samples:
    """The samples of one series as they come, in few large blocks (small pieces are merged
    once there are enough of them, so that their memory is reused, not left fragmented)."""

    _MERGE = 1 << 16

    def __init__(self) -> None:
        self.blocks: list[tuple[np.ndarray, ...]] = []
        self.pieces: list[tuple[np.ndarray, ...]] = []
        self.size = 0

    def append(self, t_ns, log_ns, values) -> None:
        self.pieces.append((np.asarray(t_ns, dtype=np.int64), np.asarray(log_ns, dtype=np.int64),
                            np.asarray(values, dtype=np.float64)))
        self.size += self.pieces[-1][0].size
        if self.size >= self._MERGE:
            self.blocks.append(self._merge(self.pieces))
            self.pieces, self.size = [], 0

    @staticmethod
    def _merge(parts) -> tuple[np.ndarray, ...]:
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """Send times, delivery times (ns) and values, all of them; the blocks are let go."""
        parts, self.blocks, self.pieces = self.blocks + self.pieces, [], []
        return self._merge(parts)


class _Channel:
    """The messages on one key, a batch at a time, in send-time order."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        self.collector, self.topic, self.plan = collector, topic, plan
        self.last_t_ns: int | None = None
        self.seen = False

    def __call__(self, batch: MessageBatch) -> None:
        order = np.argsort(batch.publish_time_ns, kind="stable")
        if np.any(order[1:] < order[:-1]):
            batch = batch.select(order)
        t_ns = batch.publish_time_ns
        if self.last_t_ns is not None and t_ns.size and t_ns[0] < self.last_t_ns:
            raise _Unordered(self.topic)
        if t_ns.size:
            self.last_t_ns = int(t_ns[-1])
            self.take(batch)

    def found_bodies(self) -> None:
        if not self.seen:
            self.seen = True
            self.collector.ders.update(self.plan.ders)


class _FieldChannel(_Channel):
    """A key whose rules read known fields: columns decoded by msgspec, rules asked only where
    a watched field changes."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        super().__init__(collector, topic, plan)
        self.names = self.fields = plan.fields
        self.previous: dict | None = None

    def take(self, batch: MessageBatch) -> None:
        t_ns, log_ns, ordinal = batch.publish_time_ns, batch.log_time_ns, batch.ordinal
        decoded = batch.columns or decode_fields(batch, self.names)
        columns, valid = decoded.columns, decoded.valid
        if not valid.all():
            keep = np.flatnonzero(valid)
            t_ns, log_ns, ordinal = t_ns[keep], log_ns[keep], ordinal[keep]
            columns = {k: [v[i] for i in keep.tolist()] for k, v in columns.items()}
        if not t_ns.size:
            return
        self.found_bodies()
        for order, captures, spec in self.plan.specs:
            values = _floats(columns[spec.field])
            ok = np.isfinite(values)
            if ok.any():
                first = int(np.argmax(ok))
                self.collector.add(f"/{self.topic}/{spec.field}", spec,
                                   spec.name.format(**captures), self.topic, t_ns[ok],
                                   log_ns[ok], values[ok],
                                   (0, int(t_ns[first]), int(ordinal[first]), order))
        for order, rule, captures in self.plan.rules:
            self.apply(rule, order, captures, columns, t_ns, ordinal)
        self.previous = self.body(columns, t_ns.size - 1)

    def body(self, columns: dict[str, list], i: int) -> dict:
        return {k: v[i] for k, v in columns.items() if v[i] is not msgspec.UNSET}

    def apply(self, rule: EventRule, order: int, captures: dict, columns, t_ns, ordinal) -> None:
        """Ask ``rule`` about the messages of this batch where it may find an event."""
        n = t_ns.size
        if rule.watch or rule.present:
            asked = np.zeros(n, dtype=bool)
            asked[0] = True
            for name in rule.watch:
                values = np.fromiter(columns[name], dtype=object, count=n)
                asked[1:] |= (values[1:] != values[:-1]).astype(bool)
            for name in rule.present:
                asked |= np.fromiter((v is not msgspec.UNSET and v is not None
                                      for v in columns[name]), dtype=bool, count=n)
            rows = np.flatnonzero(asked).tolist()
        else:
            rows = range(n)
        for i in rows:
            previous = self.previous if i == 0 else self.body(columns, i - 1)
            found = rule.rule(self.body(columns, i), previous, captures)
            if found is not None:
                self.collector.event((int(t_ns[i]), int(ordinal[i]), order), int(t_ns[i]),
                                     rule.kind, found, self.topic)


class _WholeChannel(_Channel):
    """A key whose messages are needed whole (SI, faults, agents' events, unmatched keys):
    message by message, as decoded JSON."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        super().__init__(collector, topic, plan)
        self.previous: dict | None = None

    def take(self, batch: MessageBatch) -> None:
        series: dict[str, tuple[Field | None, str, list, tuple]] = {}
        for t, log, number, payload in zip(batch.publish_time_ns.tolist(),
                                           batch.log_time_ns.tolist(), batch.ordinal.tolist(),
                                           batch.payloads):
            body = _body(_json(payload))
            if body:
                self.found_bodies()
                self.message(t, log, number, body, series)
        for path, (spec, name, samples, first) in series.items():
            t, log, values = zip(*samples)
            self.collector.add(path, spec, name, self.topic, t, log, values, first)

    def message(self, t: int, log: int, number: int, body: dict, series: dict) -> None:
        def add(path, spec, name, value, order):
            entry = series.setdefault(path, (spec, name, [], (0, t, number, order)))
            entry[2].append((t, log, value))

        for order, captures, spec in self.plan.specs:
            value = _number(body.get(spec.field))
            if value is not None:
                add(f"/{self.topic}/{spec.field}", spec, spec.name.format(**captures), value,
                    order)
        if self.plan.is_si:
            self.collector.si(t, log, number, self.topic, body)
        for order, rule, captures in self.plan.rules:
            found = rule.rule(body, self.previous, captures)
            if found is not None:
                self.collector.event((t, number, order), t, rule.kind, found, self.topic)
        if self.plan.rules:
            self.previous = body
        if self.plan.others:
            for k, (name, raw) in enumerate(body.items()):
                value = None if name in ENVELOPE_FIELDS or isinstance(raw, bool) else \
                    _number(raw)
                if value is not None:
                    add(f"/{self.topic}/{name}", None, f"{self.topic}/{name}", value,
                        20_000 + k)


def _json(payload: bytes) -> object:
    try:
        return msgspec.json.decode(payload)
    except msgspec.DecodeError:
        pass
    try:
        return json.loads(payload)
    except ValueError:
        return None


def extract(recording: Recording, *, series_rules: Mapping[str, Iterable[Field]] = SERIES,
            event_rules: Mapping[str, EventRule] = EVENTS) -> RunData:
    """Turn a recording's messages into named series and events, using the tables above.

    Messages whose payload is not a JSON object are skipped. :func:`read_run` gives the same
    result for a file, reading it in one streaming pass.
    """
    collector = _Collector(series_rules, event_rules)
    feed_recording(recording, collector.sink_for)
    return collector.result(_t0(recording))


def feed_recording(recording: Recording, sink_for: Callable[[ChannelInfo], Sink | None]) -> None:
    """Give the messages of ``recording`` (read whole) to sinks, as :func:`scan` gives a file's:
    one batch per channel, in send-time order."""
    by_topic: dict[str, list[int]] = {}
    for number, m in enumerate(recording.messages):
        by_topic.setdefault(m.topic, []).append(number)
    for topic, info in recording.channels.items():
        sink = sink_for(info)
        numbers = by_topic.get(topic, [])
        if sink is None or not numbers:
            continue
        messages = [recording.messages[i] for i in numbers]
        sink(MessageBatch(np.asarray([m.publish_time_ns for m in messages], dtype=np.int64),
                          np.asarray([m.log_time_ns for m in messages], dtype=np.int64),
                          np.asarray(numbers, dtype=np.int64), [m.data for m in messages]))


@dataclass(frozen=True)
class RunFile:
    """A recording read by :func:`read_run`: the file's description and its series."""

    recording: ScannedRecording
    run: RunData


def read_run(path: str | Path, *, also: Callable[[], object] | None = None,
             series_rules: Mapping[str, Iterable[Field]] = SERIES,
             event_rules: Mapping[str, EventRule] = EVENTS) -> tuple[RunFile, object]:
    """Read the recording ``path`` in one streaming pass: its series and events, as
    :func:`extract` finds them, without holding its messages.

    Parameters
    ----------
    path : str or Path
        An MCAP file, complete or truncated.
    also : callable, optional
        Makes another consumer of the same pass: an object with a ``sink_for(info)`` method
        (see :func:`~adnmesh.recording.stream.scan`); it is returned beside the result.

    Returns
    -------
    (RunFile, object)
        The file and its run data, and the object ``also`` made (None without it).

    Raises
    ------
    RecordingError
        As :func:`~adnmesh.recording.stream.scan`.
    """
    collector = _Collector(series_rules, event_rules)
    other = also() if also is not None else None

    def sink_for(info: ChannelInfo) -> Sink | None:
        sinks = [s for s in (collector.sink_for(info),
                             other.sink_for(info) if other is not None else None) if s]
        if len(sinks) < 2:
            return sinks[0] if sinks else None
        return lambda batch: [sink(batch) for sink in sinks]

    try:
        scanned = scan(path, sink_for)
    except _Unordered:   # messages of a key out of send-time order: read it whole
        from adnmesh.recording.reader import read_recording

        recording = read_recording(path)
        collector = _Collector(series_rules, event_rules)
        other = also() if also is not None else None
        feed_recording(recording, sink_for)
        scanned = scan(path, lambda info: None)
    return RunFile(scanned, collector.result(_t0(scanned))), other


class LiveCollector(_Collector):
    """The series and events of messages as they come (``adnmesh up --view``), by the rules of
    :func:`extract`, handed out in pieces: :meth:`drain` returns what came since the last call.

    Not thread-safe: one thread feeds and drains.
    """

    def __init__(self, series_rules: Mapping[str, Iterable[Field]] = SERIES,
                 event_rules: Mapping[str, EventRule] = EVENTS) -> None:
        super().__init__(series_rules, event_rules)
        self._sinks: dict[str, Sink | None] = {}
        self._ordinal = 0

    def feed(self, topic: str, schema_name: str, records: list[tuple[bytes, int, int]]) -> None:
        """Take messages of one topic: ``(payload, log_time_ns, publish_time_ns)`` each, as
        the recorder writes them. Messages older than the topic's last are dropped."""
        if topic not in self._sinks:
            self._sinks[topic] = self.sink_for(ChannelInfo(topic, "json", schema_name))
        sink = self._sinks[topic]
        if sink is None or not records:
            return
        payloads, log_ns, publish_ns = zip(*records)
        publish = np.asarray(publish_ns, dtype=np.int64)
        ordinal = np.arange(self._ordinal, self._ordinal + publish.size, dtype=np.int64)
        self._ordinal += publish.size
        batch = MessageBatch(publish, np.asarray(log_ns, dtype=np.int64), ordinal, payloads)
        if sink.last_t_ns is not None:
            keep = np.flatnonzero(publish >= sink.last_t_ns)
            if keep.size < publish.size:
                batch = batch.select(keep)
        if len(batch):
            sink(batch)

    def drain(self, t0_ns: int = 0) -> RunData:
        """The series samples and events found since the last call (series: only those with
        new samples; events: in time order)."""
        run = self.result(t0_ns)
        self.events, self.availability, self.first = [], [], {}
        return run


_COUNT = Field("available_count", "DERs available", "available_count", unit="1", step=True)
