"""Several recordings of one run as one: ``adnmesh merge`` (docs/recordings.md#merge).

A run whose messages were recorded in several places (each level of a hierarchy, each site)
is read back as one recording by :func:`merge_recordings`:

- every message of every input, in delivery-time order (send time, then the input's order,
  breaking ties), each with its channel's message type and schema;
- a message recorded in two places (the same topic, payload, send and delivery time) once;
- the run metadata of the first input, with ``merged_from`` (the inputs' file names) and
  ``merged_grids``; each other input's run metadata as ``adnmesh.run.<n>`` (n from 2);
- the agents' published counts (:data:`~adnmesh.recording.writer.PUBLISHED_METADATA`) of all
  inputs, per topic (the largest where two differ), so that ``adnmesh inspect`` checks that
  every published message was recorded somewhere; the topics nobody counted of all inputs,
  and each input's log of events but the first's (which stays the run's ``events_topic``).

Refused, one line each (:class:`~adnmesh.errors.UsageError`): a topic of two message types or a
message type of two schemas, two inputs of different runs (both name a ``run_id``), an output
that is one of the inputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from adnmesh.errors import UsageError
from adnmesh.recording.reader import Recording, read_recording
from adnmesh.recording.writer import (PUBLISHED_METADATA, RUN_METADATA, UNCOUNTED_METADATA,
                                      Recorder)

__all__ = ["MergeResult", "describe", "merge_recordings"]


@dataclass(frozen=True)
class MergeResult:
    """What :func:`merge_recordings` wrote: messages written, duplicates dropped, the inputs
    that were truncated (recovered as far as they were written) and the grids
    (``adn/<grid>/...``) of the merged recording."""

    messages: int
    duplicates: int
    truncated: tuple[str, ...]
    grids: tuple[str, ...]


def _check(recordings: list[Recording]) -> tuple[dict[str, str], dict[str, dict]]:
    """``(topic -> message type, message type -> schema)`` of all inputs (see the module
    docstring for what is refused)."""
    types: dict[str, tuple[str, Path]] = {}
    schemas: dict[str, tuple[dict, Path]] = {}
    runs: dict[str, Path] = {}
    for r in recordings:
        run_id = r.run.get("run_id")
        if run_id is not None:
            runs.setdefault(run_id, r.path)
        for topic, info in r.channels.items():
            seen = types.setdefault(topic, (info.schema_name, r.path))
            if seen[0] != info.schema_name:
                raise UsageError(f"{r.path}: topic {topic} holds {info.schema_name or 'no type'}"
                                 f" messages, {seen[1]} holds {seen[0] or 'no type'}: not one "
                                 "run's recordings")
        for name, schema in r.schemas.items():
            seen_schema = schemas.setdefault(name, (schema, r.path))
            if seen_schema[0] != schema:
                raise UsageError(f"{r.path}: message type {name} has another schema than in "
                                 f"{seen_schema[1]} (recorded by another adnmesh version?)")
    if len(runs) > 1:
        (a, path_a), (b, path_b) = list(runs.items())[:2]
        raise UsageError(f"{path_b} is of run {b}, {path_a} of run {a}: only one run's "
                         "recordings merge into one")
    return {t: v[0] for t, v in types.items()}, {n: v[0] for n, v in schemas.items()}


def _counts(recordings: list[Recording]) -> tuple[dict[str, str], dict[str, str]]:
    """The published counts and the topics nobody counted, of all inputs (module docstring)."""
    published: dict[str, int] = {}
    uncounted: dict[str, str] = {}
    for n, r in enumerate(recordings):
        for topic, count in r.metadata.get(PUBLISHED_METADATA, {}).items():
            try:
                published[topic] = max(published.get(topic, 0), int(count))
            except ValueError:
                continue                        # not a count: nothing to check it against
        uncounted.update(r.metadata.get(UNCOUNTED_METADATA, {}))
        events = r.run.get("events_topic")
        if n and events:
            uncounted[events] = "the recorder's log of the run's events (another input's)"
    return {k: str(v) for k, v in published.items()}, uncounted


def merge_recordings(inputs: list[Path], out: Path) -> MergeResult:
    """Merge the recordings ``inputs`` (two or more) into ``out`` (see the module docstring).

    Raises
    ------
    UsageError
        One line: see the module docstring.
    RecordingError
        An input that cannot be read.
    """
    out_resolved = Path(out).resolve()
    if any(Path(p).resolve() == out_resolved for p in inputs):
        raise UsageError(f"{out}: is one of the recordings to merge; write to another file")
    recordings = [read_recording(p) for p in inputs]
    types, schemas = _check(recordings)
    rows, seen, duplicates = [], set(), 0
    for n, r in enumerate(recordings):
        for m in r.messages:
            identity = (m.topic, m.log_time_ns, m.publish_time_ns, m.data)
            if identity in seen:
                duplicates += 1
                continue
            seen.add(identity)
            rows.append((m.log_time_ns, m.publish_time_ns, n, m.sequence, m))
    rows.sort(key=lambda row: row[:4])
    grids = tuple(dict.fromkeys(t.split("/")[1] for t in types
                                if t.startswith("adn/") and t.count("/") >= 2))
    run = dict(recordings[0].run)
    run.update({"merged_from": " ".join(Path(p).name for p in inputs),
                "merged_grids": " ".join(grids)})
    published, uncounted = _counts(recordings)
    with Recorder(out, metadata=run, schemas=schemas) as recorder:
        for _, _, _, _, m in rows:
            recorder.write(m.topic, types[m.topic], m.data, log_time_ns=m.log_time_ns,
                           publish_time_ns=m.publish_time_ns)
        for n, r in enumerate(recordings[1:], 2):
            recorder.add_metadata(f"{RUN_METADATA}.{n}", r.run)
        if published:
            recorder.add_metadata(PUBLISHED_METADATA, published)
        if uncounted:
            recorder.add_metadata(UNCOUNTED_METADATA, uncounted)
    return MergeResult(len(rows), duplicates,
                       tuple(str(r.path) for r in recordings if not r.complete), grids)


def describe(result: MergeResult, out: Path) -> str:
    """One line of what :func:`merge_recordings` wrote."""
    truncated = (f"; recovered as far as written: {', '.join(result.truncated)}"
                 if result.truncated else "")
    return (f"wrote {out}: {result.messages} messages ({result.duplicates} recorded twice, "
            f"kept once), grids {', '.join(result.grids) or 'none'}{truncated}")

