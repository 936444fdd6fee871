"""Tests of adnmesh.recording: the recorder, reading back, recovery, schemas and counts."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from adnmesh import __version__
from adnmesh.recording import (
    PUBLISHED_METADATA,
    RECOVERY_METADATA,
    Recorder,
    RecordingError,
    RecordingLossError,
    check_counts,
    count_differences,
    read_recording,
    recover,
    validate_recording,
)
from synthetic_runs import FAKE_SCHEMAS, fake_run, write_fake_run

REPO_ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> tuple[Path, dict[str, int]]:
    """A recorded fake run (60 s of sim time) and what its publishers counted."""
    path = tmp_path_factory.mktemp("fake") / "fake.mcap"
    return path, write_fake_run(path)


@pytest.fixture(scope="module")
def chunked(tmp_path_factory) -> Path:
    """The fake run recorded with a flush every 200 messages: many small chunks."""
    path = tmp_path_factory.mktemp("chunked") / "chunked.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS) as recorder:
        for i, m in enumerate(fake_run()):
            recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                           publish_time_ns=m.t_send_ns)
            if i % 200 == 199:
                recorder.flush()
    return path


def _p_ip(seq: int, t_ns: int, value: float) -> bytes:
    return json.dumps({"v": 1, "type": "p_ip", "src": "measurement", "seq": seq,
                       "t_send_ns": t_ns, "t_deliver_ns": t_ns, "p_ip_w": value}).encode()


def test_recorded_counts_equal_published_counts(fake) -> None:
    path, published = fake
    recording = read_recording(path)
    assert recording.complete and recording.recovered_messages == 0
    assert recording.counts() == published
    assert sum(published.values()) == len(recording.messages) > 3000
    check_counts(published, recording.counts())  # does not raise
    assert {k: int(v) for k, v in recording.metadata[PUBLISHED_METADATA].items()} == published


def test_recorder_counts_what_it_wrote(tmp_path: Path) -> None:
    with Recorder(tmp_path / "r.mcap", metadata={}, schemas=FAKE_SCHEMAS) as recorder:
        for i in range(3):
            recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(i, i, 1.0), log_time_ns=i,
                           publish_time_ns=i)
        recorder.write("adn/g/scenario/p_ref", "p_ref", b"{}", log_time_ns=0, publish_time_ns=0)
        assert recorder.counts() == {"adn/g/measurement/p_ip": 3, "adn/g/scenario/p_ref": 1}
    assert read_recording(tmp_path / "r.mcap").counts() == recorder.counts()


def test_count_differences_fail_loudly() -> None:
    published = {"adn/g/a": 3, "adn/g/b": 2}
    assert count_differences(published, published) == []
    differences = count_differences(published, {"adn/g/a": 3, "adn/g/b": 1, "adn/g/c": 1})
    assert [(d.topic, d.published, d.recorded) for d in differences] == [
        ("adn/g/b", 2, 1), ("adn/g/c", 0, 1)]
    with pytest.raises(RecordingLossError, match=r"2 topic\(s\): adn/g/b: published 2, recorded 1"):
        check_counts(published, {"adn/g/a": 3, "adn/g/b": 1, "adn/g/c": 1})


def test_every_recorded_message_validates_against_its_channels_schema(fake) -> None:
    recording = read_recording(fake[0])
    assert validate_recording(recording) == []
    assert set(recording.schemas) == {m.schema_name for m in recording.messages}
    for name, schema in recording.schemas.items():
        assert schema == FAKE_SCHEMAS[name]  # the schemas travel with the file
    for topic, channel in recording.channels.items():
        assert channel.message_encoding == "json"
        assert all(m.schema_name == channel.schema_name for m in recording.messages
                   if m.topic == topic)


def test_validation_reports_a_message_that_breaks_its_schema(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS) as recorder:
        recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(1, 0, 1.0), log_time_ns=0,
                       publish_time_ns=0)
        recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(2, 0, "high"), log_time_ns=0,
                       publish_time_ns=0)
        recorder.write("adn/g/measurement/p_ip", "p_ip", b"not json", log_time_ns=0,
                       publish_time_ns=0)
    problems = validate_recording(read_recording(path))
    assert len(problems) == 2
    assert problems[0] == "adn/g/measurement/p_ip #2: p_ip_w: 'high' is not of type 'number'"
    assert problems[1].startswith("adn/g/measurement/p_ip #3: payload is not JSON")


def test_times_sequences_and_payloads_are_recorded_as_given(fake) -> None:
    recording = read_recording(fake[0])
    sent = list(fake_run())
    assert [m.data for m in recording.messages] == [m.payload for m in sent]
    for message, original in zip(recording.messages, sent):
        payload = message.payload()
        assert message.log_time_ns == original.t_deliver_ns == payload["t_deliver_ns"]
        assert message.publish_time_ns == original.t_send_ns == payload["t_send_ns"]
        assert message.schema_name == payload["type"]
    for topic in recording.channels:
        sequences = [m.sequence for m in recording.messages if m.topic == topic]
        assert sequences == list(range(1, len(sequences) + 1)), topic
    assert recording.time_range_ns() == (0, 60_100_000_000)


def test_run_metadata_holds_config_table_hash_version_seed_and_clock(fake) -> None:
    run = read_recording(fake[0]).run
    assert run["config"] == "grid: fake\n"
    assert run["config_sha256"] == "0" * 64 and run["table_sha256"] == "1" * 64
    assert run["adnmesh_version"] == __version__
    assert run["seed"] == "0" and run["clock"] == "sim"
    assert run["recording_format"] == "1" and run["flush_interval_s"] == "1"


def test_the_file_is_standard_mcap_with_json_and_jsonschema(fake) -> None:
    from mcap.reader import make_reader

    with open(fake[0], "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary.statistics.message_count == sum(fake[1].values())
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        assert [m.name for m in reader.iter_metadata()] == ["adnmesh.run", PUBLISHED_METADATA]


def test_recorder_is_thread_safe(tmp_path: Path) -> None:
    path = tmp_path / "threads.mcap"
    topics = [f"adn/g/der/D{i}/state" for i in range(4)]
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS, flush_interval_s=0.01) as recorder:
        def publish(worker: int) -> None:
            for i in range(400):
                topic = topics[(worker + i) % len(topics)]
                recorder.write(topic, "der_state", b'{"w": %d, "i": %d}' % (worker, i),
                               log_time_ns=i, publish_time_ns=i)

        threads = [threading.Thread(target=publish, args=(w,)) for w in range(8)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    recording = read_recording(path)
    assert recording.counts() == dict.fromkeys(topics, 800) == recorder.counts()
    for topic in topics:
        assert sorted(m.sequence for m in recording.messages if m.topic == topic) == \
            list(range(1, 801))
    assert len({m.data for m in recording.messages}) == 3200


def test_recorder_refuses_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="flush_interval_s"):
        Recorder(tmp_path / "a.mcap", metadata={}, schemas={}, flush_interval_s=0)
    with pytest.raises(TypeError, match="must be str"):
        Recorder(tmp_path / "a.mcap", metadata={"seed": 1}, schemas={})
    recorder = Recorder(tmp_path / "b.mcap", metadata={}, schemas=FAKE_SCHEMAS)
    with pytest.raises(ValueError, match="unknown message type 'nope'"):
        recorder.write("adn/g/x", "nope", b"{}", log_time_ns=0, publish_time_ns=0)
    recorder.write("adn/g/x", "p_ip", b"{}", log_time_ns=0, publish_time_ns=0)
    with pytest.raises(ValueError, match="recorded as 'p_ip'"):
        recorder.write("adn/g/x", "p_ref", b"{}", log_time_ns=0, publish_time_ns=0)
    with pytest.raises(ValueError, match=">= 0 ns"):
        recorder.write("adn/g/x", "p_ip", b"{}", log_time_ns=-1, publish_time_ns=0)
    recorder.close()
    recorder.close()  # a second close does nothing
    with pytest.raises(RuntimeError, match="closed"):
        recorder.write("adn/g/x", "p_ip", b"{}", log_time_ns=0, publish_time_ns=0)
    assert read_recording(tmp_path / "b.mcap").counts() == {"adn/g/x": 1}


def test_periodic_flush_makes_data_readable_before_close(tmp_path: Path) -> None:
    path = tmp_path / "open.mcap"
    recorder = Recorder(path, metadata={"clock": "sim"}, schemas=FAKE_SCHEMAS,
                        flush_interval_s=0.02)
    try:
        recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(1, 5, 2.0), log_time_ns=5,
                       publish_time_ns=5)
        deadline = time.monotonic() + 10
        while not read_recording(path).messages:  # the flush timer, not close(), writes it
            assert time.monotonic() < deadline, "nothing flushed within 10 s"
            time.sleep(0.01)
        recording = read_recording(path)
        assert not recording.complete and recording.recovered_messages == 1
        assert recording.run["clock"] == "sim"
    finally:
        recorder.close()
    assert read_recording(path).complete


def test_a_failing_disk_fails_the_recording_loudly(tmp_path: Path, monkeypatch) -> None:
    recorder = Recorder(tmp_path / "full.mcap", metadata={}, schemas=FAKE_SCHEMAS,
                        flush_interval_s=0.01)

    def disk_full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("adnmesh.recording.writer.os.fsync", disk_full)
    deadline = time.monotonic() + 10
    with pytest.raises(RuntimeError, match="recording failed") as info:
        while time.monotonic() < deadline:  # the flush timer hits the error, write() reports it
            recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(1, 0, 1.0), log_time_ns=0,
                           publish_time_ns=0)
            time.sleep(0.005)
    assert "No space left on device" in str(info.value.__cause__)
    with pytest.raises(RuntimeError, match="recording failed"):
        recorder.close()


@pytest.mark.parametrize("how", ["hook", "fsync"])
def test_a_full_disk_leaves_the_file_cut_to_what_the_last_flush_wrote(
        tmp_path: Path, monkeypatch, how: str) -> None:
    """Issue 39: a write that fails ends the recording; close() cuts the file back to the
    whole records of the last successful flush (no unfinished chunk at its end, its space
    given back), which read_recording reads and recover() completes: exactly ``on_disk``."""
    from adnmesh.recording.writer import DISK_FULL_ENV

    if how == "hook":                       # the test hook: a file that fills after 40 kB
        monkeypatch.setenv(DISK_FULL_ENV, "40000")
    path = tmp_path / "full.mcap"
    recorder = Recorder(path, metadata={"clock": "sim"}, schemas=FAKE_SCHEMAS,
                        flush_interval_s=0.01)
    assert recorder.failure is None
    if how == "fsync":
        recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(1, 0, 1.0), log_time_ns=0,
                       publish_time_ns=0)
        recorder.flush()                      # one message on disk, then the disk fails

        def disk_full(fd: int) -> None:
            raise OSError(28, "No space left on device")
        monkeypatch.setattr("adnmesh.recording.writer.os.fsync", disk_full)
    deadline, i = time.monotonic() + 20, 1 if how == "fsync" else 0
    with pytest.raises(RuntimeError, match="recording failed"):
        while time.monotonic() < deadline:
            i += 1
            recorder.write("adn/g/measurement/p_ip", "p_ip", _p_ip(i, i * 10_000_000, 1.0),
                           log_time_ns=i * 10_000_000, publish_time_ns=i * 10_000_000)
            time.sleep(0.0005)
    failure = recorder.failure
    assert isinstance(failure, OSError) and failure.errno == 28
    messages, last_ns = recorder.on_disk
    assert messages >= 1
    with pytest.raises(RuntimeError, match="recording failed"):
        recorder.close()
    monkeypatch.undo()                          # the disk works again (recover writes)
    if how == "hook":
        assert path.stat().st_size <= 40000
    recording = read_recording(path)
    assert not recording.complete and recording.dropped_bytes == 0
    assert len(recording.messages) == messages
    assert recording.messages[-1].log_time_ns == last_ns
    assert [m.sequence for m in recording.messages] == list(range(1, messages + 1))
    assert recover(path, tmp_path / "recovered.mcap") == messages
    assert read_recording(tmp_path / "recovered.mcap").complete


def test_the_disk_full_hook_fails_like_a_full_disk(tmp_path: Path, monkeypatch) -> None:
    """The test hook writes what fits (a short write), then fails every write with ENOSPC."""
    from adnmesh.recording.writer import DISK_FULL_ENV, _open_for_writing

    monkeypatch.setenv(DISK_FULL_ENV, "10")
    fh = _open_for_writing(tmp_path / "f")
    fh.write(b"0123456")
    with pytest.raises(OSError) as info:
        fh.write(b"789abcdef")
        fh.flush()
    assert info.value.errno == 28
    with pytest.raises(OSError):
        fh.close()
    assert (tmp_path / "f").read_bytes() == b"0123456789"
    monkeypatch.delenv(DISK_FULL_ENV)
    with _open_for_writing(tmp_path / "g") as fh:
        assert type(fh).__name__ == "BufferedWriter" and fh.raw.name == str(tmp_path / "g")


# A recorder in its own process, killed with SIGKILL. After each write it reports
# "<message number> <time.monotonic()>" (CLOCK_MONOTONIC is system-wide on Linux).
_WRITER = """
import json, sys, time
sys.path.insert(0, sys.argv[3])
from adnmesh.recording import Recorder
from synthetic_runs import FAKE_SCHEMAS
recorder = Recorder(sys.argv[1], metadata={"clock": "realtime"}, schemas=FAKE_SCHEMAS,
                    flush_interval_s=float(sys.argv[2]))
