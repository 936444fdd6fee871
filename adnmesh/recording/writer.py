"""The recorder: every message on the ``adn/**`` keys into one MCAP file.

An adnmesh recording is an ordinary MCAP file (https://mcap.dev) that Foxglove opens as it is:

- one **schema** record per message type (schema encoding ``jsonschema``, the JSON Schema as
  UTF-8 text, name = the message type),
- one **channel** per key (topic = the Zenoh key, message encoding ``json``),
- one **message** record per message: the JSON payload exactly as it was on the bus,
  ``log_time`` = delivery time, ``publish_time`` = send time (both ns, sim time in sim mode) and
  ``sequence`` = 1, 2, 3, … per channel, in the order the recorder wrote them,
- a **metadata** record :data:`RUN_METADATA` (``"adnmesh.run"``) written first, with the run's
  description (see :data:`RUN_METADATA_KEYS`), and any further records the runtime adds with
  :meth:`Recorder.add_metadata` (e.g. :data:`PUBLISHED_METADATA`, the agents' own counts).

Schema and channel records are written lazily, on the first message of their type or key.
Messages are grouped in zstd-compressed chunks (each followed by its message indexes, with a
chunk index, statistics and summary offsets in the summary section, as ``mcap.writer.Writer``
lays them out); the message records and message indexes, written once per message, are packed
here with :mod:`struct` (:class:`_McapStream`), every other record by :mod:`mcap.records`, and
closed chunks are compressed and written by a background thread, in order. Every
``flush_interval_s`` of wall time the chunk in progress is closed and written, and the file is
flushed and fsync'ed, so that a recorder killed at any moment (even by SIGKILL) leaves a file
whose complete chunks
:func:`adnmesh.recording.read_recording` recovers: all messages written more than about one
flush interval before the kill.

**A write that fails** (a full disk, an I/O error) ends the recording: nothing more is
written, :attr:`Recorder.failure` holds the error, :meth:`Recorder.write` raises
``RuntimeError`` from it, and :meth:`Recorder.close` cuts the file back to what the last
successful flush put on disk (whole chunks and their indexes: a truncated recording that
:func:`~adnmesh.recording.read_recording` reads and ``adnmesh inspect`` recovers, with no
unfinished record at its end; on a full disk this also gives the space of the unfinished chunk
back) before it raises. :attr:`Recorder.on_disk` says how much that is.

**Test hook**: with the environment variable :data:`DISK_FULL_ENV`
(``ADNMESH_TEST_DISK_FULL_AFTER_BYTES``) set to N, the recorder's file takes N bytes and then
fails every write with ``ENOSPC`` as a full disk does (short writes, then the error): tests of
a disk that fills during ``adnmesh up`` use it, since a small real filesystem needs a mount.
Nothing else reads it.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import BinaryIO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import LIBRARY_IDENTIFIER, MCAP0_MAGIC

from adnmesh import __version__
from adnmesh.recording.foxglove_log import FOXGLOVE_LOG, FOXGLOVE_LOG_SCHEMA

__all__ = [
    "DISK_FULL_ENV",
    "FORMAT_VERSION",
    "MESSAGE_ENCODING",
    "PUBLISHED_METADATA",
    "RECOVERY_METADATA",
    "UNCOUNTED_METADATA",
    "RUN_METADATA",
    "RUN_METADATA_KEYS",
    "Recorder",
    "SCHEMA_ENCODING",
]

FORMAT_VERSION = "1"
"""Version of the recording layout described in this module (metadata key ``recording_format``)."""

MESSAGE_ENCODING = "json"
"""MCAP message encoding of every channel."""

SCHEMA_ENCODING = "jsonschema"
"""MCAP schema encoding of every schema."""

RUN_METADATA = "adnmesh.run"
"""Name of the metadata record that describes the run (written when the recorder opens)."""

PUBLISHED_METADATA = "adnmesh.published"
"""Name of the optional metadata record ``{topic: count}`` with what the agents say they
published; ``adnmesh inspect`` compares it with the recording."""

UNCOUNTED_METADATA = "adnmesh.uncounted"
"""Name of the optional metadata record ``{topic: why}`` of the topics nobody counted (payloads
the recorder rejected, a person's commands, the keys of an agent whose process died): they are
not compared with :data:`PUBLISHED_METADATA`."""

RECOVERY_METADATA = "adnmesh.recovery"
"""Name of the metadata record that :func:`adnmesh.recording.recover` adds to a recovered file."""

RUN_METADATA_KEYS = {
    "run_id": "identifier of the run, also the default file name logs/<run_id>.mcap",
    "config": "the config file's text (YAML), verbatim",
    "config_path": "where the config was read from",
    "config_sha256": "sha256 of the config file, hex",
    "table_sha256": "sha256 of the scheduling table file used, hex",
    "adnmesh_version": "version of adnmesh that recorded (filled in if missing)",
    "seed": "seed of the random streams (ICT channel model)",
    "clock": "'sim' or 'realtime'",
    "t0_ns": "time of the run's start on the recorded time axis, ns (default 0)",
    "recording_format": "FORMAT_VERSION (filled in)",
    "flush_interval_s": "the recorder's flush interval, s (filled in)",
    "start_utc": "wall-clock time the recording started, ISO 8601 UTC (filled in); message "
                 "times stay on the run's own axis",
    "start_unix_ns": "the same instant, ns since the Unix epoch (filled in)",
    "events_topic": "the topic of the run's events as foxglove.Log messages, if recorded",
}
"""The keys of the :data:`RUN_METADATA` record and what they hold; all values are strings.
The recorder requires none of them but fills in the ones marked *filled in*."""

DISK_FULL_ENV = "ADNMESH_TEST_DISK_FULL_AFTER_BYTES"
"""Test hook (module docstring): the recorder's file fails with ``ENOSPC`` after this many
bytes."""

_CHUNK_SIZE = 4 * 1024 * 1024  # bytes; chunks are normally closed by the flush timer first

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, 2 times
_MESSAGE_FIELDS_BYTES = 2 + 4 + 8 + 8      # a message record's length without its data
_INDEX_HEAD = struct.Struct("<BQHI")       # opcode, record length, channel, entries' bytes


class _McapStream:
    """An MCAP file written as ``mcap.writer.Writer`` writes it (chunked, zstd, every index,
    statistics, summary offsets, CRCs of chunks and summary), for the recorder's lock to drive.

    Messages go into the chunk in progress through :meth:`add_messages`, a batch at a time, as
    packed bytes. :meth:`close_chunk` seals it: one background thread compresses and writes
    sealed chunks with their message indexes, in order, so that whoever records is not held up
    by zstd (tens of ms per chunk); :meth:`wait` waits for it, and every other record is written
    after it. The first error of a background write is :attr:`failure`, and raised by
    :meth:`wait`.
    """

    def __init__(self, stream: BinaryIO, library: str, chunk_size: int) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._records = RecordBuilder()
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._channel_counts: dict[int, int] = {}
        self._message_count = self._metadata_count = 0
        self._start_ns = self._end_ns = 0           # over the file
        self._chunk_writer = ThreadPoolExecutor(max_workers=1,
                                                thread_name_prefix="adnmesh-recorder-chunks")
        self._written: Future | None = None         # the last sealed chunk's write
        self.failure: BaseException | None = None
        self.written = (0, 0, 0)   # (file offset, messages, last log time ns) of whole records
        self._new_chunk()
        stream.write(MCAP0_MAGIC)
        Header(profile="", library=library).write(self._records)
        self._write_records()
        self._mark_written()

    # -- data section ----------------------------------------------------------------------

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Register a schema (its record goes into the chunk in progress); return its id."""
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._add_to_chunk(schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        """Register a channel (its record goes into the chunk in progress); return its id."""
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id, metadata={})
        self._channels.append(channel)
        self._add_to_chunk(channel)
        return channel.id

    def add_messages(self, channel_id: int, first_sequence: int,
                     messages: Iterable[tuple[bytes, int, int]]) -> int:
        """Append ``(data, log_time_ns, publish_time_ns)`` messages of one channel, numbered from
        ``first_sequence``, to the chunk in progress; return how many."""
        chunk, index = self._chunk, self._index.setdefault(channel_id, [])
        low, high, pack = self._chunk_start_ns, self._chunk_end_ns, _MESSAGE_HEAD.pack
        sequence = first_sequence
        for data, log_time, publish_time in messages:
            index.append(log_time)
            index.append(len(chunk))
            chunk += pack(Opcode.MESSAGE, _MESSAGE_FIELDS_BYTES + len(data), channel_id,
                          sequence, log_time, publish_time)
            chunk += data
            low = log_time if low is None or log_time < low else low
            high = log_time if log_time > high else high
            sequence += 1
        count = sequence - first_sequence
        self._chunk_start_ns, self._chunk_end_ns = low, high
        self._chunk_messages += count
        self._channel_counts[channel_id] = self._channel_counts.get(channel_id, 0) + count
        if len(chunk) > self._chunk_size:
            self.close_chunk()
        return count

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a metadata record after the sealed chunks (outside any chunk) and index it."""
        self.wait()
        offset = self._stream.tell()
        Metadata(name=name, metadata=dict(data)).write(self._records)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=self._records.count,
                                                    name=name))
        self._metadata_count += 1
        self._write_records()
        self._mark_written()

    def close_chunk(self) -> None:
        """Seal the chunk in progress (if it holds a message; schema and channel records alone
        wait for the next one): it is compressed and written in the background."""
        if not self._chunk_messages:
            return
        sealed = (self._chunk, self._index, self._chunk_start_ns, self._chunk_end_ns,
                  self._chunk_messages)
        if not self._message_count:
            self._start_ns = self._chunk_start_ns
        self._start_ns = min(self._start_ns, self._chunk_start_ns)
        self._end_ns = max(self._end_ns, self._chunk_end_ns)
        self._message_count += self._chunk_messages
        self._new_chunk()
        self._written = self._chunk_writer.submit(self._write_chunk, *sealed)

    def wait(self) -> None:
        """Wait until every sealed chunk is written; raise the first error in writing one."""
        written = self._written
        if written is not None:
            written.result()   # one worker: it ran after every chunk sealed before

    def _write_chunk(self, data: bytearray, index: dict[int, list[int]], start: int,
                     end: int, messages: int) -> None:
        """Compress and write one sealed chunk and its message indexes (background thread)."""
        if self.failure is not None:   # the file stops at the first failure
            raise self.failure
        try:
            compressed = zstandard.compress(data)
            chunk_offset = self._stream.tell()
            records = RecordBuilder()
            Chunk(compression="zstd", data=compressed, message_start_time=start,
                  message_end_time=end, uncompressed_crc=zlib.crc32(data),
                  uncompressed_size=len(data)).write(records)
            chunk_length = records.count
            self._stream.write(records.end())
            offsets, indexes = _message_indexes(index, chunk_offset + chunk_length)
            self._stream.write(indexes)
        except BaseException as exc:
            self.failure = exc
            raise
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_offset,
            chunk_length=chunk_length, message_index_offsets=offsets,
            message_index_length=len(indexes), compression="zstd",
            compressed_size=len(compressed), uncompressed_size=len(data)))
        _, count, last = self.written
        self._mark_written(count + messages, max(last, end))

    def _mark_written(self, messages: int | None = None, last_ns: int | None = None) -> None:
        """Note that the file's records are whole up to its current end (in the buffer)."""
        _, count, last = self.written
        self.written = (self._stream.tell(), count if messages is None else messages,
                        last if last_ns is None else last_ns)

    # -- summary section -------------------------------------------------------------------

    def finish(self) -> None:
        """Close the chunk in progress, write the data end, the summary and the footer."""
        self.close_chunk()
        self.wait()
        DataEnd(data_section_crc=0).write(self._records)
        self._write_records()
        summary_start = self._stream.tell()
        summary = RecordBuilder()
        offsets = []
        statistics = Statistics(
            message_count=self._message_count, schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0,
            metadata_count=self._metadata_count, chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_ns, message_end_time=self._end_ns,
            channel_message_counts=dict(self._channel_counts))
        for opcode, records in ((Opcode.SCHEMA, self._schemas),
                                (Opcode.CHANNEL, self._channels),
                                (Opcode.STATISTICS, [statistics]),
                                (Opcode.CHUNK_INDEX, self._chunk_indexes),
                                (Opcode.ATTACHMENT_INDEX, []),
                                (Opcode.METADATA_INDEX, self._metadata_indexes)):
            group_start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode,
                                         group_start=summary_start + group_start,
                                         group_length=summary.count - group_start))
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        footer_head = struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start,
                                  summary_offset_start)
        self._stream.write(data)
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
               summary_crc=zlib.crc32(footer_head, zlib.crc32(data))).write(self._records)
        self._write_records()
        self._stream.write(MCAP0_MAGIC)

    # -- internals -------------------------------------------------------------------------

    def _new_chunk(self) -> None:
        self._chunk = bytearray()
        self._index: dict[int, list[int]] = {}   # channel -> [log_time, offset, ...]
        self._chunk_messages = 0
        self._chunk_start_ns: int | None = None
        self._chunk_end_ns = 0

    def _add_to_chunk(self, record) -> None:
        builder = RecordBuilder()
        record.write(builder)
        self._chunk += builder.end()

    def close(self) -> None:
        """Stop the background thread (after the chunks it has)."""
        self._chunk_writer.shutdown(wait=True)

    def _write_records(self) -> None:
        self._stream.write(self._records.end())


