"""Integration tests of ``adnmesh up``: real agent processes around the embedded Zenoh router on
127.0.0.1, the sim clock, the recording, and shutdown (issue 5, tests 7a-7d).

Every run uses a small config (two wind turbines, 12 s of sim time) and its own gain table, writes
into the test's temporary directory, and is bounded by a timeout; processes are found and checked
by PID, never by name.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.sim.local import run_local
from adnmesh.loopmodel.step_response import simulate_step
from adnmesh.tuning.table import load_table
from up_runs import (
    CASE,
    KP2,
    KI2,
    RUN_TIMEOUT_S,
    data_messages,
    finish,
    run_up,
    start_long_run,
    up_argv,
    write_case,
)

@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    """One sim run of the test case, shared by the tests that only read it; its agents note
    when their windows ran (adnmesh.runtime.window_times), which changes none of its messages
    (test_distributed_run_equals_the_in_process_run; runs without it equal the in-process run
    in tests/test_runtime_faults.py)."""
    from adnmesh.runtime.window_times import ENV

    tmp_path = tmp_path_factory.mktemp("up")
    config, table = write_case(tmp_path)
    (tmp_path / "windows").mkdir()
    result, recording, summary = run_up(tmp_path, config, table, "reference",
                                        "--view", str(tmp_path / "live.rrd"),
                                        env={ENV: str(tmp_path / "windows")})
    return tmp_path, config, table, result, recording, summary


# --- 7a: the runtime and the analysis tell the same story ----------------------------------------


def test_distributed_step_response_matches_the_numerics(reference_run) -> None:
    """P_IP recorded by the distributed run vs the closed-loop step response of the reference
    model (adnmesh.loopmodel.step_response) for the same subset and gains.

    Tolerance: the runtime samples P_IP and runs the PI every h = 10 ms and holds P_Y between
    samples; the analysis is continuous. The hold delays the actuation by h/2 on average, so the
    two responses differ by about (h/2) |dy/dt| scaled by the loop's sensitivity (|S| <= 1/2 +
    1/alpha = 1.17 for disk margin alpha >= 1.5): |error| <= h * max|dy/dt| (normalised to the
    step). The in-process tests show the error is first order in h at 0.2 h max|dy/dt|.
    """
    _, config_path, _, _, recording, _ = reference_run
    config = load_config(config_path)
    h = config.runtime.measurement_period_s
    samples = [json.loads(m.data) for m in recording.messages
               if m.topic.endswith("/measurement/p_ip")]
    t = np.array([s["t_send_ns"] for s in samples]) * 1e-9
    p_ip = np.array([s["p_ip_w"] for s in samples])
    assert np.all(np.diff(t) > 0) and t[0] == 0.0 and t[-1] == config.scenario.duration_s
    assert np.allclose(np.diff(t), h)                                  # sampled every h
    p_before = config.runtime.rest_of_grid_w + sum(d.p_sched_w for d in config.ders)
    step = config.scenario.p_ref_steps[0]
    window = (t >= step.t_s) & (t < config.scenario.availability[0].t_s)
    assert np.all(p_ip[t < step.t_s] == p_before)
    t_num, y_num = simulate_step(plant_from_ders(config.ders, config.t_com_s, config.t_meas_s),
                                 KP2, KI2, 8.0, 0.001)
    slope = np.max(np.abs(np.diff(y_num[0]))) / 0.001
    y = (p_ip[window] - p_before) / step.delta_w
    error = np.max(np.abs(y - np.interp(t[window] - step.t_s, t_num, y_num[0])))
    assert error <= h * slope, f"max |y - y_num| = {error:.2e} > h max|dy/dt| = {h * slope:.2e}"


def test_distributed_run_equals_the_in_process_run(reference_run) -> None:
    """The processes exchange exactly the payloads the in-process runner computes."""
    _, config_path, table_path, _, recording, _ = reference_run
    config = load_config(config_path)
    local = run_local(config, GainSchedule(config, load_table(table_path, config),
                                           on_demand=False))
    expected = sorted(local.messages, key=lambda m: (json.loads(m[1])["t_deliver_ns"], m[0],
                                                     json.loads(m[1])["seq"]))
    assert data_messages(recording) == expected


def test_every_agent_noted_when_its_windows_ran(reference_run) -> None:
    """With ADNMESH_WINDOW_TIMES set, each agent writes one file at its end: every window it
    ran, in order of sim time, its grant seen before it began, ended after; its windows are
    those its recorded clock reports say it was granted (one report a window, and the ones
    before the start)."""
    from adnmesh.sim.topology import Topology

    tmp_path, config_path, _, _, recording, _ = reference_run
    topology = Topology.from_config(load_config(config_path))
    paths = sorted((tmp_path / "windows").glob("*.json"))
    files = {json.loads(p.read_text())["agent"]: json.loads(p.read_text())["windows"]
             for p in paths}
    assert len(paths) == len(topology.agents) and sorted(files) == sorted(topology.agents)
    end_ns = max(m.log_time_ns for m in recording.messages)
    for agent, windows in files.items():
        assert windows, agent
        untils = [w[0] for w in windows]
        assert untils == sorted(untils) and len(set(untils)) == len(untils), agent
        assert 0 < untils[0] and untils[-1] <= end_ns + 10 ** 9, agent
        assert all(granted is not None and granted < began <= ended and cpu >= 0
                   for _, granted, began, ended, cpu in windows), agent
        reports = [m for m in recording.messages
                   if m.topic == topology.keys.of("clock_report", agent)]
        granted = {json.loads(m.data)["granted_ns"] for m in reports}
        assert granted - {0} == set(untils), agent   # 0: its reports before the start


def test_recording_holds_every_published_message(reference_run) -> None:
    _, _, _, result, recording, summary = reference_run
    from adnmesh.recording import count_differences, validate_recording
    from adnmesh.recording.writer import PUBLISHED_METADATA

    published = {k: int(v) for k, v in recording.metadata[PUBLISHED_METADATA].items()}
    recorded = {}
    for m in recording.messages:
        if m.topic != recording.run["events_topic"]:   # the recorder's own log of events
            recorded[m.topic] = recorded.get(m.topic, 0) + 1
    assert count_differences(published, recorded) == []
    assert validate_recording(recording, limit=5) == []
    assert recording.run["clock"] == "sim" and recording.run["seed"] == "7"
    assert summary["extra"]["rejected_by_agents"] == 0 and summary["extra"]["agents"] == 5
    assert summary["extra"]["rejected_by_recorder"] == 0


def test_summary_of_the_run(reference_run) -> None:
    _, _, _, result, _, summary = reference_run
    (step,) = summary["steps"]
    assert step["t_s"] == 1.0 and step["step_w"] == 1e6
    assert step["window_s"] == 7.0                # until SGen2's heartbeat says unavailable
    figures = step["figures"]
    assert 2.0 < figures["rise_time_s"] < 3.0 and figures["overshoot_pct"] < 1.0
    assert abs(step["steady_error_w"]) < 5e3                      # 0.5 % of the step
    assert summary["speed_factor"] > 1.0 and summary["extra"]["clock_grants"] > 0
    assert "P_ref steps" in result.stdout and "speed factor" in result.stdout


def assert_inspect_agrees(recording, summary: dict) -> None:
    """``adnmesh inspect``'s step figures of the recording are the summary's, exactly; and so
    are the summary's own figures of every recorded message (SI included)."""
    from adnmesh.commands.inspect import settling_band_pct
    from adnmesh.results.figures import run_figures
    from adnmesh.results.series import extract
    from adnmesh.results.summary import SUMMARY_TYPES, RunSeries, RunSummary, summarize

    def as_json(steps) -> list:
        return json.loads(json.dumps(RunSummary(steps, (), 0, 0, None, None).to_json()["steps"]))

    band = settling_band_pct(recording)
    assert band == summary["band_pct"]
    inspected = run_figures(extract(recording), band_pct=band)
    assert inspected.steps and as_json(inspected.steps) == summary["steps"]
    series = RunSeries()
    for m in sorted(recording.messages, key=lambda m: m.publish_time_ns):
        body = json.loads(m.data)
        if m.schema_name in SUMMARY_TYPES and body["type"] in SUMMARY_TYPES and (body["type"] != "p_y" or "switch" in body):
            series.add(body["type"], body)
    again = summarize(series, end_ns=int(summary["sim_time_s"] * 1e9), band_pct=band)
    assert as_json(again.steps) == summary["steps"]


