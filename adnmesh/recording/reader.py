"""Reading recordings back, including the unfinished file of a killed run.

:func:`read_recording` reads an MCAP file front to back (never through its summary section),
one record at a time: the records of a complete file, or, for a truncated one, every record
that was completely written. Since the recorder writes its messages in chunks that are closed
and flushed every flush interval, a recorder killed at any moment leaves a file from which all
messages of its closed chunks come back. :func:`recover` writes them into a new, complete file.

Anything that is neither a complete nor a truncated MCAP file (not MCAP at all, a chunk whose
checksum does not match, a malformed record) raises :class:`RecordingError`, whose message is
one line naming the file; the command line reports it with exit code 2. The file's framing and
the words for what is wrong with it are :mod:`~adnmesh.recording.mcap_records`', the same for
:func:`~adnmesh.recording.stream.scan`.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from adnmesh.files import write_atomic
from adnmesh.recording.mcap_records import (MCAP_MAGIC, MESSAGE_HEAD, RECORD_HEAD,
                                            RecordingError, TopLevelRecords, chunk_content,
                                            chunk_records, open_recording, parse_inner,
                                            parse_record, schema_not_json, unknown_channel)
from adnmesh.recording.writer import RECOVERY_METADATA, RUN_METADATA, SCHEMA_ENCODING

__all__ = [
    "ChannelInfo",
    "MCAP_MAGIC",
    "RecordedMessage",
    "Recording",
    "RecordingError",
    "read_recording",
    "recover",
]

_MESSAGE_FIELDS = struct.Struct("<HIQQ")  # a message record's channel, sequence and two times


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded message.

    Attributes
    ----------
    topic : str
        The bus key it was published on.
    schema_name : str
        Its message type ("" for a channel without schema).
    sequence : int
        Its number on its channel: 1, 2, 3, … in recording order.
    log_time_ns, publish_time_ns : int
        Delivery and send time, ns (sim time in sim mode).
    data : bytes
        The payload as recorded (JSON text for adnmesh recordings).
    """

    topic: str
    schema_name: str
    sequence: int
    log_time_ns: int
    publish_time_ns: int
    data: bytes

    def payload(self) -> Any:
        """Return the payload decoded from JSON (raises ValueError if it is not JSON)."""
        return json.loads(self.data)


@dataclass(frozen=True)
class ChannelInfo:
    """A recorded channel: its topic, message encoding, message type and channel metadata."""

    topic: str
    message_encoding: str
    schema_name: str
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Recording:
    """The content of a recording file.

    Attributes
    ----------
    path : Path
        The file read.
    messages : tuple of RecordedMessage
        Every message, in file order (the order the recorder wrote them).
    channels : dict of str to ChannelInfo
        Per topic, in order of first appearance.
    schemas : dict of str to dict
        Message type -> its JSON Schema (schemas of other encodings are left out).
    metadata_records : tuple of (str, dict)
        Every metadata record, in file order.
    library : str
        The writer named in the file's header.
    complete : bool
        False if the file was truncated (a killed run) and read as far as it was written.
    dropped_bytes : int
        Bytes at the end of a truncated file that did not form a complete record.
    """

    path: Path
    messages: tuple[RecordedMessage, ...]
    channels: dict[str, ChannelInfo]
    schemas: dict[str, dict]
    metadata_records: tuple[tuple[str, dict[str, str]], ...]
    library: str
    complete: bool
    dropped_bytes: int = 0

    @property
    def recovered_messages(self) -> int:
        """The number of messages read from a truncated file (0 for a complete one)."""
        return 0 if self.complete else len(self.messages)

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (a later record of the same name adds to and overrides)."""
        merged: dict[str, dict[str, str]] = {}
        for name, data in self.metadata_records:
            merged.setdefault(name, {}).update(data)
        return merged

    @property
    def run(self) -> dict[str, str]:
        """The run's description: the ``adnmesh.run`` metadata record (empty if absent)."""
        return self.metadata.get(RUN_METADATA, {})

    def counts(self) -> dict[str, int]:
        """Return the number of messages per topic, topics in order of first appearance."""
        counts = dict.fromkeys(self.channels, 0)
        for message in self.messages:
            counts[message.topic] += 1
        return counts

    def time_range_ns(self) -> tuple[int, int] | None:
        """Return (earliest, latest) over send and delivery times, ns; None without messages."""
        if not self.messages:
            return None
        start = min(min(m.publish_time_ns, m.log_time_ns) for m in self.messages)
        end = max(max(m.publish_time_ns, m.log_time_ns) for m in self.messages)
        return start, end