class _FullAfter(io.RawIOBase):
    """A file that takes ``limit`` bytes and then fails as a full disk does: a short write up
    to the limit, then ``OSError(ENOSPC)`` (the test hook :data:`DISK_FULL_ENV`)."""

    def __init__(self, raw: io.FileIO, limit: int) -> None:
        super().__init__()
        self._raw, self._left = raw, limit

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def write(self, data) -> int:
        data = memoryview(data).cast("B")
        if not data.nbytes:
            return 0
        if self._left <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = self._raw.write(data[:self._left])
        self._left -= n
        return n

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._raw.seek(offset, whence)

    def tell(self) -> int:
        return self._raw.tell()

    def fileno(self) -> int:
        return self._raw.fileno()

    def close(self) -> None:
        if not self.closed:
            self._raw.close()
        super().close()


def _open_for_writing(path: Path) -> BinaryIO:
    """``open(path, "wb")``, or with :data:`DISK_FULL_ENV` set, a file that fills up."""
    limit = os.environ.get(DISK_FULL_ENV)
    if not limit:
        return open(path, "wb")  # noqa: SIM115 -- closed by the recorder
    return io.BufferedWriter(_FullAfter(io.FileIO(path, "wb"), int(limit)))


def _message_indexes(index: dict[int, list[int]], start: int) -> tuple[dict[int, int], bytes]:
    """The message index records of a chunk (``index``: channel -> [log_time, offset, ...]),
    written at file offset ``start``: ``({channel: offset}, bytes)``."""
    offsets, parts, at = {}, [], start
    for channel_id, entries in index.items():
        record = _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + 8 * len(entries), channel_id,
                                  8 * len(entries)) + struct.pack(f"<{len(entries)}Q", *entries)
        offsets[channel_id] = at
        at += len(record)
        parts.append(record)
    return offsets, b"".join(parts)


