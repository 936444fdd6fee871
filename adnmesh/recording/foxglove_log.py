"""Foxglove's ``foxglove.Log`` message, the format of a recording's events topic.

A recorder given an events producer (:class:`~adnmesh.recording.Recorder`, ``events_topic``
and ``events``) writes what that producer says happened as ``foxglove.Log`` messages, in their
JSON form, so that Foxglove's log panel shows them. This module knows only the format: the
schema's name, its JSON Schema and how one record is built; what counts as an event is the
producer's business (``adnmesh up`` passes :class:`adnmesh.results.eventlog.EventLog`).
"""

from __future__ import annotations

import json

__all__ = ["FOXGLOVE_LOG", "FOXGLOVE_LOG_SCHEMA", "LOG_LEVELS", "log_record"]

FOXGLOVE_LOG = "foxglove.Log"
"""The schema name Foxglove recognises for log messages (JSON encoding)."""

LOG_LEVELS = {"UNKNOWN": 0, "DEBUG": 1, "INFO": 2, "WARN": 3, "WARNING": 3, "ERROR": 4,
              "FATAL": 5}
"""adnmesh's event levels -> the ``foxglove.Log`` level enum."""

FOXGLOVE_LOG_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": FOXGLOVE_LOG,
    "description": "A log message",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object", "title": "time",
            "description": "Timestamp of log message",
            "properties": {"sec": {"type": "integer", "minimum": 0},
                           "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
        },
        "level": {"title": "foxglove.LogLevel", "description": "Log level",
                  "oneOf": [{"title": name, "const": value} for name, value in
                            (("UNKNOWN", 0), ("DEBUG", 1), ("INFO", 2), ("WARNING", 3),
                             ("ERROR", 4), ("FATAL", 5))]},
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "maximum": 4294967295,
                 "description": "Line number in the file"},
    },
}
"""The JSON Schema of ``foxglove.Log`` (fields timestamp {sec, nsec}, level, message, name,
file, line)."""


def log_record(t_ns: int, level: str, message: str, name: str, file: str = "",
               line: int = 0) -> bytes:
    """One ``foxglove.Log`` message as JSON: ``t_ns`` (ns) as {sec, nsec}, ``level`` one of
    :data:`LOG_LEVELS`; ``name`` the process or node that logged it or that it is about (what
    Foxglove's Log panel filters by), ``file`` and ``line`` its source file and line, if
    there is one (else empty and 0)."""
    return json.dumps({"timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
                       "level": LOG_LEVELS.get(level, 0), "message": message, "name": name,
                       "file": file, "line": line}, separators=(",", ":")).encode()
