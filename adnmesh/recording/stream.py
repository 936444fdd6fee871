"""Reading a recording in one streaming pass, as NumPy columns (``inspect``, ``plot``, ``replay``).

:func:`scan` goes through an MCAP file front to back, one record and one chunk in memory at a
time (:class:`~adnmesh.recording.mcap_records.TopLevelRecords`, as
:func:`~adnmesh.recording.read_recording` goes through it), so an unfinished file of a killed
run reads as far as its last whole record. Message records are located through the message
indexes that follow each chunk (the stretches of a chunk they do not cover, a chunk without
indexes and one whose indexes do not fit it are walked record by record) and their heads (channel, times) are read as NumPy columns:
there is no Python object per message. Payloads are handed on, a chunk at a time, only for
the channels a caller asks for; every channel's count and time range is kept.

:func:`decode_fields` decodes a batch of JSON payloads into columns of a few named fields with
``msgspec`` (one call per batch, unknown fields skipped).

Errors are those of :func:`~adnmesh.recording.read_recording`, in the same words (both read
through :mod:`~adnmesh.recording.mcap_records`): a :class:`RecordingError` of one line naming
the file for anything that is neither a complete nor a truncated MCAP file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from operator import attrgetter
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema

from adnmesh.recording.mcap_records import (MESSAGE_HEAD, RECORD_HEAD, TopLevelRecords,
                                            chunk_content, chunk_records, open_recording,
                                            parse_inner, parse_record, schema_not_json,
                                            unknown_channel)
from adnmesh.recording.reader import ChannelInfo
from adnmesh.recording.writer import RUN_METADATA, SCHEMA_ENCODING

__all__ = [
    "ChannelStats",
    "FieldColumns",
    "MessageBatch",
    "ScannedRecording",
    "Sink",
    "decode_fields",
    "scan",
]



class MessageBatch:
    """The messages of one channel in one chunk.

    Attributes
    ----------
    publish_time_ns, log_time_ns : numpy.ndarray of int64
        Send and delivery times, ns.
    ordinal : numpy.ndarray of int64
        Each message's position in the file (0, 1, 2, ... over all channels).
    """

    def __init__(self, publish_time_ns: np.ndarray, log_time_ns: np.ndarray,
                 ordinal: np.ndarray, payloads: Sequence[bytes] | None = None, *,
                 data: np.ndarray | None = None, starts: np.ndarray | None = None,
                 ends: np.ndarray | None = None) -> None:
        self.publish_time_ns, self.log_time_ns, self.ordinal = publish_time_ns, log_time_ns, \
            ordinal
        self._payloads = None if payloads is None else list(payloads)
        self._data, self._starts, self._ends = data, starts, ends
        self.columns: FieldColumns | None = None
        """Decoded fields, if the reader decoded them (for a sink with ``fields``)."""

    def __len__(self) -> int:
        return self.publish_time_ns.size

    def select(self, rows: np.ndarray) -> MessageBatch:
        """The batch of the messages ``rows`` (indices), in that order."""
        if self._payloads is not None:
            chosen = MessageBatch(self.publish_time_ns[rows], self.log_time_ns[rows],
                                  self.ordinal[rows], [self._payloads[i] for i in rows.tolist()])
        else:
            chosen = MessageBatch(self.publish_time_ns[rows], self.log_time_ns[rows],
                                  self.ordinal[rows], data=self._data,
                                  starts=self._starts[rows], ends=self._ends[rows])
        if self.columns is not None:
            picked = rows.tolist()
            chosen.columns = FieldColumns(self.columns.valid[rows], {
                k: [v[i] for i in picked] for k, v in self.columns.columns.items()})
        return chosen

    @property
    def payloads(self) -> list[bytes]:
        """The payloads, one bytes object each."""
        if self._payloads is None:
            data = self._data.data
            self._payloads = [bytes(data[s:e]) for s, e in zip(self._starts.tolist(),
                                                               self._ends.tolist())]
        return self._payloads

    def lengths(self) -> np.ndarray:
        """Payload sizes, bytes."""
        if self._payloads is not None:
            return np.fromiter(map(len, self._payloads), dtype=np.int64,
                               count=len(self._payloads))
        return self._ends - self._starts

    def json_array(self) -> bytes:
        """The payloads joined into one JSON array text: ``[p1,p2,...]``."""
        if self._payloads is not None:
            return b"[" + b",".join(self._payloads) + b"]"
        lengths = self._ends - self._starts
        total, n = int(lengths.sum()), lengths.size
        out = np.full(total + n + 1, ord(","), dtype=np.uint8)
        out[0], out[-1] = ord("["), ord("]")
        before = np.cumsum(lengths) - lengths
        source = np.arange(total) + np.repeat(self._starts - before, lengths)
        out[1 + np.repeat(np.arange(n), lengths) + np.arange(total)] = self._data[source]
        return out.tobytes()


Sink = Callable[[MessageBatch], None]
"""Takes the batches of one channel, in file order. A sink with an attribute ``fields`` (a
tuple of payload field names) gets them decoded in :attr:`MessageBatch.columns`."""


@dataclass
class ChannelStats:
    """A channel of a scanned recording: what it is, how many messages and their times."""

    info: ChannelInfo
    count: int = 0
    first_publish_ns: int | None = None
    last_publish_ns: int | None = None
    earliest_ns: int | None = None   # over send and delivery times
    latest_ns: int | None = None

    def take(self, publish: np.ndarray, log: np.ndarray) -> None:
        """Count the messages with these send and delivery times, ns."""
        self.count += publish.size
        low, high = int(min(publish.min(), log.min())), int(max(publish.max(), log.max()))
        first, last = int(publish.min()), int(publish.max())
        self.first_publish_ns = first if self.first_publish_ns is None else \
            min(self.first_publish_ns, first)
        self.last_publish_ns = last if self.last_publish_ns is None else \
            max(self.last_publish_ns, last)
        self.earliest_ns = low if self.earliest_ns is None else min(self.earliest_ns, low)
        self.latest_ns = high if self.latest_ns is None else max(self.latest_ns, high)


@dataclass
class ScannedRecording:
    """What :func:`scan` read: everything of a :class:`~adnmesh.recording.Recording` except
    the messages themselves (channels by topic, with counts and time ranges)."""

    path: Path
    channel_stats: dict[str, ChannelStats] = field(default_factory=dict)
    schemas: dict[str, dict] = field(default_factory=dict)
    metadata_records: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    library: str = ""
    complete: bool = False
    dropped_bytes: int = 0

    @property
    def channels(self) -> dict[str, ChannelInfo]:
        """Per topic, in order of first appearance."""
        return {topic: stats.info for topic, stats in self.channel_stats.items()}

    @property
    def message_count(self) -> int:
        """Messages read."""
        return sum(stats.count for stats in self.channel_stats.values())

    @property
    def recovered_messages(self) -> int:
        """The number of messages read from a truncated file (0 for a complete one)."""
        return 0 if self.complete else self.message_count

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (a later record of the same name adds to and overrides)."""
        merged: dict[str, dict[str, str]] = {}
        for name, data in self.metadata_records:
            merged.setdefault(name, {}).update(data)
        return merged

    @property
    def run(self) -> dict[str, str]:
        """The ``adnmesh.run`` metadata record (empty if absent)."""
        return self.metadata.get(RUN_METADATA, {})

    def counts(self) -> dict[str, int]:
        """Messages per topic, topics in order of first appearance."""
        return {topic: stats.count for topic, stats in self.channel_stats.items()}

    def time_range_ns(self) -> tuple[int, int] | None:
        """(earliest, latest) over send and delivery times, ns; None without messages."""
        seen = [s for s in self.channel_stats.values() if s.count]
        if not seen:
            return None
        return min(s.earliest_ns for s in seen), max(s.latest_ns for s in seen)


