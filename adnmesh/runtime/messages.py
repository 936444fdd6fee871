"""Bus messages: keys, JSON Schemas, and the envelope every payload carries.

Every payload on ``adn/<grid>/...`` is one JSON object, the **envelope** (version ``v`` = 1)::

    {"v": 1, "type": "p_ip", "src": "measurement", "seq": 41,
     "t_send_ns": 4100000000, "t_deliver_ns": 4200000000, "p_ip_w": 1000012.5}

``type`` is fixed by the key (:func:`message_type`), ``src`` is the sending agent's id (``up`` for
the clock messages of ``adnmesh up`` itself), ``seq``
counts the messages of one sender on one key from 0, and the two times are sim-time ns in sim mode
(scaled wall time since the run's start in realtime mode): when the sender sent it and when the
ICT channel model delivers it. The body's fields sit next to the envelope's. Every type has a JSON
Schema (draft 2020-12) in :data:`SCHEMAS`; :func:`decode` checks a payload against it with a
validator generated from the schema (:mod:`adnmesh.runtime.validator`) plus the one relation a
schema cannot state (``t_deliver_ns >= t_send_ns``) and raises :class:`MessageError` for anything
malformed or out of range. The recorder publishes the same schemas with the recording.

**Framing.** A Zenoh sample on a key carries one or more envelopes of that key, one per line
(JSON Lines; compact JSON never contains a raw newline): in sim mode an agent sends everything
it has for a key in one clock window as one sample (:func:`frames`), which saves most of the
per-sample cost of the bus; receivers and the recorder split samples back into envelopes
(:func:`split_frame`), count envelopes and record one MCAP message per envelope.

Keys, below ``adn/<grid>/`` (``<grid>`` is the config's ``grid``; agent ids are ``cpfc``,
``measurement``, ``availability``, ``der/<id>``; ``up`` is ``adnmesh up`` itself):

===========================  ================  ===============================================
key                          type              sent by → to
===========================  ================  ===============================================
``cpfc/p_y``                 ``p_y``           CPFC → every DER (P_Y; weights W on a switch)
``scenario/p_ref``           ``p_ref``         CPFC, when the reference changes (recorded)
``der/<id>/state``           ``der_state``     DER → measurement (infeed, at sampling times)
``der/<id>/heartbeat``       ``heartbeat``     DER → availability monitor
``measurement/p_ip``         ``p_ip``          measurement → CPFC
``availability/si``          ``si``            availability monitor → CPFC
``fault/<agent>``            ``fault``         an agent, when an injected fault starts or ends
``clock/report/<agent>``     ``clock_report``  agent → coordinator (sim clock)
``clock/grant/<agent>``      ``clock_grant``   coordinator → agent (sim clock)
``clock/start``              ``clock_start``   ``up`` → every agent (the run starts)
``clock/stop``               ``clock_stop``    ``up`` → every agent (the run ends)
``clock/bye/<agent>``        ``agent_bye``     agent → ``up`` (what it published)
===========================  ================  ===============================================
"""

from __future__ import annotations

import functools
import json
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import orjson

from adnmesh.runtime.validator import SchemaViolation, compile_schema

__all__ = [
    "ENVELOPE_FIELDS",
    "MESSAGE_VERSION",
    "SCHEMAS",
    "Message",
    "MessageError",
    "Keys",
    "decode",
    "encode",
    "frames",
    "message_type",
    "parse_json",
    "split_frame",
    "validate",
]

MESSAGE_VERSION = 1
"""Version ``v`` of the envelope and of every body defined here."""

ENVELOPE_FIELDS = ("v", "type", "src", "seq", "t_send_ns", "t_deliver_ns")
"""Fields every payload carries besides its body."""

_ID = r"^[A-Za-z][A-Za-z0-9_-]*$"
_AGENT = r"^(cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)$"
_SENDER = r"^(up|cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)$"
_NS = {"type": "integer", "minimum": 0}
_NUMBER = {"type": "number"}
_WEIGHT = {"type": "number", "minimum": 0, "maximum": 1}