def test_inspect_gives_the_summary_figures(reference_run) -> None:
    _, _, _, _, recording, summary = reference_run
    assert_inspect_agrees(recording, summary)


# --- 7c: a gain switch with a non-zero integrator causes no jump in P_Y ---------------------------


def test_the_live_view_streamed_during_the_run_equals_its_replay(reference_run) -> None:
    """``up --view FILE.rrd`` (a Rerun stream to a file, headless) during the run: the same
    series and events as ``adnmesh replay`` of its recording."""
    from adnmesh.results.rerun_export import export_rrd
    from adnmesh.results.series import extract, recorded_grid_limits
    from test_live import compare_with_replay

    tmp_path, _, _, result, recording, _ = reference_run
    assert f"live view: streaming to {tmp_path / 'live.rrd'}" in result.stderr
    assert "live view stopped" not in result.stderr
    export_rrd(recording, tmp_path / "replay.rrd")
    compare_with_replay(tmp_path / "live.rrd", tmp_path / "replay.rrd", extract(recording),
                        recorded_grid_limits(recording.run))


def test_gain_switch_is_bumpless_in_the_distributed_run(reference_run) -> None:
    _, config_path, _, _, recording, summary = reference_run
    switches = [json.loads(m.data) for m in recording.messages
                if m.topic.endswith("/cpfc/p_y") and b'"switch"' in m.data]
    (switch,) = switches
    assert switch["t_send_ns"] == 8_200_000_000
    p_ref, kp, ki = switch["p_ref_w"], switch["switch"]["kp_before"], switch["switch"]["ki_before"]
    p_meas = [json.loads(m.data)["p_ip_w"] for m in recording.messages
              if m.topic.endswith("/measurement/p_ip")
              and json.loads(m.data)["t_deliver_ns"] <= switch["t_send_ns"]][-1]
    integrator = (switch["switch"]["p_y_before"] - kp * (p_ref - p_meas)) / ki
    assert abs(ki * integrator) > 0.1                    # the integrator carries P_Y
    assert switch["p_y"] == switch["switch"]["p_y_before"]
    assert (switch["kp"], switch["ki"]) == (2 * KP2, 2 * KI2)
    assert summary["switches"][0]["p_y_jump"] == 0.0


