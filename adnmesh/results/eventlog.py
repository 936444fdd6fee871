"""The run's events as ``foxglove.Log`` messages, so Foxglove's log panel shows them.

While it records, the recorder (:class:`~adnmesh.recording.Recorder`, to which ``adnmesh up``
passes :meth:`EventLog.observe` as its ``events``) gives each message to an :class:`EventLog`,
which says what happened in the words of
:mod:`adnmesh.results.rules` (the same rules ``replay`` and ``inspect`` use): gain switches,
availability changes (SI, a DER's heartbeat flag), injected faults, the agents' own events
(watchdog fallbacks, overruns, alarms), rejected payloads and the run's start. Each becomes a
message in Foxglove's ``foxglove.Log`` schema, in its JSON form, on the events topic, at the
event's send time (sim time in sim mode, as every message's time). The format is
:mod:`adnmesh.recording.foxglove_log`'s; the rules of what is an event are here.

Only the messages that can hold an event are decoded (a ``p_y`` message only if it carries a
switch record); the 100 Hz state and measurement messages are not.
"""

from __future__ import annotations

import json

from adnmesh.recording.foxglove_log import log_record
from adnmesh.results.rules import (AVAILABILITY_KEYS, EVENTS, availability_change,
                                   available_ders, match_key, message_body)

__all__ = ["EventLog"]

_REJECTED = "rejected"   # the recorder tap's type of rejected payloads
_SKIPPED = {"der_mode"}  # 100 Hz states; a watchdog fallback is also an agent's event


class EventLog:
    """Finds events in recorded messages, one topic's previous message at a time."""

    def __init__(self) -> None:
        self._rules: dict[str, list] = {}
        self._previous: dict[str, dict] = {}
        self._available: frozenset[str] | None = None

    def observe(self, topic: str, schema_name: str, payload: bytes,
                t_ns: int) -> list[bytes]:
        """The ``foxglove.Log`` messages (JSON) of the events in one message sent at ``t_ns``."""
        if schema_name == _REJECTED:
            return [self._rejected(payload, t_ns)]
        rules = self._rules.get(topic)
        if rules is None:
            rules = self._rules[topic] = self._plan(topic)
        if not rules or (schema_name == "p_y" and b'"switch"' not in payload):
            return []
        try:
            body = message_body(json.loads(payload))
        except ValueError:
            return []
        found = []
        for kind, rule, captures in rules:
            if kind == "availability":
                found += self._availability(body, t_ns)
                continue
            event = rule(body, None if kind == "gain_switch" else self._previous.get(topic),
                         captures)
            if event is not None:
                level, text, _ = event
                found.append(log_record(t_ns, level, text, kind, topic))
        self._previous[topic] = body
        return found

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
        return [log_record(t_ns, level, text, "availability")]

    def _rejected(self, payload: bytes, t_ns: int) -> bytes:
        try:
            body = json.loads(payload)
            text = f"rejected a payload on {body['key']}: {body['reason']} ({body['detail']})"
        except (ValueError, KeyError, TypeError):
            text = "rejected a payload"
        return log_record(t_ns, "WARNING", text, "rejected")