def _schema(type_name: str, title: str, body: dict, required: list[str]) -> dict:
    """The JSON Schema of an envelope of ``type_name`` with the given body properties."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://adnmesh.invalid/schemas/{type_name}.json",
        "title": title,
        "type": "object",
        "properties": {
            "v": {"const": MESSAGE_VERSION},
            "type": {"const": type_name},
            "src": {"type": "string", "pattern": _SENDER},
            "seq": {"type": "integer", "minimum": 0},
            "t_send_ns": _NS,
            "t_deliver_ns": _NS,
            **body,
        },
        "required": [*ENVELOPE_FIELDS, *required],
        "additionalProperties": False,
    }


SCHEMAS: dict[str, dict] = {
    "p_y": _schema(
        "p_y",
        "CPFC output P_Y (dimensionless) with the gains in use; weights W on a switch",
        {
            "p_y": _NUMBER,
            "p_ref_w": _NUMBER,
            "kp": {"type": "number", "exclusiveMinimum": 0},
            "ki": {"type": "number", "exclusiveMinimum": 0},
            "entry": {"type": "integer", "minimum": 0},
            "w": {
                "type": "object",
                "propertyNames": {"pattern": _ID},
                "additionalProperties": _WEIGHT,
            },
            "switch": {
                "type": "object",
                "properties": {
                    "p_y_before": _NUMBER,
                    "p_y_limited": _NUMBER,
                    "kp_before": {"type": "number", "exclusiveMinimum": 0},
                    "ki_before": {"type": "number", "exclusiveMinimum": 0},
                },
                "required": ["p_y_before", "kp_before", "ki_before"],
                "additionalProperties": False,
            },
        },
        ["p_y", "p_ref_w", "kp", "ki", "entry"],
    ),
    "p_ref": _schema("p_ref", "Reference P_ref at the interconnection point, W",
                     {"p_ref_w": _NUMBER}, ["p_ref_w"]),
    "der_state": _schema(
        "der_state",
        "DER infeed and setpoint at a sampling instant, W",
        {
            "p_w": _NUMBER,
            "setpoint_w": _NUMBER,
            "mode": {"enum": ["control", "schedule", "watchdog"]},
        },
        ["p_w", "setpoint_w", "mode"],
    ),
    "heartbeat": _schema("heartbeat", "DER heartbeat with its availability flag",
                         {"available": {"type": "boolean"}}, ["available"]),
    "p_ip": _schema("p_ip", "Measured active power at the interconnection point, W",
                    {"p_ip_w": _NUMBER}, ["p_ip_w"]),
    "si": _schema(
        "si",
        "Availability vector SI: one boolean per DER",
        {
            "si": {
                "type": "object",
                "propertyNames": {"pattern": _ID},
                "additionalProperties": {"type": "boolean"},
                "minProperties": 1,
            }
        },
        ["si"],
    ),
    "fault": _schema(
        "fault",
        "An injected fault starting (active) or ending",
        {
            "fault": {"enum": ["der_offline", "crash"]},
            "agent": {"type": "string", "pattern": _AGENT},
            "active": {"type": "boolean"},
        },
        ["fault", "agent", "active"],
    ),
    "clock_report": _schema(
        "clock_report",
        "Sim clock: an agent's next event and its message counts",
        {
            "next_ns": {"type": ["integer", "null"], "minimum": 0},
            "granted_ns": _NS,
            "received": {"type": "integer", "minimum": 0},
            "sent": {
                "type": "object",
                "additionalProperties": {
                    "type": "array",
                    "prefixItems": [{"type": "integer", "minimum": 1}, _NS],
                    "minItems": 2,
                    "maxItems": 2,
                },
            },
        },
        ["next_ns", "granted_ns", "received", "sent"],
    ),
    "clock_grant": _schema(
        "clock_grant",
        "Sim clock: process every event before until_ns once `expect` messages have arrived",
        {"until_ns": _NS, "expect": {"type": "integer", "minimum": 0}},
        ["until_ns", "expect"],
    ),
    "clock_start": _schema(
        "clock_start",
        "The run starts (realtime: sim time = (wall - epoch_ns) * speed) with this ICT seed",
        {
            "clock": {"enum": ["sim", "realtime"]},
            "epoch_ns": _NS,
            "speed": {"type": "number", "exclusiveMinimum": 0},
            "end_ns": _NS,
            "seed": {"type": "integer", "minimum": 0},
        },
        ["clock", "epoch_ns", "speed", "end_ns", "seed"],
    ),
    "clock_stop": _schema("clock_stop", "The run ends; agents report and exit",
                          {"reason": {"type": "string"}}, ["reason"]),
    "agent_bye": _schema(
        "agent_bye",
        "An agent's final counts: messages published per key, rejected, lost on its links",
        {
            "published": {"type": "object",
                          "additionalProperties": {"type": "integer", "minimum": 0}},
            "rejected": {"type": "integer", "minimum": 0},
            "lost": {"type": "integer", "minimum": 0},
            "stats": {"type": "object", "additionalProperties": _NUMBER},
        },
        ["published", "rejected", "lost"],
    ),
}
"""Message type -> JSON Schema (draft 2020-12) of its payload (envelope and body)."""

_ROUTES: tuple[tuple[re.Pattern, str], ...] = tuple(
    (re.compile(rf"^adn/[A-Za-z][A-Za-z0-9_-]*/{pattern}$"), name)
    for pattern, name in (
        (r"cpfc/p_y", "p_y"),
        (r"scenario/p_ref", "p_ref"),
        (r"der/[A-Za-z][A-Za-z0-9_-]*/state", "der_state"),
        (r"der/[A-Za-z][A-Za-z0-9_-]*/heartbeat", "heartbeat"),
        (r"measurement/p_ip", "p_ip"),
        (r"availability/si", "si"),
        (r"fault/(?:cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)", "fault"),
        (r"clock/report/(?:cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)",
         "clock_report"),
        (r"clock/grant/(?:cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)",
         "clock_grant"),
        (r"clock/start", "clock_start"),
        (r"clock/stop", "clock_stop"),
        (r"clock/bye/(?:cpfc|measurement|availability|der/[A-Za-z][A-Za-z0-9_-]*)",
         "agent_bye"),
    )
)

_TYPE_CACHE: dict[str, str] = {}


def message_type(key: str) -> str:
    """Return the message type carried on ``key`` (a key of :data:`SCHEMAS`).

    Raises
    ------
    ValueError
        If ``key`` is not an adnmesh bus key.
    """
    found = _TYPE_CACHE.get(key)
    if found is not None:
        return found
    for pattern, name in _ROUTES:
        if pattern.match(key):
            if len(_TYPE_CACHE) < 4096:
                _TYPE_CACHE[key] = name
            return name
    raise ValueError(f"not an adnmesh bus key: {key!r}")


@dataclass(frozen=True)
class Keys:
    """The bus keys of one grid, ``adn/<grid>/...`` (see the module docstring)."""

    grid: str

    @property
    def root(self) -> str:
        return f"adn/{self.grid}"

    @property
    def all(self) -> str:
        """Key expression matching every message of the grid."""
        return f"adn/{self.grid}/**"

    @property
    def p_y(self) -> str:
        return f"adn/{self.grid}/cpfc/p_y"

    @property
    def p_ref(self) -> str:
        return f"adn/{self.grid}/scenario/p_ref"

    def der_state(self, der_id: str) -> str:
        return f"adn/{self.grid}/der/{der_id}/state"

    def heartbeat(self, der_id: str) -> str:
        return f"adn/{self.grid}/der/{der_id}/heartbeat"

    @property
    def p_ip(self) -> str:
        return f"adn/{self.grid}/measurement/p_ip"

    @property
    def si(self) -> str:
        return f"adn/{self.grid}/availability/si"

    def fault(self, agent: str) -> str:
        return f"adn/{self.grid}/fault/{agent}"

    def report(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/report/{agent}"

    def grant(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/grant/{agent}"

    @property
    def start(self) -> str:
        return f"adn/{self.grid}/clock/start"

    @property
    def stop(self) -> str:
        return f"adn/{self.grid}/clock/stop"

    def bye(self, agent: str) -> str:
        return f"adn/{self.grid}/clock/bye/{agent}"

    def liveliness(self, agent: str) -> str:
        """Liveliness token of a running agent (``up`` itself is agent ``up``)."""
        return f"adn/{self.grid}/alive/{agent}"


# --- decoding and validation ------------------------------------------------------------------


class MessageError(ValueError):
    """A payload is not a valid message: not JSON, wrong shape, or a value out of range.

    Parameters
    ----------
    problem : str
        One line, with the JSON path of the offending value where there is one.
    """


class Message(NamedTuple):
    """A decoded, validated message (an immutable named tuple: cheap to build per envelope).

    Attributes
    ----------
    key : str
        The bus key it came on.
    type : str
        Its message type.
    src : str
        Sending agent.
    seq : int
        Per-(src, key) sequence number.
    t_send_ns, t_deliver_ns : int
        Send and delivery time, ns.
    body : dict
        The whole payload (envelope fields included).
    """

    key: str
    type: str
    src: str
    seq: int
    t_send_ns: int
    t_deliver_ns: int
    body: dict


def _reject_constant(name: str):
    raise MessageError(f"not valid JSON: {name} is not a number")


_decoder = json.JSONDecoder(parse_constant=_reject_constant)
_encoder = json.JSONEncoder(separators=(",", ":"), allow_nan=False)

_VALIDATORS = {name: compile_schema(schema, f"check_{name}")
               for name, schema in SCHEMAS.items()}

# orjson reads an integer beyond 64 bits as a float, the standard library as an int: a payload
# with 19 digits in a row (never one of ours: times are < 1e19 ns, floats have <= 17 digits)
# takes the standard library's path, so that both paths give the same values
_DIGIT_RUNS = bytes(48 if 48 <= i <= 57 else 32 for i in range(256))  # digit -> "0", else " "
_LONG_INTEGER = b"0" * 19


def parse_json(payload: bytes | str) -> Any:
    """The JSON value of ``payload``, exactly as the strict standard-library decoder gives it.

    orjson parses (in a fifth of the time); whatever it refuses is parsed again by the standard
    library, which accepts it or explains the problem.

    Raises
    ------
    MessageError
        Not UTF-8, not JSON, or a NaN/Infinity constant.
    """
    if type(payload) is bytes and _LONG_INTEGER not in payload.translate(_DIGIT_RUNS):
        try:
            return orjson.loads(payload)
        except orjson.JSONDecodeError:
            pass
    try:
        return _decoder.decode(payload.decode("utf-8") if isinstance(payload, bytes | bytearray)
                               else payload)
    except MessageError:
        raise
    except (ValueError, UnicodeDecodeError) as exc:
        raise MessageError(f"not valid JSON: {exc}") from None


def validate(type_name: str, payload: Any) -> None:
    """Check a decoded payload against the schema of ``type_name`` and the envelope relations.

    Raises
    ------
    MessageError
        For the first problem found.
    """
    check = _VALIDATORS.get(type_name)
    if check is None:
        raise MessageError(f"unknown message type {type_name!r}")
    try:
        check(payload)
    except SchemaViolation as exc:
        raise MessageError(str(exc)) from None
    if payload["t_deliver_ns"] < payload["t_send_ns"]:
        raise MessageError("$.t_deliver_ns: earlier than t_send_ns")


def decode(key: str, payload: bytes | str) -> Message:
    """Parse and validate the payload received on ``key``.

    Raises
    ------
    MessageError
        Unknown key, not UTF-8 JSON, not matching the schema of the key's type, or out of range.
    """
    type_name = _TYPE_CACHE.get(key)
    if type_name is None:
        try:
            type_name = message_type(key)
        except ValueError as exc:
            raise MessageError(str(exc)) from None
    data = parse_json(payload)
    validate(type_name, data)
    return Message(key, type_name, data["src"], data["seq"], data["t_send_ns"],
                   data["t_deliver_ns"], data)


def _body_encoder() -> Callable[[Mapping[str, Any]], str]:
    """``body -> str`` exactly as ``_encoder.encode`` (compact, no NaN), with the standard
    library's C encoder built once instead of on every call. Bodies are trees of dicts, lists and
    scalars (the agents build them), so it skips the check for circular references."""
    make = json.encoder.c_make_encoder
    if make is None:
        return _encoder.encode
    iterencode = make(None, _encoder.default, json.encoder.encode_basestring_ascii, None,
                      ":", ",", False, False, False)
    return lambda body: "".join(iterencode(body, 0))


_encode_body = _body_encoder()


def encode(type_name: str, src: str, seq: int, t_send_ns: int, t_deliver_ns: int,
           body: Mapping[str, Any]) -> bytes:
    """Return the payload (UTF-8 JSON, no spaces) of an envelope with ``body``.

    The envelope's fields come first, in the order of :data:`ENVELOPE_FIELDS`, then the body's.

    Raises
    ------
    ValueError
        A non-finite number in ``body`` (JSON has none), or a body field named like an
        envelope field.
    """
    if not body:
        tail = "}"
    else:
        if not _ENVELOPE_SET.isdisjoint(body):
            raise ValueError(f"body fields {sorted(_ENVELOPE_SET & set(body))} are envelope fields")
        tail = "," + _encode_body(body)[1:]
    return (f'{_head(type_name, src)}{int(seq)},"t_send_ns":{int(t_send_ns)},'
            f'"t_deliver_ns":{int(t_deliver_ns)}{tail}').encode()


_ENVELOPE_SET = frozenset(ENVELOPE_FIELDS)


@functools.lru_cache(maxsize=1024)
def _head(type_name: str, src: str) -> str:
    """The constant start of every envelope of one type from one sender, up to ``"seq":``."""
    return (f'{{"v":{MESSAGE_VERSION},"type":{_encoder.encode(type_name)},'
            f'"src":{_encoder.encode(src)},"seq":')


MAX_FRAME_BYTES = 32 * 1024
"""A frame grows to at most this size (one envelope may exceed it alone), so that a sample fits
in one Zenoh transport batch (64 KiB) and is never fragmented."""


def frames(messages: list[tuple[str, bytes]],
           max_bytes: int = MAX_FRAME_BYTES) -> list[tuple[str, bytes]]:
    """Group ``(key, payload)`` envelopes into samples per key (JSON Lines) of at most
    ``max_bytes``, keeping the order of the envelopes of each key."""
    grouped: dict[str, list[list]] = {}
    for key, payload in messages:
        chunks = grouped.setdefault(key, [])
        if chunks and chunks[-1][0] + len(payload) + 1 <= max_bytes:
            chunks[-1][0] += len(payload) + 1
            chunks[-1][1].append(payload)
        else:
            chunks.append([len(payload), [payload]])
    return [(key, b"\n".join(payloads)) for key, chunks in grouped.items()
            for _, payloads in chunks]


def split_frame(frame: bytes) -> list[bytes]:
    """The envelopes of one sample (see the framing above)."""
    return frame.split(b"\n") if b"\n" in frame else [frame]