def test_the_cpfc_announced_each_entry_as_an_actuator(reference_run) -> None:
    """docs/hierarchy.md#what-an-adn-announces: the recording holds the ADN as an actuator at
    the start and at the switch, and each announcement rebuilds its entry's closed loop."""
    import msgspec

    from adnmesh.cascade.lower_adn import announced
    from adnmesh.cascade.upper_table import lower_adn
    from adnmesh.wire.messages import AdnActuator

    _, config_path, table_path, _, recording, _ = reference_run
    config = load_config(config_path)
    table = load_table(table_path, config)
    sent = [msgspec.json.decode(m.data, type=AdnActuator) for m in recording.messages
            if m.topic.endswith("/cpfc/actuator")]
    assert [(a.t_send_ns, a.entry) for a in sent] == [(0, 0), (8_200_000_000, 1)]
    assert len(sent[1].ders) == len(sent[0].ders) - 1
    omega = np.geomspace(1e-3, 1e2, 40)
    for a in sent:
        entry = table.lookup(a.ders)
        assert np.array_equal(announced("x", a).closed_loop(omega),
                              lower_adn(config, entry, "x").closed_loop(omega))


# --- 7b: same config and seed, same messages ------------------------------------------------------


def test_two_sim_runs_with_the_same_seed_send_identical_messages(tmp_path: Path) -> None:
    """... whether the agents are forked from the fork server (the default) or started as
    programs (``runtime.agent_start: exec``)."""
    links = {"cpfc_to_der": {"jitter_s": 0.02, "loss": 0.05},
             "der_to_availability": {"jitter_s": 0.05, "loss": 0.1}}
    config, table = write_case(tmp_path, "noisy", runtime={"links": links})
    as_programs = write_case(tmp_path, "noisy-exec",
                             runtime={"links": links, "agent_start": "exec"})
    first_run, first, _ = run_up(tmp_path, config, table, "first")
    assert "fork server" not in first_run.stderr        # forked, not started as programs
    _, second, _ = run_up(tmp_path, *as_programs, "second")
    assert data_messages(first) == data_messages(second)
    _, other, summary = run_up(tmp_path, config, table, "other", "--seed", "8")
    assert data_messages(other) != data_messages(first)
    assert summary["extra"]["lost_on_links"] > 0