class Recorder:
    """Write bus messages to an MCAP file; thread-safe.

    Parameters
    ----------
    path : str or Path
        The file to create (parent directories are made; an existing file is replaced).
    metadata : dict of str to str
        The run's description, written as the :data:`RUN_METADATA` record (keys: see
        :data:`RUN_METADATA_KEYS`).
    schemas : dict of str to dict
        Message type name -> JSON Schema (draft 2020-12) of its payload. Only types that are
        written get a schema record.
    flush_interval_s : float
        Wall-clock seconds between flushes to disk (> 0). Bounds what a killed run loses.
    events_topic : str, optional
        Also write the run's events as ``foxglove.Log`` messages on this topic
        (:mod:`~adnmesh.recording.foxglove_log`), for Foxglove's log panel; with ``events``.
        They are not in :meth:`counts`.
    events : callable, optional
        ``(topic, schema_name, payload, t_ns) -> list of bytes``: the ``foxglove.Log`` records
        (JSON, e.g. by :func:`~adnmesh.recording.foxglove_log.log_record`) of the events in one
        message sent at ``t_ns``; called for every message written, in order, with the lock
        held. The recorder knows the format, not what an event is: ``adnmesh up`` passes
        :meth:`adnmesh.results.eventlog.EventLog.observe` (gain switches, availability
        changes, faults, the agents' events, rejected payloads).
    events_quiet : callable, optional
        ``(topic, schema_name) -> bool``: True for a topic whose messages of that type never
        hold an event; they are not given to ``events`` (asked once per topic and type: most
        of a large run's messages are states, reports and grants, and ``adnmesh up`` passes
        :meth:`adnmesh.results.eventlog.EventLog.quiet`).

    Examples
    --------
    >>> rec = Recorder("logs/run.mcap", metadata={"clock": "sim"}, schemas=SCHEMAS)
    >>> rec.write("adn/g/measurement/p_ip", "p_ip", b'{"p_ip_w": 1.0e6}',
    ...           log_time_ns=200_000_000, publish_time_ns=100_000_000)
    >>> rec.close()
    """

    def __init__(
        self,
        path: str | Path,
        *,
        metadata: Mapping[str, str],
        schemas: Mapping[str, Mapping],
        flush_interval_s: float = 1.0,
        events_topic: str | None = None,
        events: Callable[[str, str, bytes, int], list[bytes]] | None = None,
        events_quiet: Callable[[str, str], bool] | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be > 0, got {flush_interval_s!r}")
        if (events_topic is None) != (events is None):
            raise ValueError("events_topic and events go together: give both or neither")
        bad = {k: v for k, v in metadata.items() if not (isinstance(k, str) and isinstance(v, str))}
        if bad:
            raise TypeError(f"metadata keys and values must be str, got {bad!r}")
        self.path = Path(path)
        self._schemas = {name: json.dumps(schema, sort_keys=True).encode() for name, schema in
                         schemas.items()}
        self._flush_interval_s = float(flush_interval_s)
        run = dict(metadata)
        run.setdefault("adnmesh_version", __version__)
        run.setdefault("recording_format", FORMAT_VERSION)
        run.setdefault("flush_interval_s", f"{self._flush_interval_s:g}")
        start = time.time_ns()
        run.setdefault("start_utc", datetime.fromtimestamp(start / 1e9, timezone.utc)
                       .isoformat(timespec="microseconds"))
        run.setdefault("start_unix_ns", str(start))
        self._events_topic = events_topic
        self._events = events
        self._events_quiet = events_quiet
        self._quiet: dict[tuple[str, str], bool] = {}   # (topic, type) -> events_quiet's answer
        if events_topic is not None:
            self._schemas[FOXGLOVE_LOG] = json.dumps(FOXGLOVE_LOG_SCHEMA,
                                                     sort_keys=True).encode()
            run["events_topic"] = events_topic

        self._lock = threading.Lock()
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._counts: dict[str, int] = {}
        self._event_count = 0
        self._dirty = False
        self._closed = False
        self._failure: BaseException | None = None
        self._on_disk = (0, 0, 0)      # the writer's ``written`` at the last successful fsync

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _open_for_writing(self.path)
        try:
            self._writer = _McapStream(self._file, f"adnmesh {__version__}; {LIBRARY_IDENTIFIER}",
                                       _CHUNK_SIZE)
            self._writer.add_metadata(RUN_METADATA, run)
            self._sync()
        except BaseException as exc:
            with contextlib.suppress(OSError):
                self._file.close()
            if isinstance(exc, OSError) and exc.filename is None:   # the file, named
                raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
            raise
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="adnmesh-recorder-flush",
                                         daemon=True)
        self._flusher.start()

    # -- writing ---------------------------------------------------------------------------

    def write(self, topic: str, schema_name: str, payload: bytes, *, log_time_ns: int,
              publish_time_ns: int) -> None:
        """Record one message.

        Parameters
        ----------
        topic : str
            The key it was published on, e.g. ``adn/<grid>/der/<id>/state``.
        schema_name : str
            Its message type, a key of ``schemas``. All messages of one topic must share it.
        payload : bytes
            The JSON payload as it was on the bus (recorded unchanged).
        log_time_ns, publish_time_ns : int
            Delivery and send time, ns (>= 0; sim time in sim mode).

        Raises
        ------
        ValueError
            Unknown ``schema_name``, a second type on one topic, or a negative time.
        RuntimeError
            The recorder is closed, or an earlier flush failed (the cause is chained).
        """
        self.write_many(topic, schema_name, [(payload, log_time_ns, publish_time_ns)])

    def write_many(self, topic: str, schema_name: str,
                   messages: list[tuple[bytes, int, int]]) -> None:
        """Record several messages of one topic, in order: ``(payload, log_time_ns,
        publish_time_ns)`` each (see :meth:`write`). All or none are recorded.

        Raises
        ------
        ValueError, RuntimeError
            As :meth:`write`.
        """
        if schema_name not in self._schemas:
            raise ValueError(f"{topic}: unknown message type {schema_name!r}")
        for _, log_time_ns, publish_time_ns in messages:
            if log_time_ns < 0 or publish_time_ns < 0:
                raise ValueError(f"{topic}: times must be >= 0 ns, got log_time_ns="
                                 f"{log_time_ns}, publish_time_ns={publish_time_ns}")
        with self._lock:
            self._check_open()
            channel = self._channels.get(topic)
            if channel is None:
                channel = (self._register(topic, schema_name), schema_name)
                self._channels[topic] = channel
            elif channel[1] != schema_name:
                raise ValueError(f"{topic}: message type {schema_name!r}, but the topic is "
                                 f"recorded as {channel[1]!r}")
            first = self._counts.get(topic, 0) + 1
            written = self._writer.add_messages(channel[0], first, (
                (bytes(payload), int(log_time), int(publish_time))
                for payload, log_time, publish_time in messages))
            self._counts[topic] = first - 1 + written
            self._dirty = True
            if self._events is not None and not self._is_quiet(topic, schema_name):
                self._log_events(topic, schema_name, messages)

    def _is_quiet(self, topic: str, schema_name: str) -> bool:
        """``events_quiet``'s answer for the topic and type, asked once."""
        if self._events_quiet is None:
            return False
        found = self._quiet.get((topic, schema_name))
        if found is None:
            found = self._quiet[topic, schema_name] = bool(self._events_quiet(topic, schema_name))
        return found

    def _log_events(self, topic: str, schema_name: str, messages) -> None:
        """Write the events in ``messages`` on the events topic (``foxglove.Log``; not in
        :meth:`counts`: no agent publishes them)."""
        logs = [(record, publish_time, publish_time) for payload, _, publish_time in messages
                for record in self._events(topic, schema_name, bytes(payload),
                                           int(publish_time))]
        if not logs:
            return
        channel = self._channels.get(self._events_topic)
        if channel is None:
            channel = (self._register(self._events_topic, FOXGLOVE_LOG), FOXGLOVE_LOG)
            self._channels[self._events_topic] = channel
        self._event_count += self._writer.add_messages(channel[0], self._event_count + 1, logs)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add a metadata record ``name`` (e.g. :data:`PUBLISHED_METADATA`) and flush."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise TypeError(f"metadata {name!r}: keys and values must be str")
        with self._lock:
            self._check_open()
            try:
                self._writer.add_metadata(name, dict(data))
                self._sync()
            except OSError as exc:
                self._failure = self._failure or exc
                raise RuntimeError(f"{self.path}: recording failed") from exc

    @property
    def failure(self) -> BaseException | None:
        """The error that ended the recording (a write or flush that failed: a full disk, say),
        or None while it goes well. Nothing is written after it."""
        return self._failure or self._writer.failure

    @property
    def on_disk(self) -> tuple[int, int]:
        """``(messages, last log time ns)`` on disk as of the last successful flush: what a
        file cut at that moment holds (after a failure, what the file keeps)."""
        return self._on_disk[1], self._on_disk[2]

    def counts(self) -> dict[str, int]:
        """Return the number of messages written so far, per topic."""
        with self._lock:
            return dict(self._counts)

    def flush(self) -> None:
        """Write everything recorded so far to disk now (the timer does this periodically).
        Raises RuntimeError as :meth:`write`."""
        with self._lock:
            self._check_open()
            try:
                self._sync()
            except OSError as exc:
                self._failure = self._failure or exc
                raise RuntimeError(f"{self.path}: recording failed") from exc

    def close(self) -> None:
        """Stop the flush timer and finish the file (summary section, indexes, footer).

        Calling it again does nothing. Raises RuntimeError if a write or flush had failed (or
        finishing the file fails); the file is then cut back to what the last successful flush
        wrote (module docstring).
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        self._flusher.join()
        with self._lock:
            try:
                self._failure = self._failure or self._writer.failure
                if self._failure is None:
                    self._writer.finish()
                    self._file.flush()
                    os.fsync(self._file.fileno())
            except OSError as exc:
                self._failure = exc
            finally:
                self._writer.close()
                try:
                    self._file.close()       # after a failure its buffer fails again: said
                except OSError as exc:
                    self._failure = self._failure or exc
            if self._failure is not None:
                self._cut_to_disk()
                raise RuntimeError(f"{self.path}: recording failed") from self._failure

    def _cut_to_disk(self) -> None:
        """After a failure: the file back to its length at the last successful flush (whole
        records only), if it can be."""
        try:
            os.truncate(self.path, self._on_disk[0])
        except OSError:
            pass

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- internals (called with the lock held) ---------------------------------------------

    def _check_open(self) -> None:
        failure = self._failure or self._writer.failure
        if failure is not None:
            raise RuntimeError(f"{self.path}: recording failed") from failure
        if self._closed:
            raise RuntimeError(f"{self.path}: recorder is closed")

    def _register(self, topic: str, schema_name: str) -> int:
        schema_id = self._schema_ids.get(schema_name)
        if schema_id is None:
            schema_id = self._writer.add_schema(schema_name, SCHEMA_ENCODING,
                                                self._schemas[schema_name])
            self._schema_ids[schema_name] = schema_id
        return self._writer.add_channel(topic, MESSAGE_ENCODING, schema_id)

    def _flush_file(self) -> None:
        """Write the chunk in progress and flush the file's buffer (no fsync)."""
        self._writer.close_chunk()
        self._writer.wait()
        self._file.flush()

    def _sync(self) -> None:
        """Close the chunk in progress and push the file to disk."""
        self._flush_file()
        written = self._writer.written
        os.fsync(self._file.fileno())
        self._on_disk = written
        self._dirty = False

    def _flush_loop(self) -> None:
        # the chunk is sealed under the lock; its compression, the write and the fsync happen
        # outside it, so that writers are not held up by zstd or the disk; close() stops this
        # thread before it closes the file
        while not self._stop.wait(self._flush_interval_s):
            with self._lock:
                if self._closed or self._failure is not None or not self._dirty:
                    continue
                self._writer.close_chunk()
                self._dirty = False
            try:
                self._writer.wait()
                written = self._writer.written   # whole records up to here, before the flush
                self._file.flush()
                os.fsync(self._file.fileno())
            except BaseException as exc:  # noqa: BLE001 -- reported by write()/close()
                with self._lock:
                    self._failure = self._failure or exc
                continue
            with self._lock:
                self._on_disk = max(self._on_disk, written)
