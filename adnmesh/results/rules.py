"""What recorded messages mean: the one table to adjust, of series, events and step windows.

:data:`SERIES` maps key patterns to the numbers taken from each message on a matching key;
:data:`EVENTS` maps key patterns to the text events derived from them; :data:`AVAILABILITY_KEYS`
names the keys of the availability vector SI; :data:`QUIET_KEYS` the keys whose numbers are
not kept. :class:`StepWindowEnds` says which of those events end a step's window. Everything
that reads meaning into messages applies these rules: the extraction of a recording's series
and events (:mod:`adnmesh.results.series`: ``adnmesh replay``, ``plot``, ``inspect``, the live
view), the events the recorder logs while a run records (:mod:`adnmesh.results.eventlog`) and
``adnmesh up``'s summary (:class:`adnmesh.results.summary.RunSeries`); so a renamed key or
field is fixed here, once. The keys and fields are those of :mod:`adnmesh.wire.messages`.

Key patterns are bus keys with placeholders: ``{name}`` matches one key level and captures it
(``{der}`` is the DER id; series names may use it), ``*`` matches one level, ``**`` the rest.
A payload's fields are looked up in the payload itself, or in its ``body`` object if it has
one (:func:`message_body`). Every value is placed at the message's **send time**
(``publish_time``: the instant the sender sampled or decided it).

Numbers on keys that no pattern matches are kept too, as series named ``<key>/<field>`` with
role ``"other"`` (except on :data:`QUIET_KEYS`), so nothing numeric is invisible.
"""

from __future__ import annotations

import colorsys
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache

from adnmesh.wire.protocol import KINDS, PROTOCOL

__all__ = [
    "AVAILABILITY_KEYS",
    "COLORS",
    "DER_COLORS",
    "DISPLAY_UNITS",
    "ENVELOPE_FIELDS",
    "EVENTS",
    "Event",
    "EventRule",
    "Field",
    "QUIET_KEYS",
    "SERIES",
    "StepWindowEnds",
    "availability_change",
    "available_ders",
    "der_colors",
    "display_unit",
    "lighter",
    "match_key",
    "message_body",
    "natural_key",
    "series_color",
    "window_ends",
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


COLORS: dict[str, tuple[int, int, int]] = {
    "p_ref": (255, 160, 0), "p_ip": (60, 150, 255), "p_y": (40, 180, 80),
    "kp": (170, 100, 220), "ki": (255, 130, 40), "grid_v_min": (230, 120, 0),
    "grid_v_max": (60, 60, 200), "grid_line_loading": (90, 90, 90),
    "grid_trafo_loading": (160, 110, 50), "q_ip": (200, 80, 160), "grid_q_ip": (200, 80, 160),
    "q_ref": (120, 40, 100), "q_y": (20, 120, 60),
    "available_count": (80, 80, 80), "grid_limit": (230, 30, 30), "tap_pos": (0, 130, 130),
}
"""Role -> the RGB colour of its line in Rerun (the others: Rerun's choice; a DER's series:
:func:`series_color`). ``grid_limit`` is the configured band and loading limit drawn with the
grid's extremes."""

DISPLAY_UNITS: dict[str, tuple[str, float]] = {
    "W": ("MW", 1e-6), "var": ("Mvar", 1e-6), "1/W": ("1/MW", 1e6), "1/(W s)": ("1/(MW s)", 1e6),
}
"""SI unit of a series -> (the unit viewers show it in, the factor from the SI value to it):
powers in MW and Mvar, gains per MW, so that a controls engineer reads 17.55 MW and
K_P 0.5 1/MW instead of 17550000 W and 5e-07 1/W. Every viewer and export uses it (``plot``,
``replay`` and the live view, ``export``); other units are shown as they are."""


def display_unit(unit: str) -> tuple[str, float]:
    """The unit a value of SI ``unit`` is shown in and the factor to it (:data:`DISPLAY_UNITS`;
    an other unit: itself, 1)."""
    return DISPLAY_UNITS.get(unit, (unit, 1.0))


DER_COLORS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
    (57, 59, 121), (99, 121, 57), (140, 109, 49), (132, 60, 57), (123, 65, 115))
"""The colours of the DERs, in the natural order of their ids (matplotlib's tab10, then five
darker ones of tab20b); beyond 15 DERs, hues spread by the golden angle."""

SETPOINT_LIGHTER = 0.45
"""A DER's set-point is drawn in its colour this much lighter (towards white) than its infeed:
the two lines of one DER are related, and told apart."""


