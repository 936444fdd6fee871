"""The records of an MCAP file as both readers take them, and what can be wrong with a file.

:func:`~adnmesh.recording.read_recording` (every message as an object) and
:func:`~adnmesh.recording.stream.scan` (one streaming pass, as NumPy columns) read a recording
through the same pieces, so that they agree on where a truncated file ends and say the same
words about a file that is no readable recording:

- :class:`TopLevelRecords`: the whole records after the magic, front to back; a file that ends
  inside a record (or in zeros, as a crash can leave) is *truncated*, not corrupt; the
  closing magic after the footer makes it *complete*;
- :func:`parse_record`: a top-level record's body as the ``mcap`` library's record;
- :func:`chunk_content`: a chunk's decompressed content, its checksum checked;
- :func:`chunk_records`, :func:`parse_inner`: the records inside a chunk.

Every problem is a :class:`RecordingError` with one line naming the file (``adnmesh`` reports
it with exit code 2): ``no such file``, ``is a directory, not a recording``, ``cannot read``,
``empty file, not an MCAP recording``, ``not an MCAP file (it does not start with the MCAP
magic)``, and ``corrupt MCAP file: ...`` for the rest (no header record after the magic, an
invalid record opcode, bytes after the footer, a malformed record, a chunk whose content does
not decompress, has an unknown compression, does not match its checksum or holds malformed
records, a message on an unknown channel, a schema that is no JSON).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema

from adnmesh.errors import UsageError
from adnmesh.files import unreadable

__all__ = [
    "KNOWN_OPCODES",
    "MCAP_MAGIC",
    "MESSAGE_HEAD",
    "RECORD_HEAD",
    "RecordingError",
    "TopLevelRecords",
    "chunk_content",
    "chunk_problem",
    "chunk_records",
    "open_recording",
    "parse_inner",
    "parse_record",
    "schema_not_json",
    "unknown_channel",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes at the start and the end of every MCAP file."""

RECORD_HEAD = struct.Struct("<BQ")
"""A record's head: opcode, length of the record's body."""

MESSAGE_HEAD = 31
"""Bytes of a message record before its payload: opcode 1, length 8, channel 2, sequence 4,
log time 8, publish time 8."""

KNOWN_OPCODES = frozenset(int(op) for op in Opcode)

_PARSED = {Opcode.HEADER: Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: Schema,
           Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata, Opcode.CHUNK: Chunk,
           Opcode.DATA_END: DataEnd}
# the records a reader takes (message indexes aside, which scan reads itself); the others
# (chunk and metadata indexes, statistics, summary offsets, attachments) are passed over


class RecordingError(UsageError):
    """A file is not a readable recording; the message is one line naming the file."""


def _corrupt(path: Path, what: str) -> RecordingError:
    return RecordingError(f"{path}: corrupt MCAP file{what}")


def _problem(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _name(opcode: int) -> str:
    return Opcode(opcode).name.lower() if opcode in KNOWN_OPCODES else f"0x{opcode:02x}"


def open_recording(path: Path) -> BinaryIO:
    """``path`` opened for reading, or the error that says why it cannot be."""
    try:
        return open(path, "rb")  # noqa: SIM115 -- the caller closes it
    except OSError as exc:
        raise RecordingError(unreadable(path, exc, "recording")) from None


class TopLevelRecords:
    """The whole top-level records of the MCAP file ``stream`` (``size`` bytes), front to back.

    Iterating yields ``(opcode, offset, body)`` per record, after checking the magic. It stops
    at the footer, or where the file ends inside a record or in zeros after the last whole one
    (a truncated file: :attr:`complete` stays False, :attr:`dropped_bytes` says how much was
    after the last whole record).

    Raises
    ------
    RecordingError
        An empty file, no MCAP magic, a first record that is no header, an invalid record
        opcode (not followed by zeros only), bytes after the footer that are not the magic.
    """

    def __init__(self, path: Path, stream: BinaryIO, size: int) -> None:
        self.path, self.stream, self.size = path, stream, size
        self.complete = False
        self.end = len(MCAP_MAGIC)
        """Where the last whole record ends (the magic's end before the first one)."""

    @property
    def dropped_bytes(self) -> int:
        """Bytes after the last whole record of a truncated file (0 for a complete one)."""
        return 0 if self.complete else self.size - self.end

    def __iter__(self) -> Iterator[tuple[int, int, bytes]]:
        path, stream, size = self.path, self.stream, self.size
        head = stream.read(len(MCAP_MAGIC))
        if not head:
            raise RecordingError(f"{path}: empty file, not an MCAP recording")
        if head != MCAP_MAGIC:
            raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP "
                                 "magic)")
        first, at = True, len(MCAP_MAGIC)
        while size - at >= RECORD_HEAD.size:
            opcode, length = RECORD_HEAD.unpack(stream.read(RECORD_HEAD.size))
            if opcode not in KNOWN_OPCODES and opcode < 0x80:   # MCAP reserves them
                stream.seek(at)
                if stream.read().count(0) == size - at:
                    break              # zeros after a crash: the end of what was written
                raise _corrupt(path, f": invalid record opcode 0x{opcode:02x} at byte {at}")
            end = at + RECORD_HEAD.size + length
            if end > size:
                break                  # the file ends inside this record: truncated
            if first and opcode != Opcode.HEADER:
                raise _corrupt(path, ": no header record after the magic")
            first = False
            body = stream.read(length)
            yield opcode, at, body
            at = self.end = end
            if opcode == Opcode.FOOTER:
                rest = stream.read(len(MCAP_MAGIC) + 1)
                if rest == MCAP_MAGIC:
                    self.complete = True
                elif rest and not MCAP_MAGIC.startswith(rest):
                    raise _corrupt(path, f": {size - at} unexpected bytes after the footer")
                return
        if first:
            raise _corrupt(path, ": no header record after the magic")