def _index_offsets(body: bytes) -> np.ndarray | None:
    """The message offsets of a message index record's ``body`` (channel 2, entries' bytes 4,
    then (log time, offset) pairs of 8 bytes), as a NumPy column; None if it is malformed."""
    if len(body) < 6 or int.from_bytes(body[2:6], "little") != len(body) - 6 \
            or (len(body) - 6) % 16:
        return None
    entries = np.frombuffer(body, dtype="<u8", offset=6)
    return entries[1::2].astype(np.int64)


class _Scanner:
    """State of one :func:`scan`: schemas, channels, the chunk waiting for its indexes."""

    def __init__(self, path: Path, sink_for: Callable[[ChannelInfo], Sink | None]) -> None:
        self.result = ScannedRecording(path=path)
        self.sink_for = sink_for
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, tuple[ChannelStats, Sink | None]] = {}
        self.pending: tuple[Chunk, int] | None = None
        self.indexes: list[np.ndarray] | None = []   # None: an index was malformed
        self.ordinal = 0

    def take(self, opcode: int, offset: int, body: bytes) -> None:
        """Take one top-level record that starts at byte ``offset``."""
        if opcode == Opcode.MESSAGE_INDEX:
            offsets = _index_offsets(body)
            if offsets is None:
                self.indexes = None        # walk the chunk instead
            elif self.indexes is not None:
                self.indexes.append(offsets)
            return
        self.flush()
        record = parse_record(self.result.path, opcode, offset, body)
        if isinstance(record, Chunk):
            self.pending = (record, offset)
        elif isinstance(record, Header):
            self.result.library = record.library
        elif isinstance(record, Metadata):
            self.result.metadata_records.append((record.name, dict(record.metadata)))
        elif isinstance(record, (Schema, Channel)):
            self.register(record)
        elif isinstance(record, Message):       # outside any chunk: a chunk of its own
            head = RECORD_HEAD.pack(opcode, len(body))
            self.dispatch(head + body, np.zeros(1, np.int64),
                          np.asarray([RECORD_HEAD.size + len(body)], np.int64), offset)

    def register(self, record: Schema | Channel) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
            if record.encoding == SCHEMA_ENCODING and record.name not in self.result.schemas:
                try:
                    self.result.schemas[record.name] = json.loads(record.data)
                except ValueError:
                    raise schema_not_json(self.result.path, record.name) from None
            return
        if record.id in self.channels:
            return
        schema = self.schemas.get(record.schema_id)
        info = ChannelInfo(topic=record.topic, message_encoding=record.message_encoding,
                           schema_name=schema.name if schema else "",
                           metadata=dict(record.metadata))
        stats = self.result.channel_stats.setdefault(record.topic, ChannelStats(info))
        self.channels[record.id] = (stats, self.sink_for(stats.info))

    def flush(self) -> None:
        """Read the chunk waiting for its message indexes, if any."""
        if self.pending is None:
            return
        (chunk, offset), indexes = self.pending, self.indexes
        self.pending, self.indexes = None, []
        data = chunk_content(self.result.path, chunk, offset)
        starts, ends = _message_records(self.result.path, data, indexes, offset, self.register)
        self.dispatch(data, starts, ends, offset)

    def dispatch(self, data: bytes, starts: np.ndarray, ends: np.ndarray, offset: int) -> None:
        """Hand the messages of a chunk (record ``starts`` and ``ends``) to their channels."""
        if not starts.size:
            return
        raw = np.frombuffer(data, dtype=np.uint8)
        channel = _column(raw, starts + 9, 2, "<u2")
        log = _column(raw, starts + 15, 8, "<u8").astype(np.int64)
        publish = _column(raw, starts + 23, 8, "<u8").astype(np.int64)
        ordinal = np.arange(self.ordinal, self.ordinal + starts.size, dtype=np.int64)
        self.ordinal += starts.size
        by_channel = np.argsort(channel, kind="stable")
        counts = np.bincount(channel)
        present = np.flatnonzero(counts)
        groups = []
        for channel_id, mine in zip(present.tolist(),
                                    np.split(by_channel, np.cumsum(counts[present])[:-1])):
            if channel_id not in self.channels:
                raise unknown_channel(self.result.path, channel_id, offset)
            stats, sink = self.channels[channel_id]
            stats.take(publish[mine], log[mine])
            if sink is not None:
                groups.append((mine, sink))
        decoded = _decode_chunk(data, starts, ends, groups)
        for mine, sink in groups:
            batch = MessageBatch(publish[mine], log[mine], ordinal[mine], data=raw,
                                 starts=starts[mine] + MESSAGE_HEAD, ends=ends[mine])
            if decoded is not None and getattr(sink, "fields", None) is not None:
                batch.columns = decoded.select(mine, sink.fields)
            sink(batch)