# --- realtime ------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_realtime_run_at_speed_1_gives_the_sim_runs_figures(reference_run) -> None:
    """Messages carry their scheduled times, so a realtime run processes the same inputs at the
    same times as the sim run unless a message arrives after its delivery time. With no late
    arrival the figures are equal; with some (a loaded machine), each late message acts as a
    longer delay once, which moves a crossing of P_IP by at most the largest delivery error plus
    one PI period, twice for a rise time (two crossings); the derivation is in
    docs/runtime.md#realtime-the-scaled-wall-clock."""
    tmp_path, config, table, _, _, sim = reference_run          # the sim run of the same case
    result, recording, real = run_up(tmp_path, config, table, "rt", "--clock", "realtime",
                                     "--speed", "1")
    assert recording.run["clock"] == "realtime"
    timing = real["realtime"]
    assert {e["link"] for e in timing["links"]} >= {"cpfc_to_der", "measurement_to_cpfc",
                                                   "physical", "timer"}
    assert "delivery error per link" in result.stdout + result.stderr
    (a,), (b,) = sim["steps"], real["steps"]
    names = ("rise_time_s", "settling_time_s", "overshoot_pct")
    if timing["late_arrivals"] == 0:
        for name in names:
            assert b["figures"][name] == pytest.approx(a["figures"][name], rel=1e-9, abs=1e-9)
    else:
        pi_period = load_config(config).runtime.pi_period_s
        worst_s = max(e["max_ms"] for e in timing["links"]) / 1e3
        bound = 2 * (worst_s + pi_period)
        for name in ("rise_time_s", "settling_time_s"):
            assert abs(b["figures"][name] - a["figures"][name]) <= bound, (name, a, b, timing)
    assert abs(b["steady_error_w"] - a["steady_error_w"]) < 0.01 * abs(a["step_w"])
    assert real["speed_factor"] == pytest.approx(1.0, rel=0.1)


@pytest.mark.slow
def test_strict_stops_a_run_the_machine_cannot_keep_in_real_time(tmp_path: Path) -> None:
    # a tolerance of 1 ns: no machine keeps that, so the first overrun stops the run
    config, table = write_case(tmp_path, "strict", runtime={"realtime_tolerance_s": 1e-9})
    out = tmp_path / "strict.mcap"
    result = subprocess.run(up_argv(config, table, out, "--clock", "realtime", "--speed", "1",
                                    "--strict"), cwd=tmp_path, capture_output=True, text=True,
                            timeout=RUN_TIMEOUT_S, check=False)
    assert result.returncode == 3, result.stderr
    assert "not real time" in result.stderr and "Traceback" not in result.stderr
    from adnmesh.recording import read_recording
    recording = read_recording(out)                     # finished and readable
    assert any("/event/" in m.topic and b'"overrun"' in m.data
               for m in recording.messages)


def test_strict_needs_the_realtime_clock(capsys) -> None:
    from adnmesh.cli import main

    assert main(["up", str(CASE), "--strict"]) == 2
    assert "--strict needs --clock realtime" in capsys.readouterr().err


# --- 7d: nothing is left behind -------------------------------------------------------------------


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupt_leaves_no_process(tmp_path: Path, signum: int, code: int) -> None:
    proc, agents, config = start_long_run(tmp_path, f"sig{signum}")
    proc.send_signal(signum)
    returncode, err = finish(proc, agents, config)
    assert returncode == code, err
    assert "run stopped: SIG" in err


# --- resources: a disk that fills while the run goes ----------------------------------------------