def natural_key(text: str) -> tuple:
    """Sort key that orders ``SGen2`` before ``SGen10``."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text))


def der_colors(der_ids: Iterable[str]) -> dict[str, tuple[int, int, int]]:
    """DER id -> its RGB colour (:data:`DER_COLORS`, by the natural order of the ids): one per
    DER, the same in every view (infeed, set-point, availability)."""
    colors = {}
    for i, der in enumerate(sorted(set(der_ids), key=natural_key)):
        if i < len(DER_COLORS):
            colors[der] = DER_COLORS[i]
        else:
            hue = (i * 0.381966) % 1.0
            colors[der] = tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(hue, 0.75, 0.7))
    return colors


def lighter(color: tuple[int, int, int], amount: float = SETPOINT_LIGHTER) -> tuple[int, int, int]:
    """``color`` moved ``amount`` (0..1) of the way towards white."""
    return tuple(int(round(c + (255 - c) * amount)) for c in color)


def series_color(role: str, der: str | None, der_ids: Iterable[str],
                 default: tuple[int, int, int] | None = None) -> tuple[int, int, int] | None:
    """The colour of a series of ``role``: a DER's own (:func:`der_colors`; lighter for its
    set-point) for its infeed, set-point and availability; else ``default`` (by role,
    :data:`COLORS`)."""
    if der is None or role not in ("der_infeed", "der_setpoint", "availability"):
        return default
    color = der_colors([*der_ids, der])[der]
    return lighter(color) if role == "der_setpoint" else color


SERIES: dict[str, tuple[Field, ...]] = {
    kind.pattern: tuple(Field(f.field, f.name, f.role, f.unit, f.step, COLORS.get(f.role))
                        for f in kind.series)
    for kind in PROTOCOL if kind.series}
"""Key pattern -> the series taken from each message on a matching key: the plotted fields of
the protocol table (:mod:`adnmesh.wire.protocol`)."""

AVAILABILITY_KEYS = (KINDS["si"].pattern,)
"""Keys whose messages carry the availability vector SI (see :func:`available_ders`): each
gives a 0/1 step series per DER (role ``availability``), the count of available DERs (role
``available_count``) and an event whenever the set of available DERs changes."""

QUIET_KEYS = (*(kind.pattern for kind in PROTOCOL if kind.quiet), "adn/{grid}/alive/**")
"""Keys whose numbers are not kept as series of role ``other`` (the quiet kinds of the protocol
table: sim-clock traffic, heartbeats; and liveliness); they are still counted by ``adnmesh
inspect``."""


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
    direction = switch.get("direction") if isinstance(switch, Mapping) else None
    if direction:
        text += f"; the DERs move {direction}"
    if active:
        text += f"; DERs: {', '.join(active)}"
    if isinstance(switch, Mapping) and switch.get("handover_s"):
        text += f"; handover in {_g(switch['handover_s'])} s"
    return "INFO", text, {"kp": kp, "ki": ki, "entry": body.get("entry"), "active": active,
                          "switch": isinstance(switch, Mapping), "direction": direction}


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


EVENTS: dict[str, EventRule] = {KINDS[kind].pattern: rule for kind, rule in (
    ("p_y", EventRule("gain_switch", _gain_switch, ("kp", "ki", "p_y", "entry", "switch", "w"),
                      watch=("kp", "ki"), present=("switch",))),
    ("der_state", EventRule("der_mode", _der_mode, ("mode",), watch=("mode",))),
    ("heartbeat", EventRule("der_available", _der_available, ("available",),
                            watch=("available",))),
    ("fault", EventRule("fault", _fault)),
    ("event", EventRule("event", _agent_event)),
    ("clock_start", EventRule("run_start", _run_start, ("end_ns", "clock"))),
)}
"""Key pattern (of a kind of the protocol table) -> its :class:`EventRule`. Availability changes
come from :data:`AVAILABILITY_KEYS`."""


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


def availability_change(available: Iterable[str],
                        before: frozenset[str] | None) -> tuple[str, str, dict] | None:
    """An SI message whose set of available DERs (:func:`available_ders`) differs from the
    previous SI's (``before``; None for the first SI, which is the initial state and an event
    too); returns (level, text, data) as an :class:`EventRule`'s rule does, else None."""
    available = sorted(available)
    if before is not None and frozenset(available) == before:
        return None
    return ("INFO", f"availability: {len(available)} available: {', '.join(available)}",
            {"available": available})


class StepWindowEnds:
    """What ends a step's window, besides the next step of P_ref: the one rule of ``adnmesh
    up``'s summary (:class:`~adnmesh.results.summary.RunSeries`, fed as the run goes) and of
    the figures ``adnmesh inspect`` finds in a recording (:func:`window_ends`).

    Fed the run's events in time order (:meth:`take`), it keeps in :attr:`instants` (ns) those
    of

    - a gain switch with the CPFC's switch record (``gain_switch`` with ``switch``; a change
      of the gains without one is no switch of the table entry), unless it was made because
      the DERs move the other way (its record's ``direction``): that is the response to the
      step itself (docs/method.md#directional-availability),
    - a DER's heartbeat flag that differs from its previous one (``der_available``),
    - a change of the availability vector SI (``availability``; not the first SI, which is the
      initial state),
    - an injected fault: its start and, if it has one, its end (``fault``; a fault sent again
      to a restarted agent counts once);
    - an agent lost (``up``'s event of kind ``agent_lost``: a process that died or stopped
      unplanned).
    """

    def __init__(self) -> None:
        self.instants: list[int] = []
        self._initial_si = True
        self._faults: set = set()

    def take(self, event: Event) -> None:
        """Note ``event`` if it ends a window."""
        kind = event.kind
        if kind == "availability":
            if not self._initial_si:
                self.instants.append(event.t_ns)
            self._initial_si = False
        elif kind == "der_available" or (kind == "gain_switch" and event.data.get("switch")
                                         and not event.data.get("direction")):
            self.instants.append(event.t_ns)
        elif kind == "event" and event.data.get("kind") == "agent_lost":
            self.instants.append(event.t_ns)
        elif kind == "fault" and event.data["fault_id"] not in self._faults:
            self._faults.add(event.data["fault_id"])
            self.instants += [t for t in (event.data["start_ns"], event.data.get("end_ns"))
                              if t is not None]


def window_ends(events: Iterable[Event]) -> list[int]:
    """The instants (ns) at which ``events`` (in time order) end a step's window, by the rule
    of :class:`StepWindowEnds`."""
    ends = StepWindowEnds()
    for event in events:
        ends.take(event)
    return ends.instants


def message_body(payload: object) -> dict:
    """The fields of a decoded payload: its own, and those of its ``body`` object if it has one
    (empty for anything that is not a JSON object)."""
    if not isinstance(payload, dict):
        return {}
    inner = payload.get("body")
    return {**payload, **inner} if isinstance(inner, dict) else payload



def _g(value: object) -> str:
    return f"{value:.4g}" if isinstance(value, (int, float)) else str(value)