def _decode_chunk(data: bytes, starts: np.ndarray, ends: np.ndarray,
                  groups: list) -> _ChunkRows | None:
    """Decode every message of a chunk at once with the fields the sinks want (the chunk's
    bytes with every record head blanked are one JSON array); None if no sink wants fields
    or a payload is not a JSON object (then each sink decodes its own)."""
    names = tuple(dict.fromkeys(name for _, sink in groups
                                for name in (getattr(sink, "fields", None) or ())))
    if not names:
        return None
    text = bytearray(data)
    text += b"]"
    blank = np.frombuffer(text, dtype=np.uint8)
    blank[(starts[:, None] + np.arange(MESSAGE_HEAD)).reshape(-1)] = ord(" ")
    blank[starts[1:]] = ord(",")
    blank[starts[0]] = ord("[")
    previous_ends = np.concatenate([[0], ends[:-1]])
    for a, b in zip(previous_ends[starts > previous_ends].tolist(),
                    starts[starts > previous_ends].tolist()):
        blank[a:b] = ord(" ")       # schema and channel records between messages
    blank[ends[-1]:len(data)] = ord(" ")
    del blank
    row = _row_type(names)
    try:
        rows = msgspec.json.decode(text, type=list[row])
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    lengths = ends - starts - MESSAGE_HEAD
    valid = np.ones(len(rows), dtype=bool)
    for i in np.flatnonzero(lengths < 16).tolist():
        if b"".join(data[starts[i] + MESSAGE_HEAD:ends[i]].split()) == b"{}":
            valid[i] = False
    return _ChunkRows(rows, valid, names, _BODY in text)


