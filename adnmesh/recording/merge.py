"""Several recordings of one run as one: ``adnmesh merge`` (docs/recordings.md#merge).

A run whose messages were recorded in several places (each level of a hierarchy, each site)
is read back as one recording by :func:`merge_recordings`:

- every message of every input, in delivery-time order (send time, then the inputs' order and
  each input's own, breaking ties), each with its channel's message type and schema;
- a message recorded in two places (the same topic, payload and send time; delivered at
  different times at two sites) once, at its earliest delivery;
- the run metadata of the first input, with ``merged_from`` (the inputs' file names) and
  ``merged_grids``; each other input's run metadata as ``adnmesh.run.<n>`` (n from 2);
- the agents' published counts (:data:`~adnmesh.recording.writer.PUBLISHED_METADATA`) of all
  inputs, per topic (the largest where two differ), so that ``adnmesh inspect`` checks that
  every published message was recorded somewhere; the topics nobody counted of all inputs,
  each input's log of events but the first's (which stays the run's ``events_topic``), and
  the topics only inputs without counts hold (a killed run's file has none).

OUT is written to a hidden file beside it and renamed when complete: a merge cut short leaves
no OUT. The inputs are read whole: about 880 MB for two inputs of 500,000 messages each.

Refused, one line each (:class:`~adnmesh.errors.UsageError`): a topic of two message types or
without a JSON schema, a message type of two schemas, two inputs of different runs (both name
a ``run_id``), an input named twice, an output that is one of the inputs.
"""

from __future__ import annotations

import os
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
            if not info.schema_name or info.schema_name not in r.schemas:
                raise UsageError(f"{r.path}: topic {topic} has no JSON schema (not an adnmesh "
                                 "recording): only adnmesh recordings merge")
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
    without = [r for r in recordings if PUBLISHED_METADATA not in r.metadata]
    for n, r in enumerate(recordings):
        for topic, count in r.metadata.get(PUBLISHED_METADATA, {}).items():
            try:
                published[topic] = max(published.get(topic, 0), int(count))
            except ValueError:
                continue                        # not a count: nothing to check it against
        uncounted.update(r.metadata.get(UNCOUNTED_METADATA, {}))
        events = r.run.get("events_topic")
        if n and events:
            uncounted[events] = "another input's log of the run's events"
    if published:          # topics only inputs without counts hold (a killed run's) are not
        for r in without:  # checked: nobody said what was published on them
            for topic in r.channels:
                if topic not in published:
                    uncounted.setdefault(topic, f"{r.path.name} has no published counts")
    return {k: str(v) for k, v in published.items()}, uncounted


def _distinct_files(inputs: list[Path], out: Path) -> None:
    """Refuse an input named twice and an OUT that is an input (by the file, not its name)."""
    for i, a in enumerate(inputs):
        for b in inputs[i + 1:]:
            if a.exists() and b.exists() and os.path.samefile(a, b):
                raise UsageError(f"{b}: named twice among the recordings to merge")
        if out.exists() and a.exists() and os.path.samefile(a, out):
            raise UsageError(f"{out}: is one of the recordings to merge; write to another file")


def merge_recordings(inputs: list[Path], out: Path) -> MergeResult:
    """Merge the recordings ``inputs`` (two or more) into ``out`` (see the module docstring).

    Raises
    ------
    UsageError
        One line: see the module docstring.
    RecordingError
        An input that cannot be read.
    """
    _distinct_files([Path(p) for p in inputs], Path(out))
    recordings = [read_recording(p) for p in inputs]
    types, schemas = _check(recordings)
    rows = sorted((m.log_time_ns, m.publish_time_ns, n, k, m)
                  for n, r in enumerate(recordings) for k, m in enumerate(r.messages))
    kept, seen, duplicates = [], set(), 0
    for row in rows:               # a message is its topic, payload and send time; the
        m = row[-1]                # earliest delivery of it is kept
        identity = (m.topic, m.publish_time_ns, m.data)
        if identity in seen:
            duplicates += 1
            continue
        seen.add(identity)
        kept.append(m)
    grids = tuple(dict.fromkeys(t.split("/")[1] for t in types
                                if t.startswith("adn/") and t.count("/") >= 2))
    run = dict(recordings[0].run)
    run.update({"merged_from": " ".join(Path(p).name for p in inputs),
                "merged_grids": " ".join(grids)})
    published, uncounted = _counts(recordings)
    partial = Path(out).with_name(f".{Path(out).name}.{os.getpid()}.partial")
    try:
        with Recorder(partial, metadata=run, schemas=schemas) as recorder:
            for m in kept:
                recorder.write(m.topic, types[m.topic], m.data, log_time_ns=m.log_time_ns,
                               publish_time_ns=m.publish_time_ns)
            for n, r in enumerate(recordings[1:], 2):
                recorder.add_metadata(f"{RUN_METADATA}.{n}", r.run)
            if published:
                recorder.add_metadata(PUBLISHED_METADATA, published)
            if uncounted:
                recorder.add_metadata(UNCOUNTED_METADATA, uncounted)
        os.replace(partial, out)          # a merge cut short leaves no OUT that looks whole
    finally:
        partial.unlink(missing_ok=True)
    return MergeResult(len(kept), duplicates,
                       tuple(str(r.path) for r in recordings if not r.complete), grids)


def describe(result: MergeResult, out: Path) -> str:
    """One line of what :func:`merge_recordings` wrote."""
    truncated = (f"; recovered as far as written: {', '.join(result.truncated)}"
                 if result.truncated else "")
    return (f"wrote {out}: {result.messages} messages ({result.duplicates} recorded twice, "
            f"kept once), grids {', '.join(result.grids) or 'none'}{truncated}")

