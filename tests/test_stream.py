"""Tests of the streaming, columnar reading of recordings (adnmesh.recording.stream and
series.read_run), against the whole-file reader and an independent MCAP reader."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from adnmesh.recording import Recorder, RecordingError, read_recording
from adnmesh.results.series import extract, read_run
from adnmesh.recording.stream import MessageBatch, decode_fields, scan
from synthetic_runs import FAKE_SCHEMAS, fake_run, write_fake_run


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fake") / "fake.mcap"
    write_fake_run(path)
    return path


@pytest.fixture(scope="module")
def chunked(tmp_path_factory) -> Path:
    """The fake run with a flush every 300 messages: many chunks, each with its indexes."""
    path = tmp_path_factory.mktemp("chunked") / "chunked.mcap"
    with Recorder(path, metadata={"run_id": "chunked"}, schemas=FAKE_SCHEMAS,
                  flush_interval_s=3600) as recorder:
        for i, m in enumerate(fake_run()):
            recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                           publish_time_ns=m.t_send_ns)
            if i % 300 == 299:
                recorder.flush()
    return path


def assert_same_run(a, b) -> None:
    assert list(a.series) == list(b.series)
    for path, s in a.series.items():
        t = b.series[path]
        assert (s.name, s.role, s.unit, s.step, s.topic) == (t.name, t.role, t.unit, t.step,
                                                             t.topic)
        assert np.array_equal(s.t_ns, t.t_ns) and np.array_equal(s.log_time_ns, t.log_time_ns)
        assert np.array_equal(s.values, t.values)
    assert a.events == b.events
    assert (a.der_ids, a.t0_ns) == (b.der_ids, b.t0_ns)


def test_counts_and_times_agree_with_an_independent_reader(fake: Path) -> None:
    from mcap.reader import make_reader

    counts, first, last = Counter(), {}, {}
    with open(fake, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            first.setdefault(channel.topic, message.publish_time)
            first[channel.topic] = min(first[channel.topic], message.publish_time)
            last[channel.topic] = max(last.get(channel.topic, 0), message.publish_time)
    scanned = scan(fake, lambda info: None)
    assert scanned.complete and scanned.dropped_bytes == 0
    assert scanned.counts() == dict(counts) and scanned.message_count == 3917
    for topic, stats in scanned.channel_stats.items():
        assert (stats.first_publish_ns, stats.last_publish_ns) == (first[topic], last[topic])
    whole = read_recording(fake)
    assert scanned.time_range_ns() == whole.time_range_ns()
    assert scanned.schemas == whole.schemas and scanned.metadata == whole.metadata
    assert scanned.channels == whole.channels and scanned.library == whole.library


def test_sinks_get_every_payload_of_their_channels_in_file_order(chunked: Path) -> None:
    got: dict[str, list] = {}

    def sink_for(info):
        return lambda batch: got.setdefault(info.topic, []).extend(
            zip(batch.ordinal.tolist(), batch.publish_time_ns.tolist(),
                batch.log_time_ns.tolist(), batch.payloads))

    scan(chunked, sink_for)
    whole = read_recording(chunked).messages
    for topic, rows in got.items():
        mine = [(i, m.publish_time_ns, m.log_time_ns, m.data) for i, m in enumerate(whole)
                if m.topic == topic]
        assert rows == mine


def test_read_run_equals_extract_of_the_whole_file(fake: Path, chunked: Path) -> None:
    for path in (fake, chunked):
        found, _ = read_run(path)
        assert_same_run(found.run, extract(read_recording(path)))


def test_truncated_files_read_as_far_as_the_whole_reader_reads(chunked: Path,
                                                               tmp_path: Path) -> None:
    data = chunked.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    seen = set()
    for cut in range(100, len(data), len(data) // 41):
        cut_path.write_bytes(data[:cut])
        whole = read_recording(cut_path)
        found, _ = read_run(cut_path)
        assert found.recording.complete is False
        assert found.recording.message_count == len(whole.messages)
        assert found.recording.dropped_bytes == whole.dropped_bytes
        assert_same_run(found.run, extract(whole))
        seen.add(len(whole.messages))
    assert len(seen) > 5     # the cuts fell into many chunks


def test_a_tail_of_zeros_is_a_truncation(fake: Path, tmp_path: Path) -> None:
    data = fake.read_bytes()
    path = tmp_path / "zeros.mcap"
    path.write_bytes(data[: len(data) // 2] + bytes(4096))
    scanned = scan(path, lambda info: None)
    assert not scanned.complete
    assert scanned.message_count == len(read_recording(path).messages)


@pytest.mark.parametrize("content, message", [
    (b"", "empty file, not an MCAP recording"),
    (b"hello, world\n", "not an MCAP file"),
    (b"\x89MCAP0\r\n" + bytes(range(7, 200)), "no header record after the magic"),
])
def test_what_is_no_recording_is_a_one_line_error(tmp_path: Path, content: bytes,
                                                  message: str) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message) as info:
        scan(path, lambda info: None)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_a_damaged_chunk_is_an_error_naming_it(chunked: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    with open(chunked, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[3]
    data = bytearray(chunked.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 20] ^= 0xFF
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=f"corrupt MCAP file: chunk record at byte "
                                             f"{chunk.chunk_start_offset}"):
        scan(path, lambda info: None)


def test_a_file_without_message_indexes_is_walked(tmp_path: Path) -> None:
    from mcap.writer import IndexType, Writer

    path = tmp_path / "plain.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, index_types=IndexType.NONE, chunk_size=400)
        writer.start()
        schema = writer.register_schema("p_ip", "jsonschema", b"{}")
        channel = writer.register_channel("adn/x/measurement/p_ip", "json", schema)
        for i in range(50):
            payload = {"v": 1, "type": "p_ip", "src": "m", "seq": i, "t_send_ns": i * 10**8,
                       "t_deliver_ns": i * 10**8, "p_ip_w": float(i)}
            writer.add_message(channel, log_time=i * 10**8, publish_time=i * 10**8,
                               data=json.dumps(payload).encode())
        writer.finish()
    found, _ = read_run(path)
    assert found.recording.message_count == 50
    assert found.run.one("p_ip").values.tolist() == [float(i) for i in range(50)]


def test_field_decoding_reads_bodies_and_skips_what_is_no_object() -> None:
    payloads = [b'{"a": 1, "b": "x"}', b'{"body": {"a": 2}}', b'[1, 2]', b'{}', b'NaN',
                b'{"a": NaN}']
    batch = MessageBatch(np.arange(6), np.arange(6), np.arange(6), payloads)
    decoded = decode_fields(batch, ("a", "b"))
    assert decoded.valid.tolist() == [True, True, False, False, False, True]
    assert decoded.columns["a"][:2] == [1, 2] and decoded.columns["b"][0] == "x"
    assert np.isnan(decoded.columns["a"][5])


def test_messages_out_of_send_order_across_chunks_are_read_whole(tmp_path: Path) -> None:
    path = tmp_path / "unordered.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS, flush_interval_s=3600) as recorder:
        for i, t in enumerate([5, 6, 7, 1, 2, 3]):
            body = {"v": 1, "type": "p_ip", "src": "measurement", "seq": i,
                    "t_send_ns": t * 10**8, "t_deliver_ns": t * 10**8, "p_ip_w": float(t)}
            recorder.write("adn/fake/measurement/p_ip", "p_ip", json.dumps(body).encode(),
                           log_time_ns=t * 10**8, publish_time_ns=t * 10**8)
            if i == 2:
                recorder.flush()
    found, _ = read_run(path)
    assert found.run.one("p_ip").values.tolist() == [1.0, 2.0, 3.0, 5.0, 6.0, 7.0]
    assert_same_run(found.run, extract(read_recording(path)))


def _damaged(chunked: Path) -> dict[str, tuple[bytes, str | None]]:
    """Damaged copies of ``chunked``: name -> (content, the error both readers give; None:
    a truncated file both read as far as it goes)."""
    import struct

    from mcap.reader import make_reader

    with open(chunked, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[3]
    data, at = chunked.read_bytes(), chunk.chunk_start_offset
    head = at + 9 + 8 + 8 + 8          # a chunk: start, end and size, then crc, compression

    def patched(offset: int, new: bytes) -> bytes:
        return data[:offset] + new + data[offset + len(new):]

    inside = f"corrupt MCAP file: chunk record at byte {at}: "
    metadata = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]        # the record after the header
    assert data[metadata] == 0x0C
    cases = {
        "zero bytes": (b"", "empty file, not an MCAP recording"),
        "garbage": (b"hello, world\n" * 8, "not an MCAP file (it does not start with the "
                                          "MCAP magic)"),
        "wrong magic": (b"\x89MCAP1\r\n" + data[8:], "not an MCAP file (it does not start "
                                                      "with the MCAP magic)"),
        "magic alone": (data[:8], "corrupt MCAP file: no header record after the magic"),
        "first record no header": (data[:8] + b"\x03" + data[9:], "corrupt MCAP file: no "
                                                                  "header record after the "
                                                                  "magic"),
        "truncated mid-chunk": (data[:at + chunk.chunk_length // 2], None),
        "truncated in zeros": (data[:at] + bytes(5000), None),     # a crash left zeros
        "truncated in the closing magic": (data[:-3], None),
        "invalid opcode": (patched(at, b"\x42"), f"corrupt MCAP file: invalid record opcode "
                                                 f"0x42 at byte {at}"),
        "broken crc": (patched(head, struct.pack("<I", 12345)),
                       inside + "the checksum of its content does not match"),
        "unknown compression": (patched(head + 8, b"abcd"), inside + "unknown compression "
                                                                     "'abcd'"),
        "damaged compressed data": (patched(at + chunk.chunk_length - 20,
                                            bytes([data[at + chunk.chunk_length - 20] ^ 0xFF])),
                                    inside + "decompression error: Data corruption detected"),
        "chunk length too short": (patched(at + 1, struct.pack("<Q", 10)),
                                   inside + "unpack requires a buffer of 8 bytes"),
        "bytes after the footer": (data + b"xyz", "corrupt MCAP file: 11 unexpected bytes "
                                                  "after the footer"),
        "malformed metadata record": (patched(metadata + 9, struct.pack("<I", 10**6)),
                                      f"corrupt MCAP file: metadata record at byte {metadata}: "),
    }
    assert data[head + 8:head + 12] == b"zstd"
    return cases


@pytest.mark.parametrize("case", ["zero bytes", "garbage", "wrong magic", "magic alone",
                                  "first record no header", "truncated mid-chunk",
                                  "truncated in zeros", "truncated in the closing magic",
                                  "invalid opcode", "broken crc", "unknown compression",
                                  "damaged compressed data", "chunk length too short",
                                  "bytes after the footer", "malformed metadata record"])
def test_both_readers_say_the_same_of_a_damaged_file(chunked: Path, tmp_path: Path,
                                                     case: str) -> None:
    """read_recording (and recover, through it) and scan give one error text for one
    problem (a malformed record: the parser's own words after the same head), and read a
    truncated file to the same end."""
    from adnmesh.recording import recover

    content, problem = _damaged(chunked)[case]
    path = tmp_path / "damaged.mcap"
    path.write_bytes(content)
    if problem is None:
        whole, scanned = read_recording(path), scan(path, lambda info: None)
        assert not whole.complete and not scanned.complete
        assert scanned.message_count == len(whole.messages) > 0
        assert scanned.dropped_bytes == whole.dropped_bytes > 0
        assert recover(path, tmp_path / "out.mcap") == len(whole.messages)
        return
    said = []
    for read in (read_recording, lambda p: scan(p, lambda info: None),
                 lambda p: recover(p, tmp_path / "out.mcap")):
        with pytest.raises(RecordingError) as info:
            read(path)
        said.append(str(info.value))
    assert said == [said[0]] * 3 and said[0].startswith(f"{path}: {problem}")
    assert problem.endswith(": ") or said[0] == f"{path}: {problem}"


def test_messages_outside_chunks_are_read_by_both_readers(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "unchunked.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, use_chunking=False)
        writer.start()
        schema = writer.register_schema("p_ip", "jsonschema", b"{}")
        channel = writer.register_channel("adn/x/measurement/p_ip", "json", schema)
        for i in range(5):
            writer.add_message(channel, log_time=i, publish_time=i,
                               data=json.dumps({"p_ip_w": float(i)}).encode())
        writer.finish()
    found, _ = read_run(path)
    assert found.recording.message_count == len(read_recording(path).messages) == 5
    assert found.run.one("p_ip").values.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