@dataclass(frozen=True)
class _ChunkRows:
    """The decoded messages of a chunk (see :func:`_decode_chunk`)."""

    rows: list
    valid: np.ndarray
    names: tuple[str, ...]
    bodies: bool            # some payload may have a ``body`` object

    def select(self, mine: np.ndarray, names: tuple[str, ...]) -> FieldColumns:
        """The columns ``names`` of the messages ``mine`` (indices into the chunk)."""
        picked = [self.rows[i] for i in mine.tolist()]
        attribute = {name: f"f{i}" for i, name in enumerate(self.names)}
        columns = {name: list(map(attrgetter(attribute[name]), picked)) for name in names}
        if self.bodies:
            _merge_bodies(picked, columns, f"f{len(self.names)}")
        return FieldColumns(valid=self.valid[mine], columns=columns)


def _merge_bodies(rows: list, columns: dict[str, list], attribute: str) -> None:
    """Read the fields of a payload's ``body`` object as the payload's own."""
    for i, r in enumerate(rows):
        inner = getattr(r, attribute)
        if isinstance(inner, dict):
            for name, values in columns.items():
                if name in inner:
                    values[i] = inner[name]


def _column(raw: np.ndarray, at: np.ndarray, width: int, dtype: str) -> np.ndarray:
    """The little-endian numbers of ``width`` bytes at the offsets ``at`` of ``raw``."""
    return raw[at[:, None] + np.arange(width)].view(dtype).reshape(-1)


def _message_records(path: Path, data: bytes, indexes: list[np.ndarray] | None, offset: int,
                     register: Callable[[Any], None]) -> tuple[np.ndarray, np.ndarray]:
    """Start and end offsets of the message records in a chunk's ``data``, in file order.

    Messages named by the ``indexes`` are located by them; the rest of the chunk (schema and
    channel records, messages no index names) is walked record by record, and its schema and
    channel records are given to ``register``. Indexes that do not fit the chunk (or None: a
    malformed index record) are not used: the whole chunk is walked, as
    :func:`~adnmesh.recording.read_recording` walks every chunk, so that both read the same.
    """
    raw = np.frombuffer(data, dtype=np.uint8)
    starts = np.sort(np.concatenate(indexes)) if indexes else np.zeros(0, np.int64)
    ends = starts
    if starts.size:
        fits = starts[0] >= 0 and starts[-1] + MESSAGE_HEAD <= len(data) \
            and not np.any(raw[starts] != Opcode.MESSAGE)
        if fits:
            ends = starts + RECORD_HEAD.size + _column(raw, starts + 1, 8, "<u8").astype(np.int64)
            fits = not (np.any(starts[1:] < ends[:-1]) or ends[-1] > len(data))  # or twice
        if not fits:
            starts = ends = np.zeros(0, np.int64)
    found_starts, found_ends, at = [], [], 0
    for start, end in zip([*starts.tolist(), len(data)], [*ends.tolist(), len(data)]):
        for opcode, inner, stop in chunk_records(path, data, offset, at, start):
            if opcode == Opcode.MESSAGE:
                found_starts.append(inner)
                found_ends.append(stop)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                register(parse_inner(path, offset, opcode, data, inner, stop))
        at = end
    if found_starts:
        starts = np.concatenate([starts, np.asarray(found_starts, dtype=np.int64)])
        ends = np.concatenate([ends, np.asarray(found_ends, dtype=np.int64)])
        order = np.argsort(starts, kind="stable")
        starts, ends = starts[order], ends[order]
    return starts, ends


