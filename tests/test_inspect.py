"""Tests of ``adnmesh inspect``: summary, recovery of a killed run's file, errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.cli import main
from adnmesh.recording import PUBLISHED_METADATA, Recorder, read_recording
from synthetic_runs import FAKE_SCHEMAS, fake_run, write_fake_run


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> Path:
    """A recorded fake run (60 s of sim time) with its publishers' counts."""
    path = tmp_path_factory.mktemp("fake") / "fake.mcap"
    write_fake_run(path)
    return path


def _lines(text: str) -> list[str]:
    return [" ".join(line.replace("│", " ").split()) for line in text.splitlines()]


def test_inspect_summarises_a_complete_recording(fake: Path, capsys) -> None:
    assert main(["inspect", str(fake)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    lines = _lines(out)
    assert lines[0].startswith(f"{fake}: complete MCAP recording, 3917 messages on 13 topics, ")
    assert lines[1].startswith("run: run_id fake, clock sim, seed 0, adnmesh_version ")
    assert "time: 0.000 to 60.100 s (sim_time, send and delivery times)" in lines
    assert "adn/fake/measurement/p_ip p_ip 601 0.000 60.000" in lines
    assert "adn/fake/der/WT1/state der_state 601 0.000 60.000" in lines
    assert "adn/fake/faults fault 1 40.000 40.000" in lines
    assert "5.00 +1.000 1.186 1.588 0.585 -1.33 10.00" in lines     # window ends at the next step
    assert "50.00 -0.200 5.978 6.912 4.324 8.65 10.00" in lines     # ... at the end of the run
    assert "events: 1 gain switches, 1 availability changes, 1 fault events, 4 DER mode " \
           "changes" in lines
    assert any(line.startswith("25.000 s gain switch to entry 12: K_P 6.593e-08 -> 6.364e-07")
               for line in lines)
    assert "41.000 s CHP1: mode control -> watchdog" in lines
    assert "published counts: every message recorded (3917 on 13 topics)" in lines
    assert not any("recovered" in line for line in lines)


def test_inspect_validates_schemas_on_request(fake: Path, capsys) -> None:
    assert main(["inspect", str(fake), "--validate"]) == 0
    assert "schema check: all 3917 messages valid" in _lines(capsys.readouterr().out)


def test_inspect_prints_the_metadata_on_request(fake: Path, capsys) -> None:
    assert main(["inspect", str(fake), "--metadata"]) == 0
    lines = _lines(capsys.readouterr().out)
    assert "metadata adnmesh.run:" in lines and "config: grid: fake" in lines
    assert f"metadata {PUBLISHED_METADATA}:" in lines


def test_inspect_recovers_a_truncated_recording(fake: Path, tmp_path: Path, capsys) -> None:
    # a killed recorder: the fake run with a flush every 500 messages, cut mid-chunk
    path = tmp_path / "killed.mcap"
    recorder = Recorder(path, metadata={"run_id": "killed"}, schemas=FAKE_SCHEMAS,
                        flush_interval_s=3600)   # chunks end where the test flushes, not by time
    for i, m in enumerate(fake_run()):
        recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                       publish_time_ns=m.t_send_ns)
        if i % 500 == 499:
            recorder.flush()
    size_before = path.stat().st_size
    recorder.flush()  # the last 100 messages: one more chunk (and its message indexes)
    size_after = path.stat().st_size
    recorder.close()
    data = path.read_bytes()
    path.write_bytes(data[: (size_before + size_after) // 2])  # the last chunk is unfinished
    expected = read_recording(path)
    assert 0 < len(expected.messages) < 3917 and len(expected.messages) % 500 == 0

    assert main(["inspect", str(path)]) == 0
    lines = _lines(capsys.readouterr().out)
    n = len(expected.messages)
    recovered = tmp_path / "killed.recovered.mcap"
    assert lines[0].startswith(f"{path}: TRUNCATED MCAP recording, {n} messages on ")
    assert lines[1] == f"recovered {n} messages into {recovered} " \
                       f"({expected.dropped_bytes} bytes of an unfinished record dropped)"
    assert expected.dropped_bytes > 0
    again = read_recording(recovered)
    assert again.complete and again.messages == expected.messages
    assert again.run["run_id"] == "killed"

    out = tmp_path / "elsewhere" / "r.mcap"
    assert main(["inspect", str(path), "--recover-to", str(out)]) == 0
    assert f"recovered {n} messages into {out} " in capsys.readouterr().out
    assert read_recording(out).complete


def test_inspect_fails_loudly_when_counts_differ(tmp_path: Path, capsys) -> None:
    path = tmp_path / "lossy.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS) as recorder:
        for m in list(fake_run(1.0))[:10]:
            recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                           publish_time_ns=m.t_send_ns)
        published = recorder.counts()
        published["adn/fake/measurement/p_ip"] += 2
        recorder.add_metadata(PUBLISHED_METADATA, {k: str(v) for k, v in published.items()})
    assert main(["inspect", str(path)]) == 1
    lines = _lines(capsys.readouterr().out)
    assert "published counts: MISMATCH on 1 topic(s)" in lines
    assert "adn/fake/measurement/p_ip: published 3, recorded 1" in lines


def test_inspect_reports_schema_violations(tmp_path: Path, capsys) -> None:
    path = tmp_path / "invalid.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS) as recorder:
        recorder.write("adn/g/measurement/p_ip", "p_ip", b'{"p_ip_w": 1}', log_time_ns=0,
                       publish_time_ns=0)
    assert main(["inspect", str(path), "--validate"]) == 1
    lines = _lines(capsys.readouterr().out)
    assert "schema check: 1 problems" in lines
    assert "adn/g/measurement/p_ip #1: (top level): 'v' is a required property" in lines


@pytest.mark.parametrize("content, problem", [
    (b"", "empty file, not an MCAP recording"),
    (b"PK\x03\x04 a zip file", "not an MCAP file (it does not start with the MCAP magic)"),
    (b"\x89MCAP0\r\n\x07garbage-garbage-garbage", "corrupt MCAP file: no header record after "
                                                   "the magic"),
    (b"\x89MCAP0\r\n\x42" + bytes(40), "corrupt MCAP file: invalid record opcode 0x42 at byte 8"),
])
def test_a_corrupt_or_non_mcap_file_is_a_one_line_error_exit_2(tmp_path: Path, content: bytes,
                                                               problem: str, capsys) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    assert main(["inspect", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"adnmesh: error: {path}: {problem}\n"


def test_a_damaged_chunk_is_a_one_line_error_exit_2(fake: Path, tmp_path: Path,
                                                    capsys) -> None:
    from mcap.reader import make_reader

    with open(fake, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[0]
    data = bytearray(fake.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x55
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"adnmesh: error: {path}: corrupt MCAP file: chunk record at byte "
                          f"{chunk.chunk_start_offset}: ")
    assert err.count("\n") == 1


def test_inspect_of_a_missing_file_is_exit_2(tmp_path: Path, capsys) -> None:
    assert main(["inspect", str(tmp_path / "nope.mcap")]) == 2
    assert capsys.readouterr().err == f"adnmesh: error: {tmp_path / 'nope.mcap'}: no such file\n"


def test_inspect_runs_as_a_program(fake: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "adnmesh", "inspect", str(fake)],
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    assert "3917 messages on 13 topics" in result.stdout


def test_inspect_finds_the_windows_of_up_s_summary(tmp_path: Path) -> None:
    """Every event that ends a step's window in ``up``'s summary ends it in ``inspect`` too:
    a switch record, a heartbeat flag change, an SI change alone (a heartbeat timeout), a
    fault; not a gain change without a switch record, not the initial SI nor a repeated one;
    the last window closes at the start message's end."""
    import dataclasses
    import json
    import math

    import numpy as np

    from adnmesh.results.figures import run_figures
    from adnmesh.results.series import extract
    from adnmesh.results.summary import SUMMARY_TYPES, RunSeries, summarize
    from adnmesh.wire.keys import Keys, route
    from adnmesh.wire.messages import Switch
    from adnmesh.wire.schemas import message_schemas
    from payloads import payload

    keys, s = Keys("g"), 1_000_000_000
    gains = {"p_y": 0.1, "p_ref_w": 0.0, "kp": 1e-7, "ki": 2e-7, "entry": 3}
    events = [(0, keys.of("clock_start"), "up", {"clock": "sim", "epoch_ns": 0, "speed": 1.0,
                                     "end_ns": 70 * s, "seed": 0}),
              (0, keys.of("si"), "availability", {"si": {"A": True, "B": True}}),
              (3 * s, keys.of("si"), "availability", {"si": {"A": True, "B": True}}),
              (8 * s, keys.of("p_y"), "cpfc", {**gains, "kp": 3e-7}),          # no switch record
              (12 * s, keys.of("p_y"), "cpfc", {**gains, "w": {"A": 1.0}, "switch": Switch(
                  p_y_before=0.1, p_y_limited=0.1, kp_before=3e-7, ki_before=2e-7)}),
              (15 * s, keys.of("heartbeat", "B"), "der/B", {"available": True}),
              (22 * s, keys.of("heartbeat", "B"), "der/B", {"available": False}),
              (33 * s, keys.of("si"), "availability", {"si": {"A": False, "B": False}}),
              (1 * s, keys.of("fault"), "up", {"fault_id": 1, "kind": "der_offline", "der": "A",
                                          "start_ns": 41 * s, "end_ns": 80 * s})]
    steps = ((0, 0.0), (5, 1e6), (20, 0.0), (30, 1e6), (40, 0.0), (60, 1e6))
    events += [(t * s, keys.of("p_ref"), "cpfc", {"p_ref_w": w}) for t, w in steps]
    p_ip = 0.0                                   # P_ref through a 1 s lag, sampled every 10 ms
    for k in range(7001):
        events.append((k * 10_000_000, keys.of("p_ip"), "measurement", {"p_ip_w": p_ip}))
        p_ref = [w for t, w in steps if t * 100 <= k][-1]
        p_ip += (p_ref - p_ip) * (1 - math.exp(-0.01))
    path = tmp_path / "windows.mcap"
    series = RunSeries()
    with Recorder(path, metadata={}, schemas=message_schemas()) as recorder:
        for i, (t_ns, key, src, body) in enumerate(sorted(events, key=lambda e: e[0])):
            kind = route(key).type
            data = payload(key, body, src=src, seq=i, t_send_ns=t_ns, t_deliver_ns=t_ns + 1)
            recorder.write(key, kind, data, log_time_ns=t_ns + 1, publish_time_ns=t_ns)
            if kind in SUMMARY_TYPES and (kind != "p_y" or "switch" in body):
                series.add(kind, json.loads(data))
    summary = summarize(series, end_ns=70 * s)
    inspected = run_figures(extract(read_recording(path)))
    assert [(x.t_s, x.window_s) for x in summary.steps] == [
        (5.0, 7.0), (20.0, 2.0), (30.0, 3.0), (40.0, 1.0), (60.0, 10.0)]
    assert math.isnan(summary.steps[3].figures.rise_time_s)     # 1 s: no 90 % crossing
    np.testing.assert_equal([dataclasses.astuple(x) for x in inspected.steps],
                            [dataclasses.astuple(x) for x in summary.steps])
    _assert_one_window_rule(path, series)


def _assert_one_window_rule(path: Path, series) -> None:
    """The instants that ended windows in ``up``'s summary (``series``, fed as the recorder
    tap feeds it) are those the one rule finds in the recording's events, and the summary
    ``inspect`` computes of the recording itself has the same steps."""
    import dataclasses

    import numpy as np

    from adnmesh.commands.inspect import _summary, _SummaryMessages
    from adnmesh.results.figures import run_figures
    from adnmesh.results.rules import window_ends
    from adnmesh.results.series import read_run

    found, messages = read_run(path, also=_SummaryMessages)
    assert sorted(set(series.windows.instants)) == sorted(set(window_ends(found.run.events)))
    again = _summary(found.recording, messages, 5.0)
    np.testing.assert_equal([dataclasses.astuple(x) for x in again.steps],
                            [dataclasses.astuple(x) for x in run_figures(found.run).steps])


def test_up_s_summary_and_inspect_agree_on_a_run_with_every_kind_of_window_end(
        fake: Path) -> None:
    """The fake run (steps, a gain switch as two DERs leave, their heartbeat flags and SI, a
    fault with its end): ``up``'s summary of its messages, fed as the recorder tap feeds
    them, and ``inspect``'s figures of its recording have the same steps, windows and all."""
    import dataclasses
    import json

    import numpy as np

    from adnmesh.results.figures import run_figures
    from adnmesh.results.series import extract
    from adnmesh.results.summary import SUMMARY_TYPES, RunSeries, summarize

    series = RunSeries()
    for m in fake_run():
        if m.schema_name in SUMMARY_TYPES and (m.schema_name != "p_y" or b'"switch"' in m.payload):
            series.add(m.schema_name, json.loads(m.payload))
    summary = summarize(series, end_ns=60_000_000_000)
    inspected = run_figures(extract(read_recording(fake)))
    assert [(x.t_s, x.window_s) for x in summary.steps] == [
        (5.0, 10.0), (15.0, 10.0), (30.0, 10.0), (50.0, 10.0)]
    # at 25 s the switch, SI and the two heartbeat flags; the fault from 40 s to 42 s
    assert sorted(series.windows.instants) == [25_000_000_000] * 4 + [40_000_000_000,
                                                                      42_000_000_000]
    np.testing.assert_equal([dataclasses.astuple(x) for x in inspected.steps],
                            [dataclasses.astuple(x) for x in summary.steps])
    _assert_one_window_rule(fake, series)


def test_the_summary_finds_its_window_events_by_the_event_rules() -> None:
    """Each message type the summary asks about an event (:data:`WINDOW_EVENTS`) is the type
    of the keys whose rule finds that kind of event (:data:`EVENTS`, SI:
    :data:`AVAILABILITY_KEYS`): the summary and the extraction read the same messages."""
    from adnmesh.results.rules import AVAILABILITY_KEYS, EVENTS
    from adnmesh.results.summary import SUMMARY_TYPES, WINDOW_EVENTS
    from adnmesh.wire.keys import route

    def key(pattern: str) -> str:
        return pattern.format(grid="g", der="D").replace("/**", "/cpfc")

    patterns = {rule.kind: [p for p, r in EVENTS.items() if r.kind == rule.kind]
                for rule in EVENTS.values()} | {"availability": list(AVAILABILITY_KEYS)}
    assert set(WINDOW_EVENTS) <= SUMMARY_TYPES
    for message_type, kind in WINDOW_EVENTS.items():
        assert [route(key(p)).type for p in patterns[kind]] == [message_type], kind


def test_inspect_json_is_one_object_with_topics_counts_figures_and_events(fake: Path,
                                                                          capsys) -> None:
    import json

    assert main(["inspect", str(fake), "--json"]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)                 # the whole output is one JSON object
    assert err == ""
    assert report["complete"] is True and report["messages"] == 3917
    assert report["run"]["run_id"] == "fake" and "config" not in report["run"]
    topics = {t["topic"]: t for t in report["topics"]}
    from adnmesh.results.rules import natural_key

    assert list(topics) == sorted(topics, key=natural_key)      # sorted, as the table is
    assert sorted(["adn/g/der/SGen10/state", "adn/g/der/SGen2/state"], key=natural_key)[0] \
        == "adn/g/der/SGen2/state"
    assert topics["adn/fake/measurement/p_ip"] == {
        "topic": "adn/fake/measurement/p_ip", "type": "p_ip", "messages": 601, "first_s": 0.0,
        "last_s": 60.0}
    assert report["counts"]["check"] == "ok"
    figures = report["figures"]
    first = figures["steps"][0]
    assert (first["t_s"], first["step_w"], first["window_s"]) == (5.0, 1.0e6, 10.0)
    assert round(first["rise_time_s"], 3) == 1.186 and first["settled"] is True
    assert (figures["gain_switches"], figures["availability_changes"], figures["faults"],
            figures["mode_changes"]) == (1, 1, 1, 4)
    kinds = [e["kind"] for e in report["events"]]
    assert "gain_switch" in kinds and "fault" in kinds
    assert any(e["text"] == "CHP1: mode control -> watchdog" and e["t_s"] == 41.0
               for e in report["events"])


def test_piped_tables_keep_long_topic_names_whole(tmp_path: Path, capsys) -> None:
    path = tmp_path / "long.mcap"
    topic = "adn/" + "a-very-long-grid-name-" * 5 + "/measurement/p_ip"
    with Recorder(path, metadata={"run_id": "long"}, schemas=FAKE_SCHEMAS) as recorder:
        recorder.write(topic, "p_ip", b'{"v":1,"type":"p_ip","src":"m","seq":0,"t_send_ns":0,'
                       b'"t_deliver_ns":0,"p_ip_w":1.0}', log_time_ns=0, publish_time_ns=0)
    assert main(["inspect", str(path)]) == 0
    assert f"{topic} p_ip 1 0.000 0.000" in _lines(capsys.readouterr().out)