def test_a_disk_that_fills_stops_the_run_with_one_line_and_writes_the_summary(
        tmp_path: Path) -> None:
    """Issue 39: the recording's disk fills (the writer's test hook: ENOSPC after 16 kB, as a
    full disk does). Before, the run went on recording nothing and ended in a traceback, with
    no summary and no summary JSON. Now it stops at once with exit code 1 and one line that
    says why, prints its summary and writes the JSON (on another disk here), and the file keeps
    what its last flush wrote, which ``adnmesh inspect`` recovers."""
    import os

    from adnmesh.recording import read_recording
    from adnmesh.recording.writer import DISK_FULL_ENV
    from up_runs import processes_mentioning

    config, table = write_case(tmp_path, "full", scenario={"duration_s": 3600})
    out, summary_path = tmp_path / "full.mcap", tmp_path / "full.summary.json"
    env = {**os.environ, DISK_FULL_ENV: "16384"}
    result = subprocess.run(up_argv(config, table, out, "--summary-json", str(summary_path)),
                            cwd=tmp_path, capture_output=True, text=True, env=env,
                            timeout=RUN_TIMEOUT_S, check=False)
    err = result.stderr
    assert result.returncode == 1, err
    assert "Traceback" not in err and "Error" not in err, err
    failed = [line for line in err.splitlines() if "recording failed" in line]
    assert failed == [f"adnmesh up: run stopped: recording failed: {out}: No space left on "
                      "device"], err
    incomplete = [line for line in err.splitlines() if "INCOMPLETE" in line]
    assert len(incomplete) == 1, err
    kept = int(incomplete[0].split("it keeps the ")[1].split()[0])
    assert "P_ref steps" in result.stdout and "ended recording failed" in result.stdout
    summary = json.loads(summary_path.read_text())
    assert summary["extra"]["ended"] == f"recording failed: {out}: No space left on device"
    assert summary["extra"]["messages_on_disk"] == kept
    assert 0 < summary["sim_time_s"] < 3600
    assert out.stat().st_size <= 16384
    recording = read_recording(out)           # whole chunks only: nothing unfinished at its end
    assert not recording.complete and recording.dropped_bytes == 0
    assert len(recording.messages) == kept
    recovered = tmp_path / "recovered.mcap"
    inspect = subprocess.run([*up_argv(config, table, out)[:3], "inspect", str(out),
                              "--recover-to", str(recovered)], capture_output=True, text=True,
                             timeout=RUN_TIMEOUT_S, check=False)
    assert inspect.returncode == 0, inspect.stderr
    assert f"recovered {kept} messages" in inspect.stdout
    assert read_recording(recovered).complete
    assert processes_mentioning(str(config)) == []


def test_a_summary_json_that_cannot_be_written_is_one_line(tmp_path: Path, monkeypatch,
                                                           capsys) -> None:
    """The summary is printed first; a JSON the disk refuses is one line, no half file."""
    import argparse

    from adnmesh.commands import up_summary
    from adnmesh.runtime.launcher import UpResult

    def disk_full(path, content, mode=0o644):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("adnmesh.files.write_atomic", disk_full)
    args = argparse.Namespace(summary_json=str(tmp_path / "s.json"), clock="sim", secure=False,
                              certs=None, speed=None)
    line = up_summary.print_and_write_summary(args, load_config(CASE), "run", UpResult(end_ns=12 * 10**9,
                                                                      reached_ns=12 * 10**9))
    assert line == (f"--summary-json {tmp_path / 's.json'}: not written (No space left on "
                    "device); the summary above is the whole of it")
    assert "P_ref steps" in capsys.readouterr().out
    assert not (tmp_path / "s.json").exists()


# --- user errors ---------------------------------------------------------------------------------