def scan(path: str | Path, sink_for: Callable[[ChannelInfo], Sink | None]) -> ScannedRecording:
    """Read ``path`` in one pass; give each channel's messages to the sink ``sink_for`` returns.

    Parameters
    ----------
    path : str or Path
        An MCAP file, complete or cut short (a killed run).
    sink_for : callable
        Called once per channel, when its record is read, with its :class:`ChannelInfo`;
        returns the sink that takes the channel's messages, or None to skip their payloads.

    Returns
    -------
    ScannedRecording
        With ``complete`` False for a truncated file (read as far as its last whole record).

    Raises
    ------
    RecordingError
        If the file is missing, not MCAP, or corrupt (e.g. a chunk's checksum does not match),
        in the words of :func:`~adnmesh.recording.read_recording`
        (:mod:`~adnmesh.recording.mcap_records`).
    """
    path = Path(path)
    scanner = _Scanner(path, sink_for)
    with open_recording(path) as stream:
        records = TopLevelRecords(path, stream, os.fstat(stream.fileno()).st_size)
        for opcode, offset, body in records:
            scanner.take(opcode, offset, body)
        scanner.flush()
    scanner.result.complete, scanner.result.dropped_bytes = records.complete, \
        records.dropped_bytes
    return scanner.result


@dataclass(frozen=True)
class FieldColumns:
    """Named fields of a batch of JSON objects, one list per field (``msgspec.UNSET`` where a
    payload lacks the field); ``valid`` marks the payloads that are non-empty JSON objects."""

    valid: np.ndarray
    columns: dict[str, list]


_ROW_TYPES: dict[tuple[str, ...], type] = {}


def _row_type(names: tuple[str, ...]) -> type:
    """A msgspec Struct with the fields ``names`` (and ``body``), each of any type."""
    row = _ROW_TYPES.get(names)
    if row is None:
        attributes = [f"f{i}" for i in range(len(names) + 1)]
        row = msgspec.defstruct("Row", [(a, Any, msgspec.UNSET) for a in attributes],
                                rename=dict(zip(attributes, (*names, "body"))), gc=False)
        _ROW_TYPES[names] = row
    return row


def decode_fields(batch: MessageBatch, names: tuple[str, ...]) -> FieldColumns:
    """Decode the fields ``names`` of a batch's JSON payloads, in one msgspec call where all
    are JSON objects (else one at a time; a payload that is not a JSON object is not
    ``valid``).

    A payload with a ``body`` object is read as the payload with that object's fields merged
    in (as :func:`adnmesh.results.series.extract` reads payloads).
    """
    row = _row_type(names)
    text = batch.json_array()
    try:
        rows = msgspec.json.decode(text, type=list[row])
        valid = np.ones(len(rows), dtype=bool)
    except (msgspec.DecodeError, msgspec.ValidationError):
        rows, valid = _decode_one_by_one(batch.payloads, row, names)
    lengths = batch.lengths()
    for i in np.flatnonzero(lengths < 16).tolist():
        if b"".join(batch.payloads[i].split()) == b"{}":
            valid[i] = False
    attributes = [f"f{i}" for i in range(len(names))]
    columns = {name: list(map(attrgetter(a), rows)) for name, a in zip(names, attributes)}
    if _BODY in text:
        _merge_bodies(rows, columns, f"f{len(names)}")
    return FieldColumns(valid=valid, columns=columns)


_BODY = b'"body"'


def _decode_one_by_one(payloads, row, names) -> tuple[list, np.ndarray]:
    """Decode payloads singly (some are no JSON objects, or JSON msgspec does not read, such
    as NaN: those go through :func:`json.loads`)."""
    rows, valid = [], np.ones(len(payloads), dtype=bool)
    empty = row()
    for i, payload in enumerate(payloads):
        try:
            rows.append(msgspec.json.decode(payload, type=row))
            continue
        except (msgspec.DecodeError, msgspec.ValidationError):
            pass
        try:
            document = json.loads(payload)
        except ValueError:
            document = None
        if isinstance(document, dict):
            rows.append(row(*(document.get(n, msgspec.UNSET) for n in (*names, "body"))))
        else:
            rows.append(empty)
            valid[i] = False
    return rows, valid