i = 0
while True:
    i += 1
    t = time.monotonic_ns()
    payload = {"v": 1, "type": "p_ip", "src": "m", "seq": i, "t_send_ns": t, "t_deliver_ns": t,
               "p_ip_w": float(i)}
    recorder.write("adn/g/measurement/p_ip", "p_ip", json.dumps(payload).encode(),
                   log_time_ns=t, publish_time_ns=t)
    print(i, time.monotonic(), flush=True)
    time.sleep(0.0005)
"""
_FLUSH_INTERVAL_S = 0.05
# for the flush thread to get the CPU on a loaded machine (once 0.25 s in CI, with tuning pool
# workers on the other xdist worker); the writer runs for longer than that before the kill
_SCHEDULING_ALLOWANCE_S = 0.5


def test_sigkilled_recorder_leaves_every_message_older_than_the_flush_interval(
        tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    child = subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(_FLUSH_INTERVAL_S),
                              str(Path(__file__).parent)],
                             stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT)
    try:
        reported: list[tuple[int, float]] = []
        deadline = time.monotonic() + 30
        # wait for the child's own report of 10 flush intervals of writing beyond the
        # allowance (so some messages are old enough to be owed), and for flushed chunks on
        # disk (the file grows past its header)
        header_size = None
        while True:
            line = child.stdout.readline()
            assert line, "the writer died"
            number, t = line.split()
            reported.append((int(number), float(t)))
            header_size = header_size or path.stat().st_size
            if (reported[-1][1] - reported[0][1] > 10 * _FLUSH_INTERVAL_S + _SCHEDULING_ALLOWANCE_S
                    and path.stat().st_size > header_size):
                break
            assert time.monotonic() < deadline, "the writer did not get going within 30 s"
        t_kill = time.monotonic()
        os.kill(child.pid, signal.SIGKILL)
        assert child.wait(timeout=10) == -signal.SIGKILL
        reported += [(int(n), float(t)) for n, t in
                     (line.split() for line in child.stdout.read().splitlines())]
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        child.stdout.close()

    recording = read_recording(path)
    assert not recording.complete
    numbers = [m.payload()["seq"] for m in recording.messages]
    assert numbers == list(range(1, len(numbers) + 1))  # a gapless prefix
    assert [m.sequence for m in recording.messages] == numbers
    old = [n for n, t in reported if t < t_kill - _FLUSH_INTERVAL_S - _SCHEDULING_ALLOWANCE_S]
    assert old and len(numbers) >= max(old)
    assert recording.recovered_messages == len(numbers)

    out = tmp_path / "recovered.mcap"
    assert recover(path, out) == len(numbers)
    recovered = read_recording(out)
    assert recovered.complete
    assert recovered.messages == recording.messages
    assert recovered.metadata[RECOVERY_METADATA] == {
        "source": str(path), "complete": "false", "messages": str(len(numbers)),
        "dropped_bytes": str(recording.dropped_bytes)}
    assert recovered.run["clock"] == "realtime"


def test_recovery_from_any_truncation_point_keeps_whole_chunks(chunked, tmp_path: Path) -> None:
    data = chunked.read_bytes()
    whole = read_recording(chunked).messages
    previous = -1
    for cut in range(200, len(data), len(data) // 97):
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[:cut])
        recording = read_recording(path)
        assert not recording.complete
        assert recording.messages == whole[:len(recording.messages)]  # a prefix, intact
        assert len(recording.messages) >= previous
        previous = len(recording.messages)
        if cut < len(data) // 2:
            middle = previous
    assert 0 < middle < previous <= len(whole)


def test_a_tail_of_zeros_counts_as_truncation(fake, tmp_path: Path) -> None:
    data = fake[0].read_bytes()
    path = tmp_path / "zeros.mcap"
    path.write_bytes(data[: len(data) // 2] + bytes(4096))
    assert not read_recording(path).complete


def test_recover_of_a_complete_file_copies_it(fake, tmp_path: Path) -> None:
    out = tmp_path / "copy.mcap"
    assert recover(fake[0], out) == sum(fake[1].values())
    original, copy = read_recording(fake[0]), read_recording(out)
    assert copy.messages == original.messages
    assert copy.schemas == original.schemas
    assert copy.metadata_records[:-1] == original.metadata_records


@pytest.mark.parametrize("content, message", [
    (b"", "empty file, not an MCAP recording"),
    (b"hello, world\n", "not an MCAP file"),
    (b"\x89MCAP0\r\n" + bytes(range(7, 200)), "corrupt MCAP file"),
])
def test_non_mcap_files_raise_one_line_errors(tmp_path: Path, content: bytes,
                                              message: str) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message) as info:
        read_recording(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_a_damaged_chunk_is_an_error_not_a_truncation(chunked, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    with open(chunked, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[3]
    data = bytearray(chunked.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 20] ^= 0xFF  # inside compressed data
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=f"corrupt MCAP file: chunk record at byte "
                                             f"{chunk.chunk_start_offset}"):
        read_recording(path)


def test_missing_file_and_directory_raise_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.mcap")
    with pytest.raises(RecordingError, match="is a directory"):
        read_recording(tmp_path)


def test_the_file_format_imports_nothing_of_what_a_run_means() -> None:
    """adnmesh.recording is the file format: it imports nothing from adnmesh.results (nor
    anything above it), not even inside a function."""
    import ast

    above = ("adnmesh.results", "adnmesh.runtime", "adnmesh.commands")
    for path in sorted((REPO_ROOT / "adnmesh" / "recording").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else \
                [a.name for a in node.names] if isinstance(node, ast.Import) else []
            assert not [n for n in names if n.startswith(above)], path.name
