"""Checking recorded messages against their channels' JSON Schemas, and counts against the agents'.

A recording carries the JSON Schema of every message type it holds (draft 2020-12), so it can be
checked without the code that wrote it: :func:`validate_recording`. What the agents say they
published is compared with what was recorded by :func:`count_differences` /
:func:`check_counts` ("nothing lost").
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass

from adnmesh.recording.reader import Recording

__all__ = ["CountDifference", "RecordingLossError", "check_counts", "count_differences",
           "validate_recording"]


def validate_recording(recording: Recording, *, limit: int | None = None) -> list[str]:
    """Check every message against its channel's JSON Schema.

    Parameters
    ----------
    recording : Recording
        As read by :func:`~adnmesh.recording.read_recording`.
    limit : int, optional
        Stop after this many problems.

    Returns
    -------
    list of str
        One line per problem (``topic #sequence: what``); empty if every message is valid.
        A schema that is itself invalid, a message that is not JSON or whose type has no
        schema are problems too.
    """
    from jsonschema import Draft202012Validator
    from jsonschema.exceptions import SchemaError

    problems: list[str] = []
    validators = {}
    for name, schema in recording.schemas.items():
        try:
            Draft202012Validator.check_schema(schema)
        except SchemaError as exc:
            problems.append(f"schema {name!r}: invalid JSON Schema: {exc.message}")
            continue
        validators[name] = Draft202012Validator(schema)
    for message in recording.messages:
        if limit is not None and len(problems) >= limit:
            break
        where = f"{message.topic} #{message.sequence}"
        validator = validators.get(message.schema_name)
        if validator is None:
            if message.schema_name not in recording.schemas:
                problems.append(f"{where}: no JSON Schema for type {message.schema_name!r}")
            continue
        try:
            payload = json.loads(message.data)
        except ValueError as exc:
            problems.append(f"{where}: payload is not JSON: {exc}")
            continue
        error = next(iter(sorted(validator.iter_errors(payload), key=lambda e: e.path)), None)
        if error is not None:
            at = "/".join(str(p) for p in error.absolute_path) or "(top level)"
            problems.append(f"{where}: {at}: {error.message}")
    return problems


@dataclass(frozen=True)
class CountDifference:
    """A topic whose published and recorded message counts differ."""

    topic: str
    published: int
    recorded: int

    def __str__(self) -> str:
        return f"{self.topic}: published {self.published}, recorded {self.recorded}"


class RecordingLossError(RuntimeError):
    """The recording does not hold exactly what the agents published."""

    def __init__(self, differences: list[CountDifference]) -> None:
        self.differences = differences
        shown = "; ".join(str(d) for d in differences[:5])
        more = f" (and {len(differences) - 5} more topics)" if len(differences) > 5 else ""
        super().__init__(f"recording incomplete on {len(differences)} topic(s): {shown}{more}")


def count_differences(published: Mapping[str, int],
                      recorded: Mapping[str, int]) -> list[CountDifference]:
    """Return the topics whose counts differ (a topic missing on one side counts 0), sorted."""
    topics = sorted(set(published) | set(recorded))
    return [CountDifference(t, int(published.get(t, 0)), int(recorded.get(t, 0)))
            for t in topics if int(published.get(t, 0)) != int(recorded.get(t, 0))]


def check_counts(published: Mapping[str, int], recorded: Mapping[str, int]) -> None:
    """Raise :class:`RecordingLossError` unless both count every topic the same."""
    differences = count_differences(published, recorded)
    if differences:
        raise RecordingLossError(differences)
