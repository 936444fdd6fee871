"""The run's events as ``foxglove.Log`` messages, so Foxglove's log panel shows them.

While it records, the recorder (:class:`~adnmesh.recording.Recorder`, to which ``adnmesh up``
passes :meth:`EventLog.observe` as its ``events``) gives each message to an :class:`EventLog`,
which says what happened in the words of
:mod:`adnmesh.results.rules` (the same rules ``replay`` and ``inspect`` use): gain switches,
availability changes (SI, a DER's heartbeat flag), injected faults, the agents' own events
(watchdog fallbacks, overruns, alarms), rejected payloads and the run's start; and, once
a step's window has closed, a step over what its table entry was certified for
(:class:`~adnmesh.results.design_watch.OverDesignWatch`, kind ``over_design``). Each becomes a
message in Foxglove's ``foxglove.Log`` schema, in its JSON form, on the events topic, at the
event's send time (sim time in sim mode, as every message's time). The format is
:mod:`adnmesh.recording.foxglove_log`'s; the rules of what is an event are here.

The record's fields are used as Foxglove defines them: ``name`` is the agent (process) the
event is about or that sent it (``cpfc``, ``der/SGen1``, ``availability``, ``up``), which
Foxglove's Log panel filters by; ``message`` starts with the event's kind in brackets
(``[gain_switch] gain switch to entry 3: ...``); ``file`` is empty and ``line`` 0 (an event has
no source file).

Only the messages that can hold an event are decoded (a ``p_y`` message only if it carries a
switch record); the 100 Hz state and measurement messages are not.
"""

from __future__ import annotations

import json
import re

from adnmesh.names import AGENT_PATTERN, LAUNCHER, der_agent_id
from adnmesh.recording.foxglove_log import log_record
from adnmesh.results.design_watch import WATCHED_TYPES, OverDesignWatch
from adnmesh.results.rules import (AVAILABILITY_KEYS, EVENTS, availability_change,
                                   available_ders, match_key, message_body)

__all__ = ["EventLog"]

_REJECTED = "rejected"   # the recorder tap's type of rejected payloads
_SKIPPED = {"der_mode"}  # 100 Hz states; a watchdog fallback is also an agent's event
_AGENT = re.compile(AGENT_PATTERN)


class EventLog:
    """Finds events in recorded messages, one topic's previous message at a time."""

    def __init__(self) -> None:
        self._rules: dict[str, list] = {}
        self._previous: dict[str, dict] = {}
        self._available: frozenset[str] | None = None
        self._design = OverDesignWatch()

    def observe(self, topic: str, schema_name: str, payload: bytes,
                t_ns: int) -> list[bytes]:
        """The ``foxglove.Log`` messages (JSON) of the events in one message sent at ``t_ns``."""
        if schema_name == _REJECTED:
            return [self._rejected(payload, t_ns)]
        over = [_record(t_ns, "WARNING", text, "over_design", "cpfc")   # the CPFC's entry
                for _, text in self._design.observe(schema_name, payload, t_ns)]
        rules = self._rules.get(topic)
        if rules is None:
            rules = self._rules[topic] = self._plan(topic)
        if not rules or (schema_name == "p_y" and b'"switch"' not in payload):
            return over
        try:
            body = message_body(json.loads(payload))
        except ValueError:
            return over
        found = []
        for kind, rule, captures in rules:
            if kind == "availability":
                found += self._availability(body, t_ns)
                continue
            event = rule(body, None if kind == "gain_switch" else self._previous.get(topic),
                         captures)
            if event is not None:
                level, text, data = event
                found.append(_record(t_ns, level, text, data.get("kind", kind)
                                     if kind == "event" else kind, _agent(kind, body, captures)))
        self._previous[topic] = body
        return over + found

    def quiet(self, topic: str, schema_name: str) -> bool:
        """True if :meth:`observe` finds no event in any message of ``schema_name`` on
        ``topic`` (a DER's state, a clock report or grant): the recorder need not ask
        (:class:`~adnmesh.recording.writer.Recorder`'s ``events_quiet``)."""
        if schema_name == _REJECTED or schema_name in WATCHED_TYPES:
            return False
        rules = self._rules.get(topic)
        if rules is None:
            rules = self._rules[topic] = self._plan(topic)
        return not rules

    @staticmethod
    def _plan(topic: str) -> list:
        rules = [(rule.kind, rule.rule, captures) for pattern, rule in EVENTS.items()
                 if rule.kind not in _SKIPPED
                 and (captures := match_key(pattern, topic)) is not None]
        if any(match_key(p, topic) is not None for p in AVAILABILITY_KEYS):
            rules.append(("availability", None, {}))
        return rules

    def _availability(self, body: dict, t_ns: int) -> list[bytes]:
        available, _ = available_ders(body)
        found = availability_change(available, self._available)
        self._available = frozenset(available)
        if found is None:
            return []
        level, text, _ = found
        return [_record(t_ns, level, text, "availability", _agent("availability", body, {}))]

    def _rejected(self, payload: bytes, t_ns: int) -> bytes:
        try:
            body = json.loads(payload)
            text = f"rejected a payload on {body['key']}: {body['reason']} ({body['detail']})"
        except (ValueError, KeyError, TypeError):
            text = "rejected a payload"
        return _record(t_ns, "WARNING", text, "rejected", LAUNCHER)


def _record(t_ns: int, level: str, text: str, kind: str, agent: str) -> bytes:
    """One ``foxglove.Log`` record with its fields as Foxglove defines them: ``name`` the agent
    (process) the event is about or that sent it (what Foxglove's Log panel filters by), the
    event's kind first in ``message`` (``[gain_switch] gain switch to entry 3: ...``), no
    source file (``file`` empty, ``line`` 0)."""
    return log_record(t_ns, level, f"[{kind}] {text}", agent)


def _agent(kind: str, body: dict, captures: dict) -> str:
    """The agent an event is about or that sent it: the DER's (``der/<id>``) for a DER's key;
    for a fault, the agent or DER it hits (else its sender, ``up``); for an event ``up`` or
    an agent sent about an agent (``subject``), that agent; else the sender (``src``)."""
    if captures.get("der"):
        return der_agent_id(captures["der"])
    if kind == "fault":
        if isinstance(body.get("agent"), str) and body["agent"]:
            return body["agent"]
        if isinstance(body.get("der"), str) and body["der"]:
            return der_agent_id(body["der"])
    subject = body.get("subject")
    if kind == "event" and isinstance(subject, str) and _AGENT.fullmatch(subject):
        return subject
    src = body.get("src")
    return src if isinstance(src, str) else ""