def parse_record(path: Path, opcode: int, offset: int, body: bytes):
    """The record of ``opcode`` whose ``body`` starts the record at byte ``offset``: a header,
    footer, schema, channel, metadata, chunk, data end or message record of the ``mcap``
    library; None for the records neither reader needs."""
    kind = Message if opcode == Opcode.MESSAGE else _PARSED.get(opcode)
    if kind is None:
        return None
    stream = ReadDataStream(BytesIO(body))
    try:
        return Message.read(stream, len(body)) if kind is Message else kind.read(stream)
    except Exception as exc:  # noqa: BLE001 -- any failure to parse a whole record
        raise _corrupt(path, f": {_name(opcode)} record at byte {offset}: "
                             f"{_problem(exc)}") from None


def chunk_problem(path: Path, offset: int, why: str) -> RecordingError:
    """The error of the chunk record at byte ``offset``."""
    return _corrupt(path, f": chunk record at byte {offset}: {why}")


def chunk_content(path: Path, chunk: Chunk, offset: int) -> bytes:
    """The decompressed content of the chunk record at byte ``offset``, its checksum checked."""
    try:
        if chunk.compression == "zstd":
            data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
        elif chunk.compression == "":
            data = chunk.data
        elif chunk.compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(chunk.data)
        else:
            raise ValueError(f"unknown compression {chunk.compression!r}")
    except (ValueError, zstandard.ZstdError, ImportError, RuntimeError) as exc:
        raise chunk_problem(path, offset, _problem(exc)) from None
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise chunk_problem(path, offset, "the checksum of its content does not match")
    return data


def chunk_records(path: Path, data: bytes, offset: int, at: int = 0,
                  stop: int | None = None) -> Iterator[tuple[int, int, int]]:
    """``(opcode, start, end)`` of the records in ``data[at:stop]``, the content of the chunk
    record at byte ``offset`` (a message record is at least its head long)."""
    stop = len(data) if stop is None else stop
    while at < stop:
        if stop - at < RECORD_HEAD.size:
            raise chunk_problem(path, offset, f"{stop - at} bytes that are no record")
        opcode, length = RECORD_HEAD.unpack_from(data, at)
        end = at + RECORD_HEAD.size + length
        if end > stop:
            raise chunk_problem(path, offset, "a record runs past the chunk")
        if opcode == Opcode.MESSAGE and end - at < MESSAGE_HEAD:
            raise chunk_problem(path, offset, "a message record too short for its head")
        yield opcode, at, end
        at = end


def parse_inner(path: Path, offset: int, opcode: int, data: bytes, start: int, end: int):
    """The schema or channel record at ``data[start:end]`` inside the chunk at ``offset``."""
    stream = ReadDataStream(BytesIO(data[start + RECORD_HEAD.size:end]))
    try:
        return (Schema if opcode == Opcode.SCHEMA else Channel).read(stream)
    except Exception as exc:  # noqa: BLE001 -- any failure to parse a whole record
        raise chunk_problem(path, offset, f"a malformed record inside: {_problem(exc)}") \
            from None


def unknown_channel(path: Path, channel_id: int, offset: int) -> RecordingError:
    """A message on a channel no record declared, in the record at byte ``offset``."""
    return _corrupt(path, f": message on unknown channel {channel_id} at byte {offset}")


def schema_not_json(path: Path, name: str) -> RecordingError:
    """A JSON Schema record whose text is no JSON."""
    return RecordingError(f"{path}: schema {name!r} is not valid JSON")