def read_recording(path: str | Path) -> Recording:
    """Read a recording, recovering a truncated one.

    Parameters
    ----------
    path : str or Path
        An MCAP file, complete or cut short (a killed run).

    Returns
    -------
    Recording
        With ``complete`` False and ``recovered_messages`` > 0 for a truncated file.

    Raises
    ------
    RecordingError
        If the file is missing, not MCAP, or corrupt (e.g. a chunk's checksum does not match),
        in the words :func:`~adnmesh.recording.stream.scan` uses too
        (:mod:`~adnmesh.recording.mcap_records`).
    """
    path = Path(path)
    schemas_by_id: dict[int, Schema] = {}
    channels_by_id: dict[int, Channel] = {}
    messages: list[RecordedMessage] = []
    metadata: list[tuple[str, dict[str, str]]] = []
    library = ""

    def message(channel_id: int, sequence: int, log_time: int, publish_time: int, data: bytes,
                offset: int) -> None:
        channel = channels_by_id.get(channel_id)
        if channel is None:
            raise unknown_channel(path, channel_id, offset)
        schema = schemas_by_id.get(channel.schema_id)
        messages.append(RecordedMessage(
            topic=channel.topic, schema_name=schema.name if schema else "", sequence=sequence,
            log_time_ns=log_time, publish_time_ns=publish_time, data=data))

    def register(record: Schema | Channel) -> None:
        if isinstance(record, Schema):
            schemas_by_id[record.id] = record
        else:
            channels_by_id[record.id] = record

    with open_recording(path) as stream:
        frames = TopLevelRecords(path, stream, os.fstat(stream.fileno()).st_size)
        for opcode, offset, body in frames:
            record = parse_record(path, opcode, offset, body)
            if isinstance(record, Header):
                library = record.library
            elif isinstance(record, Metadata):
                metadata.append((record.name, dict(record.metadata)))
            elif isinstance(record, (Schema, Channel)):
                register(record)
            elif isinstance(record, Message):
                message(record.channel_id, record.sequence, record.log_time,
                        record.publish_time, record.data, offset)
            elif isinstance(record, Chunk):
                data = chunk_content(path, record, offset)
                for inner, start, end in chunk_records(path, data, offset):
                    if inner == Opcode.MESSAGE:
                        message(*_MESSAGE_FIELDS.unpack_from(data, start + RECORD_HEAD.size),
                                data[start + MESSAGE_HEAD:end], offset)
                    elif inner in (Opcode.SCHEMA, Opcode.CHANNEL):
                        register(parse_inner(path, offset, inner, data, start, end))

    channels: dict[str, ChannelInfo] = {}
    for channel in channels_by_id.values():
        schema = schemas_by_id.get(channel.schema_id)
        channels.setdefault(channel.topic, ChannelInfo(
            topic=channel.topic, message_encoding=channel.message_encoding,
            schema_name=schema.name if schema else "", metadata=dict(channel.metadata)))
    schemas: dict[str, dict] = {}
    for schema in schemas_by_id.values():
        if schema.encoding == SCHEMA_ENCODING:
            try:
                schemas[schema.name] = json.loads(schema.data)
            except ValueError:
                raise schema_not_json(path, schema.name) from None
    return Recording(path=path, messages=tuple(messages), channels=channels, schemas=schemas,
                     metadata_records=tuple(metadata), library=library,
                     complete=frames.complete, dropped_bytes=frames.dropped_bytes)


def write_recording(recording: Recording, out_path: str | Path,
                    extra_metadata: tuple[tuple[str, dict[str, str]], ...] = ()) -> None:
    """Write ``recording`` as a complete MCAP file (atomically:
    :func:`adnmesh.files.write_atomic`)."""

    def write(stream) -> None:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library=recording.library)
        for name, data in recording.metadata_records + tuple(extra_metadata):
            writer.add_metadata(name, data)
        schema_ids = {name: writer.register_schema(name, SCHEMA_ENCODING,
                                                   json.dumps(schema, sort_keys=True).encode())
                      for name, schema in recording.schemas.items()}
        channel_ids = {
            topic: writer.register_channel(topic, info.message_encoding,
                                           schema_ids.get(info.schema_name, 0), info.metadata)
            for topic, info in recording.channels.items()}
        for m in recording.messages:
            writer.add_message(channel_ids[m.topic], log_time=m.log_time_ns, data=m.data,
                               publish_time=m.publish_time_ns, sequence=m.sequence)
        writer.finish()

    write_atomic(out_path, write, mode=0o600)


def recover(path: str | Path, out_path: str | Path) -> int:
    """Write what ``path`` holds into the complete MCAP file ``out_path``; return the message count.

    For a truncated file these are the recovered messages; a complete file is copied record by
    record. The new file carries every metadata record of the old one plus an
    ``adnmesh.recovery`` record (source file, messages recovered, bytes dropped).

    Raises
    ------
    RecordingError
        As :func:`read_recording`.
    """
    recording = read_recording(path)
    recovery = {"source": str(path), "complete": str(recording.complete).lower(),
                "messages": str(len(recording.messages)),
                "dropped_bytes": str(recording.dropped_bytes)}
    write_recording(recording, out_path, ((RECOVERY_METADATA, recovery),))
    return len(recording.messages)