def test_up_with_a_table_that_is_not_there_says_to_tune(tmp_path: Path, capsys) -> None:
    from adnmesh.cli import main

    config, _ = write_case(tmp_path, "untuned")
    code = main(["up", str(config), "--table", str(tmp_path / "missing.json")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "run 'adnmesh tune" in err


def test_speed_needs_the_realtime_clock(capsys) -> None:
    from adnmesh.cli import main

    assert main(["up", str(CASE), "--speed", "2"]) == 2
    assert capsys.readouterr().err == "adnmesh: error: --speed needs --clock realtime\n"


def test_an_agent_closes_its_session_only_after_up_has_its_goodbye() -> None:
    # `up` played by the test: a router session with the liveliness token of `up`; the agent
    # (the availability monitor's node) is served on a client session in this main thread
    import threading

    import zenoh

    from adnmesh.control.availability_monitor import AvailabilityMonitor
    from adnmesh.runtime.bus import free_port, router_config
    from adnmesh.runtime.process import AgentProcess
    from adnmesh.sim.node import Node
    from adnmesh.wire.keys import Keys
    from payloads import payload

    config = load_config(CASE)
    keys = Keys(config.grid)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = zenoh.Config()
    client.insert_json5("mode", '"client"')
    client.insert_json5("connect/endpoints", json.dumps([endpoint]))
    client.insert_json5("scouting/multicast/enabled", "false")
    reported, said_bye, returned = threading.Event(), threading.Event(), threading.Event()
    closed_early: list[bool] = []

    with zenoh.open(router_config([endpoint])) as router:
        token = router.liveliness().declare_token(keys.liveliness("up"))
        subs = [router.declare_subscriber(keys.of("clock_report", "availability"),
                                          lambda s: reported.set()),
                router.declare_subscriber(keys.of("agent_bye", "availability"),
                                          lambda s: said_bye.set())]

        def play_up() -> None:
            assert reported.wait(30)
            router.put(keys.of("clock_stop"), payload(keys.of("clock_stop"), {"reason": "test"}))
            assert said_bye.wait(30)
            # the goodbye is in; the agent must still hold its session until up withdraws
            closed_early.append(returned.wait(0.5))
            token.undeclare()

        player = threading.Thread(target=play_up, daemon=True)
        player.start()
        node = Node.for_config(AvailabilityMonitor(config), config)
        t0 = time.monotonic()
        with zenoh.open(client) as session:
            assert AgentProcess(session, node, config.grid).serve() == 0
        returned.set()
        player.join(10)
        for sub in subs:
            sub.undeclare()
    assert closed_early == [False]
    assert time.monotonic() - t0 < 30


def test_rt_priority_needs_the_realtime_clock(capsys) -> None:
    from adnmesh.cli import main

    assert main(["up", str(CASE), "--rt-priority", "fifo"]) == 2
    assert capsys.readouterr().err == "adnmesh: error: --rt-priority needs --clock realtime\n"


_AGENT = """
import sys
import zenoh
from adnmesh.config import load_config
from adnmesh.control.availability_monitor import AvailabilityMonitor
from adnmesh.runtime.bus import client_config
from adnmesh.runtime.process import AgentProcess
from adnmesh.sim.node import Node

class Broken(AvailabilityMonitor):
    def on_timer(self, t_ns):
        if t_ns >= 10**9:
            raise ZeroDivisionError("a bug in the agent's own code")
        return super().on_timer(t_ns)

kind = Broken if sys.argv[3] == "broken" else AvailabilityMonitor
config = load_config(sys.argv[1])
with zenoh.open(client_config([sys.argv[2]])) as session:
    AgentProcess(session, Node.for_config(kind(config), config), config.grid).serve()
"""


def test_an_agent_whose_code_raises_in_a_window_ends_at_once_with_one_line() -> None:
    # Zenoh prints and swallows an exception in a callback: the agent would live on without
    # reporting its window, and up's sim clock would wait for it until the stall timeout.
    # up is played by the test: its token, the start, a first grant to 1 s, before the
    # failing timer (its report says the agent runs on the sim clock), then a grant beyond,
    # which the agent processes in the Zenoh callback that brings it.
    import queue
    import sys

    import zenoh

    from adnmesh.runtime.bus import free_port, router_config
    from adnmesh.runtime.children import EXIT_INTERNAL_ERROR
    from adnmesh.wire.envelope import decode, split_frame
    from adnmesh.wire.keys import Keys
    from payloads import payload

    config = load_config(CASE)
    keys = Keys(config.grid)
    report_key = keys.of("clock_report", "availability")
    grant_key = keys.of("clock_grant", "availability")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    reports: queue.Queue = queue.Queue()

    def on_report(sample) -> None:
        # a report comes on its own key, or rides the window's last data sample
        if str(sample.key_expr) == report_key:
            for part in split_frame(sample.payload.to_bytes()):
                reports.put(decode(report_key, part))
        elif sample.attachment is not None:
            reports.put(decode(report_key, sample.attachment.to_bytes()))

    def report_granted(until_ns: int):
        while True:
            report = reports.get(timeout=60)
            if report.granted_ns == until_ns:
                return report

    with zenoh.open(router_config([endpoint])) as router:
        token = router.liveliness().declare_token(keys.liveliness("up"))
        sub = router.declare_subscriber(keys.all, on_report)
        agent = subprocess.Popen([sys.executable, "-c", _AGENT, str(CASE), endpoint, "broken"],
                                 stderr=subprocess.PIPE, text=True)
        try:
            report_granted(0)                                       # ready
            start = keys.of("clock_start")
            router.put(start, payload(start, {"clock": "sim", "epoch_ns": 0, "speed": 1.0,
                                              "end_ns": 10**10, "seed": 1}))
            router.put(grant_key, payload(grant_key, {"until_ns": 10**9, "expect": 0}))
            assert report_granted(10**9).next_ns >= 10**9
            router.put(grant_key, payload(grant_key, {"until_ns": 10**10, "expect": 0},
                                          seq=1))
            code = agent.wait(timeout=60)
            err = agent.stderr.read()
        finally:
            if agent.poll() is None:
                agent.kill()
                agent.wait()
            sub.undeclare()
            token.undeclare()
    assert code == EXIT_INTERNAL_ERROR
    assert err.splitlines() == [
        "adnmesh agent availability: internal error: ZeroDivisionError: a bug in the agent's "
        "own code (<string>:13); the agent stops"]


def test_an_agent_that_lost_the_router_says_so_when_up_is_back_in_sight() -> None:
    # up is played by the test; its router goes away and a new one takes the same endpoint
    import queue
    import sys
    import threading

    import zenoh

    from adnmesh.runtime.bus import free_port, router_config
    from adnmesh.wire.keys import Keys

    config = load_config(CASE)
    keys = Keys(config.grid)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    reported = threading.Event()
    router = zenoh.open(router_config([endpoint]))
    token = router.liveliness().declare_token(keys.liveliness("up"))
    sub = router.declare_subscriber(keys.of("clock_report", "availability"),
                                    lambda s: reported.set())
    agent = subprocess.Popen([sys.executable, "-c", _AGENT, str(CASE), endpoint, "plain"],
                             stderr=subprocess.PIPE, text=True)
    try:
        assert reported.wait(60)
        sub.undeclare()
        token.undeclare()
        router.close()
        router = zenoh.open(router_config([endpoint]))     # the client reconnects to it
        token = router.liveliness().declare_token(keys.liveliness("up"))
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: lines.put(agent.stderr.readline()), daemon=True).start()
        line = lines.get(timeout=60)
        assert line.startswith("adnmesh agent availability: adnmesh up back in sight after "), line
        assert line.endswith(" s (the session lost the router; what crossed the gap is lost)\n")
    finally:
        agent.kill()
        agent.wait()
        token.undeclare()
        router.close()


def test_agents_still_closing_after_their_goodbye_are_ended_and_that_is_no_problem(
        tmp_path: Path, monkeypatch, capsys) -> None:
    # Under load, 103 agents with every goodbye in had not exited in the 0.5 s left after the
    # goodbyes; up killed them and said "killed after the shutdown timeout" for all, beside
    # exit 0. Here no agent gets any time to exit: each is ended after its goodbye.
    from adnmesh.cli import main
    from adnmesh.recording import read_recording
    from adnmesh.runtime.children import AgentProcesses

    import gc
    import weakref

    from adnmesh.runtime import launcher

    monkeypatch.setattr(AgentProcesses, "wait_all", lambda self, timeout_s: None)
    launches = []
    born = launcher._Launch.__init__

    def remember(self, options) -> None:
        born(self, options)
        launches.append(weakref.ref(self))

    monkeypatch.setattr(launcher._Launch, "__init__", remember)
    config, table = write_case(tmp_path, "closing")
    out = tmp_path / "closing.mcap"
    frozen = gc.get_freeze_count()
    assert main(["up", str(config), "--table", str(table), "--out", str(out)]) == 0
    # nothing of the run is kept once it returned (issue 41: an in-process run grew the
    # process by ~280 MB each; the run's heap was frozen for the run and never thawed)
    gc.collect()
    assert gc.get_freeze_count() <= frozen
    assert [ref() for ref in launches] == [None]
    err = capsys.readouterr().err
    assert "killed after the shutdown timeout" not in err
    assert " s after the shutdown timeout were ended (their goodbyes, and everything before " \
           "them, are in)" in err
    assert read_recording(out).complete
