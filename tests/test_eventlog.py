"""Tests of the run's events as foxglove.Log messages written by the recorder."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

import jsonschema
import pytest

from adnmesh.recording import Recorder, read_recording
from adnmesh.recording.foxglove_log import (FOXGLOVE_LOG, FOXGLOVE_LOG_SCHEMA, LOG_LEVELS,
                                            log_record)
from adnmesh.results.eventlog import EventLog
from adnmesh.results.series import extract, read_run
from synthetic_runs import FAKE_SCHEMAS, fake_run

EVENTS = "adn/fake/log"


@pytest.fixture(scope="module")
def logged(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("log") / "fake.mcap"
    with Recorder(path, metadata={"run_id": "log"}, schemas=FAKE_SCHEMAS,
                  events_topic=EVENTS, events=EventLog().observe) as recorder:
        for m in fake_run():
            recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                           publish_time_ns=m.t_send_ns)
        assert EVENTS not in recorder.counts()          # no agent publishes them
    return path


def test_events_are_foxglove_log_messages_beside_the_run(logged: Path) -> None:
    recording = read_recording(logged)
    assert recording.channels[EVENTS].schema_name == FOXGLOVE_LOG
    assert recording.channels[EVENTS].message_encoding == "json"
    assert recording.schemas[FOXGLOVE_LOG] == FOXGLOVE_LOG_SCHEMA
    logs = [m for m in recording.messages if m.topic == EVENTS]
    for m in logs:
        body = m.payload()
        jsonschema.validate(body, FOXGLOVE_LOG_SCHEMA)
        assert set(body) == {"timestamp", "level", "message", "name", "file", "line"}
        t = body["timestamp"]
        assert t["sec"] * 10**9 + t["nsec"] == m.publish_time_ns == m.log_time_ns
    # the same texts replay and inspect show (DER mode changes come as agents' events), the
    # kind first; name: the agent the event is about or that sent it, as Foxglove defines it
    about = {"gain_switch": lambda e: "cpfc", "availability": lambda e: "availability",
             "fault": lambda e: f"der/{e.data['der']}",
             "der_available": lambda e: f"der/{e.data['der']}"}
    shown = {(e.t_ns, f"[{e.kind}] {e.text}", about[e.kind](e))
             for e in extract(recording).events if e.kind != "der_mode"}
    assert {(m.publish_time_ns, m.payload()["message"], m.payload()["name"])
            for m in logs} == shown
    assert {(m.payload()["file"], m.payload()["line"]) for m in logs} == {("", 0)}   # no file
    assert {m.payload()["name"] for m in logs} == {"cpfc", "availability", "der/CHP1",
                                                   "der/WT1", "der/WT2"}
    levels = {m.payload()["message"]: m.payload()["level"] for m in logs}
    assert any(text.startswith("[gain_switch] gain switch") and level == LOG_LEVELS["INFO"]
               for text, level in levels.items())
    assert any(text.startswith("[fault] fault ") and level == LOG_LEVELS["WARN"]
               for text, level in levels.items())


def test_the_wall_clock_start_is_in_the_metadata(logged: Path) -> None:
    run = read_recording(logged).run
    start = datetime.fromisoformat(run["start_utc"])
    assert start.utcoffset().total_seconds() == 0
    assert abs(start.timestamp() * 1e9 - int(run["start_unix_ns"])) < 1e3
    assert run["events_topic"] == EVENTS


def test_the_log_is_neither_a_series_nor_an_event_twice(logged: Path) -> None:
    found, _ = read_run(logged)
    assert not any(s.topic == EVENTS for s in found.run.series.values())
    assert not any(e.topic == EVENTS for e in found.run.events)


def test_log_record_splits_the_time_and_maps_the_level() -> None:
    body = json.loads(log_record(12_345_678_901, "WARN", "text", "name", "a/b"))
    assert body == {"timestamp": {"sec": 12, "nsec": 345_678_901}, "level": 3,
                    "message": "text", "name": "name", "file": "a/b", "line": 0}


def test_the_recorder_takes_its_events_from_outside(tmp_path: Path) -> None:
    """The recorder knows the foxglove.Log format; what an event is comes from its caller."""
    seen = []

    def events(topic: str, schema_name: str, payload: bytes, t_ns: int) -> list[bytes]:
        seen.append((topic, schema_name, t_ns))
        return [log_record(t_ns, "INFO", f"saw {topic}", "test")]

    path = tmp_path / "own.mcap"
    with Recorder(path, metadata={}, schemas=FAKE_SCHEMAS, events_topic=EVENTS,
                  events=events) as recorder:
        recorder.write("adn/fake/measurement/p_ip", "p_ip", b"{}", log_time_ns=7,
                       publish_time_ns=5)
    assert seen == [("adn/fake/measurement/p_ip", "p_ip", 5)]
    (log,) = [m for m in read_recording(path).messages if m.topic == EVENTS]
    assert log.payload()["message"] == "saw adn/fake/measurement/p_ip"
    with pytest.raises(ValueError, match="give both or neither"):
        Recorder(tmp_path / "half.mcap", metadata={}, schemas=FAKE_SCHEMAS, events_topic=EVENTS)


def test_each_record_names_the_agent_it_is_about_or_that_sent_it() -> None:
    """Foxglove's ``name`` is the process: the agent an event is about (a lost agent, a
    fault's target, a DER's heartbeat) or that sent it; the kind leads the message."""
    from adnmesh.wire.keys import Keys, route
    from payloads import payload

    keys = Keys("g")
    log = EventLog()

    def records(key: str, body: dict, src: str | None = None) -> list[tuple[str, str]]:
        found = log.observe(key, route(key).type, payload(key, body, src=src), 5)
        return [(json.loads(r)["name"], json.loads(r)["message"]) for r in found]

    lost = {"level": "ERROR", "kind": "agent_lost", "text": "der/SGen3 died",
            "subject": "der/SGen3"}
    assert records(keys.of("event", "up"), lost) == [
        ("der/SGen3", "[agent_lost] up: der/SGen3 died")]
    stale = {"level": "WARNING", "kind": "si_stale", "text": "no SI for 2 s"}
    assert records(keys.of("event", "cpfc"), stale) == [("cpfc", "[si_stale] cpfc: no SI for 2 s")]
    kill = {"fault_id": 1, "kind": "kill", "agent": "measurement", "start_ns": 5, "end_ns": None}
    outage = {"fault_id": 2, "kind": "link_outage", "link": "cpfc_to_der", "start_ns": 5,
              "end_ns": 9}
    assert [name for name, _ in records(keys.of("fault"), kill)] == ["measurement"]
    assert [name for name, _ in records(keys.of("fault"), outage)] == ["up"]
    start = {"clock": "sim", "epoch_ns": 0, "speed": 1.0, "end_ns": 10**10, "seed": 1}
    (run_start,) = records(keys.of("clock_start"), start)
    assert run_start[0] == "up" and run_start[1].startswith("[run_start] run starts: sim clock")
    (record,) = log.observe("adn/g/rejected", "rejected", json.dumps(
        {"key": "adn/g/cpfc/p_y", "reason": "sender", "detail": "x"}).encode(), 7)
    rejected = json.loads(record)
    assert (rejected["name"], rejected["message"]) == (
        "up", "[rejected] rejected a payload on adn/g/cpfc/p_y: sender (x)")


def test_fault_spans_of_faults_at_one_instant_one_without_an_end() -> None:
    """A quarantine (a kill, an instant) and an ICT outage without an end at the same time:
    the spans sort (they compared None with a number and ``inspect`` crashed)."""
    from adnmesh.results.rules import Event
    from adnmesh.results.series import RunData

    events = [Event(0, "fault", "ERROR", "outage", "faults",
                    {"fault_id": 2, "kind": "ict_outage", "start_ns": 0, "end_ns": None}),
              Event(0, "fault", "ERROR", "kill", "faults",
                    {"fault_id": 1, "kind": "kill", "start_ns": 0, "end_ns": None}),
              Event(5, "fault", "ERROR", "again", "faults",
                    {"fault_id": 1, "kind": "kill", "start_ns": 0, "end_ns": None})]
    spans = RunData(series={}, events=events, der_ids=[], t0_ns=0).fault_spans()
    assert spans == [(0, 0, "kill"), (0, None, "outage")]


def test_quiet_topics_hold_no_event_and_leaving_them_out_changes_no_record(tmp_path) -> None:
    """``EventLog.quiet`` (the recorder's ``events_quiet``) says a topic and type hold no event:
    over an in-process run with a step and two DERs going out and coming back (gain switches),
    every message of a quiet topic observes to nothing, states, reports and grants are quiet,
    and the log written with and without it is the same."""
    from adnmesh.config import load_config
    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.sim.local import run_local
    from adnmesh.runtime.tap import recording_schemas
    from adnmesh.wire.keys import Keys, route

    config = load_config(Path(__file__).parent.parent / "configs/examples/reentry.yaml")
    messages = run_local(config, GainSchedule(config, None)).messages
    judge, quiet_types = EventLog(), set()
    for key, payload in messages:
        kind = route(key).type
        if judge.quiet(key, kind):
            quiet_types.add(kind)
            assert judge.observe(key, kind, payload, 0) == [], (key, payload)
    assert "der_state" in quiet_types
    keys = Keys(config.grid)
    assert judge.quiet(keys.of("clock_report", "der/SGen1"), "clock_report")
    assert judge.quiet(keys.of("clock_grant", "cpfc"), "clock_grant")
    assert not judge.quiet(keys.of("clock_stop"), "clock_stop")
    assert not quiet_types & {"p_y", "heartbeat", "si", "fault", "event", "p_ip"}
    logs = []
    for name, quiet in (("all", None), ("quiet", True)):
        events = EventLog()
        path = tmp_path / f"{name}.mcap"
        with Recorder(path, metadata={}, schemas=recording_schemas(), events_topic=EVENTS,
                      events=events.observe, events_quiet=quiet and events.quiet) as recorder:
            for key, payload in messages:
                body = json.loads(payload)
                recorder.write(key, body["type"], payload, log_time_ns=body["t_deliver_ns"],
                               publish_time_ns=body["t_send_ns"])
        logs.append([m.payload() for m in read_recording(path).messages if m.topic == EVENTS])
    assert logs[0] == logs[1] and len(logs[0]) > 5
