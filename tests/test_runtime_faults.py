"""Faults against real processes: ``adnmesh fault`` into a running ``up``, agents that die, a
bus full of junk, and ``up`` itself killed.

The runs use the small runtime case (two WTs, tests/up_runs.py), made long enough (scenario
``duration_s``) that there is time to act while they run; every wait is bounded.
"""

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

from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.recording import read_recording
from adnmesh.runtime.tap import REJECTED_RECORDS_KEPT
from adnmesh.runtime.window_times import ENV
from adnmesh.sim.local import _LocalRunner
from adnmesh.tuning.table import load_table
from adnmesh.wire.units import ns
from up_runs import (
    alive,
    children_of,
    data_messages,
    finish,
    process_name,
    processes_mentioning,
    run_up,
    start_long_run,
    up_argv,
    write_case,
)

pytestmark = pytest.mark.slow


def adnmesh_fault(recording: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "adnmesh", "fault", str(recording), *args],
                          capture_output=True, text=True, timeout=60, check=False)


def events(recording, kind: str | None = None) -> list[dict]:
    found = [json.loads(m.data) for m in recording.messages if "/event/" in m.topic]
    return [e for e in found if kind is None or e["kind"] == kind]


def local_run(config_path: Path, table_path: Path, faults) -> list[tuple[str, bytes]]:
    """The in-process run of the same config with ``faults`` (kind, at s, for s, target): its
    messages in :func:`up_runs.data_messages`' order (delivery time, key, seq)."""
    config = load_config(config_path)
    runner = _LocalRunner(config, GainSchedule(config, load_table(table_path, config),
                                               on_demand=False), ns(config.scenario.duration_s))
    for kind, at, duration, target in faults:
        runner.plan.add(kind, ns(at), None if duration is None else ns(duration), **target)
    grants = runner.start()
    while grants:
        grants.extend(runner.step(grants.popleft()))
    return sorted(runner.run.messages, key=lambda m: (json.loads(m[1])["t_deliver_ns"], m[0],
                                                      json.loads(m[1])["seq"]))


def agents_only(messages) -> list[tuple[str, bytes]]:
    """What the agents sent (``up``'s fault messages and events and the requests carry the
    wall-clock moment of the request)."""
    return [(k, p) for k, p in messages
            if not k.endswith(("/faults", "/event/up", "/control/fault"))]


def test_faults_injected_into_a_running_sim_run_take_effect_at_their_instant(
        tmp_path: Path) -> None:
    """`adnmesh fault` while the run goes: an outage of the CPFC -> DER link and a kill of
    the CPFC with a restart. Both take effect at the requested sim time, so the agents'
    messages are exactly those of the in-process run with the same faults."""
    proc, agents, config = start_long_run(tmp_path, "inject", scenario={"duration_s": 400})
    recording = tmp_path / "inject.mcap"
    outage = adnmesh_fault(recording, "link_outage", "cpfc_to_der", "--at", "300", "--for", "5")
    kill = adnmesh_fault(recording, "kill", "cpfc", "--at", "350", "--for", "3")
    refused = adnmesh_fault(recording, "kill", "grid", "--at", "360")
    returncode, err = finish(proc, agents, config)
    assert (outage.returncode, kill.returncode, refused.returncode) == (0, 0, 2), \
        outage.stdout + kill.stdout + refused.stderr + err
    assert "link_outage of cpfc_to_der from 300 s for 5 s" in outage.stdout
    assert "kill of cpfc at 350 s, restarted at 353 s" in kill.stdout
    assert "unknown agent 'grid'" in refused.stderr and refused.stdout == ""
    assert returncode == 0, err
    run = read_recording(recording)
    kinds = [(e["src"], e["kind"]) for e in events(run)]
    assert ("up", "killed") in kinds and ("up", "rejoined") in kinds
    assert ("der/SGen1", "watchdog_fallback") in kinds and ("cpfc", "resume") in kinds
    expected = local_run(config, tmp_path / "inject.table.json", [
        ("link_outage", 300, 5, {"link": "cpfc_to_der"}), ("kill", 350, 3, {"agent": "cpfc"})])
    assert agents_only(data_messages(run)) == agents_only(expected)


def test_a_dead_agent_does_not_end_the_run(tmp_path: Path) -> None:
    """A DER's process killed from outside: the run goes on to its end without it, prints
    its summary and says who was lost (exit code 1: an agent died unplanned). The death is a
    fault of the summary (kind ``lost``, from ``up``'s event on), detected by the measurement
    (the DER's state stopped: taken at its schedule) one watchdog timeout after its last
    state; ``inspect`` finds the same fault in the recording."""
    from adnmesh.commands.inspect import _summary, _SummaryMessages
    from adnmesh.results.series import read_run

    proc, agents, config = start_long_run(tmp_path, "victim", "--summary-json",
                                          str(tmp_path / "victim.json"),
                                          scenario={"duration_s": 120})
    victim = max(agents)
    os.kill(victim, signal.SIGKILL)
    returncode, err = finish(proc, agents, config)
    assert returncode == 1, err
    assert f"(pid {victim}) died (signal 9); the run goes on without it" in err
    assert "agent(s) lost during the run" in err
    run = read_recording(tmp_path / "victim.mcap")
    (lost,) = events(run, "agent_lost")
    last_p_ip = max(m.publish_time_ns for m in run.messages if m.topic.endswith("/p_ip"))
    assert last_p_ip == ns(120)                              # the run reached its end
    assert events(run, "unavailable")                        # the monitor noticed
    (silent,) = events(run, "der_silent")                    # and the measurement before
    assert silent["subject"] == lost["subject"]
    (fault,) = json.loads((tmp_path / "victim.json").read_text())["faults"]
    assert (fault["kind"], fault["target"], fault["end_s"]) == ("lost", lost["subject"], None)
    assert fault["start_s"] == lost["t_send_ns"] * 1e-9
    assert fault["detected_by"] == "measurement"
    assert fault["detected_s"] == silent["t_send_ns"] * 1e-9
    assert 0 < fault["detection_delay_s"] <= 1.5
    found, messages = read_run(tmp_path / "victim.mcap", also=_SummaryMessages)
    inspected = _summary(found.recording, messages, 5.0).to_json()["faults"]
    assert inspected == [fault]


def test_the_steps_a_dead_cpfc_never_sent_are_said(tmp_path: Path) -> None:
    """The CPFC's process killed from outside right after the start: the scenario's steps
    (1 s, 60 s, 100 s here) are never sent (the CPFC sends P_ref). Before, they vanished from
    the summary without a word; now every one is listed as not executed because the CPFC was
    lost, and the death is a fault detected by the DERs' watchdogs."""
    scenario = {"duration_s": 120, "p_ref_steps": [{"t_s": 1, "delta_w": 1.0e6},
                                                   {"t_s": 60, "delta_w": -1.0e6},
                                                   {"t_s": 100, "delta_w": 1.0e6}]}
    proc, agents, config = start_long_run(tmp_path, "headless", "--summary-json",
                                          str(tmp_path / "headless.json"), scenario=scenario)
    (cpfc,) = [pid for pid in agents if process_name(pid) == "cpfc"]
    os.kill(cpfc, signal.SIGKILL)
    returncode, err = finish(proc, agents, config)
    assert returncode == 1, err
    summary = json.loads((tmp_path / "headless.json").read_text())
    planned = summary["scenario_steps"]
    assert [s["t_s"] for s in planned] == [1, 60, 100]
    executed = {s["t_s"] for s in summary["steps"]}
    for step in planned:
        if step["t_s"] in executed:
            assert step["status"] == "executed"
        else:
            assert step["status"] == "not executed", step
            assert step["reason"].startswith("the CPFC, which sends P_ref, was lost at ")
    assert [s["status"] for s in planned][1:] == ["not executed"] * 2
    (fault,) = summary["faults"]
    assert (fault["kind"], fault["target"]) == ("lost", "cpfc")
    assert fault["detected_by"].startswith("der/")
    inspected = subprocess.run([sys.executable, "-m", "adnmesh", "inspect",
                                str(tmp_path / "headless.mcap"), "--json"], capture_output=True,
                               text=True, timeout=120, check=False)
    assert json.loads(inspected.stdout)["figures"]["scenario_steps"] == planned


def test_up_killed_leaves_no_agent_behind(tmp_path: Path) -> None:
    proc, agents, config = start_long_run(tmp_path, "orphans")
    proc.kill()
    proc.wait(timeout=10)
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline and any(alive(pid) for pid in agents):
        time.sleep(0.05)
    survivors = [pid for pid in agents if alive(pid)]
    for pid in survivors:               # cleanup by PID before failing
        os.kill(pid, signal.SIGKILL)
    assert survivors == [], "agents outlived a SIGKILLed up by more than 1 s"
    assert processes_mentioning(str(config)) == []


# --- a bus that junk cannot disturb ---------------------------------------------------------------


def junk_payloads(key: str, sender: str, impostor: str, n: int) -> list[bytes]:
    """``n`` payloads that are no genuine message on ``key``: malformed JSON, wrong types,
    missing fields, NaN/inf, out-of-range and 40-digit integers, unknown DER ids, stale and
    future timestamps (from the wrong sender, or delivered before sent), 1 MB payloads, deep
    nesting, well-formed envelopes with a wrong ``src``."""
    from adnmesh.wire.keys import route
    from payloads import BODIES

    kind = route(key).type
    head = {"v": 1, "type": kind, "seq": 7, "t_send_ns": 5_000_000_000,
            "t_deliver_ns": 5_100_000_000}
    valid = {**head, **BODIES[kind]}
    shapes = [
        lambda i: b'{"v":1,"type":' + str(i).encode(),                          # malformed
        lambda i: b"\xff\xfe" + bytes([i % 256]),                                 # not UTF-8
        lambda i: json.dumps({**head, "src": sender, "seq": "seven"}).encode(),   # wrong type
        lambda i: json.dumps({"v": 1, "type": kind, "src": sender}).encode(),     # missing
        lambda i: (json.dumps({**head, "src": sender})[:-1] + ',"p_w":NaN}').encode(),
        lambda i: (json.dumps({**head, "src": sender})[:-1] + ',"p_w":1e999}').encode(),
        lambda i: json.dumps({**head, "src": sender, "seq": 10 ** 40 + i}).encode(),
        lambda i: json.dumps({**head, "src": sender, "t_send_ns": -i}).encode(),
        lambda i: json.dumps({**head, "src": "availability", "type": "si",
                              "si": {f"Bogus{i}": True}}).encode(),               # unknown DER
        lambda i: json.dumps({**valid, "src": impostor, "t_send_ns": i,
                              "t_deliver_ns": i}).encode(),                       # stale
        lambda i: json.dumps({**valid, "src": impostor, "seq": 10 ** 18 + i,
                              "t_send_ns": 10 ** 18, "t_deliver_ns": 10 ** 18}).encode(),
        lambda i: json.dumps({**valid, "src": sender, "t_send_ns": 10 ** 12,
                              "t_deliver_ns": 10 ** 9}).encode(),                 # delivered early
        lambda i: b"[" * 50_000 + b"]" * 50_000,                                  # deep
        lambda i: json.dumps({**valid, "src": impostor}).encode(),                # wrong src
    ]
    out = [shapes[i % len(shapes)](i) for i in range(n)]
    out[::250] = [b'{"v":1,"x":"' + b"x" * 1_000_000 + b'"}'] * len(out[::250])   # 1 MB
    return out


def publish_junk(endpoint: str, keys: list[str], per_key: int, done: threading.Event,
                 counted: list[int]) -> None:
    """Publish the junk, then a harmless fault request (a delay beyond the run's end) on the
    same session and wait for up's answer: samples of one session arrive in order, so once
    the answer is in, up has taken every piece of junk."""
    import zenoh

    from adnmesh.runtime.bus import client_config
    from adnmesh.wire.envelope import encode
    from adnmesh.wire.keys import Keys, route
    from adnmesh.wire.messages import FaultRequest

    answered = threading.Event()
    with zenoh.open(client_config([endpoint])) as session:
        grid = keys[0].split("/")[1]
        answer = session.declare_subscriber(Keys(grid).of("event", "up"), lambda s: (
            b"sentinel" in s.payload.to_bytes() and answered.set()))
        for key in keys:
            sender = route(key).sender
            impostor = "der/SGen2" if sender != "der/SGen2" else "der/SGen1"
            publisher = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
            for payload in junk_payloads(key, sender, impostor, per_key):
                publisher.put(payload)
                counted[0] += 1
            publisher.undeclare()
        session.put(Keys(grid).of("fault_request"), encode(FaultRequest(
            1, "fault_request", "operator", 1, 0, 0, request_id="sentinel", kind="link_delay",
            at_ns=10 ** 15, for_ns=1, link="cpfc_to_der", delay_ns=0)))
        answered.wait(60)
        answer.undeclare()
    if answered.is_set():
        done.set()


def test_junk_on_every_subscribed_key_changes_nothing(tmp_path: Path) -> None:
    """1,000 junk payloads on every key an agent subscribes to, while the run goes: no agent
    or recorder error, every payload rejected and counted, and the control result identical
    to the undisturbed run's (sim clock, same seed; the in-process run, which the fault tests
    show equal to an undisturbed ``up``)."""
    from adnmesh.sim.topology import Topology

    changes = {"scenario": {"duration_s": 400, "p_ref_steps": [{"t_s": 40, "delta_w": 1.0e6}],
                            "availability": [{"t_s": 250, "available": False,
                                              "ders": ["SGen2"]}]}}
    config, table = write_case(tmp_path, "junk", **changes)
    topology = Topology.from_config(load_config(config))
    keys = sorted({k for subs in topology.subscriptions.values() for k in subs}
                  | {topology.keys.of("clock_grant", a) for a in topology.agents}
                  | {topology.keys.of("clock_kill", a) for a in topology.agents}
                  | {topology.keys.of(kind)
                     for kind in ("clock_start", "clock_stop", "fault_request")})
    proc, agents, _ = start_long_run(tmp_path, "junky", "--summary-json",
                                     str(tmp_path / "junky.json"), **changes)
    endpoint = json.loads((tmp_path / "junky.run.json").read_text())["endpoint"]
    done, counted = threading.Event(), [0]
    sender = threading.Thread(target=publish_junk, args=(endpoint, keys, 1000, done, counted),
                              daemon=True)
    sender.start()
    done.wait(timeout=120)
    still_running = proc.poll() is None
    returncode, err = finish(proc, agents, config)
    assert done.is_set() and still_running, "the junk took longer than the run"
    assert returncode == 0, err
    assert "Traceback" not in err and "error" not in err.lower()
    run = read_recording(tmp_path / "junky.mcap")
    assert agents_only(data_messages(run)) == agents_only(local_run(config, table, []))
    rejected = [m for m in run.messages if m.topic.endswith("/rejected")]
    assert counted[0] == 1000 * len(keys)
    assert len(rejected) == REJECTED_RECORDS_KEPT       # the rest counted, not recorded
    summary = json.loads((tmp_path / "junky.json").read_text())
    extra = summary["extra"]
    assert extra["rejected_by_recorder"] == counted[0]
    assert extra["rejected_by_agents"] > 0
    reasons = {json.loads(m.data)["reason"] for m in rejected}
    print(f"junk: {counted[0]} payloads on {len(keys)} keys; rejected by the recorder "
          f"{extra['rejected_by_recorder']}, by the agents {extra['rejected_by_agents']}; "
          f"reasons {sorted(reasons)}")
    assert {"malformed", "invalid", "wrong_sender", "unknown_der", "too_large",
            "time_order"} <= reasons


def test_config_faults_with_restarts_give_the_in_process_run_exactly(tmp_path: Path) -> None:
    """Every fault kind from the config, two kills with restarts among them: the recording
    holds exactly the in-process run's messages, ``up``'s fault messages and events included."""
    from adnmesh.sim.local import run_local

    faults = [
        {"kind": "link_loss", "link": "cpfc_to_der", "probability": 0.3, "t_s": 1.5,
         "duration_s": 1},
        {"kind": "link_delay", "link": "measurement_to_cpfc", "delay_s": 0.05, "t_s": 2.5,
         "duration_s": 1},
        {"kind": "der_offline", "der": "SGen2", "t_s": 3, "duration_s": 2},
        {"kind": "kill", "agent": "der/SGen1", "t_s": 5.5, "restart_after_s": 0.7},
        {"kind": "kill", "agent": "cpfc", "t_s": 7, "restart_after_s": 1.5},
        {"kind": "link_outage", "link": "availability_to_cpfc", "t_s": 9, "duration_s": 0.5},
        {"kind": "ict_outage", "t_s": 10, "duration_s": 0.3},
    ]
    config, table = write_case(tmp_path, "faulty", runtime={"faults": faults})
    (tmp_path / "windows").mkdir()                 # the stage timeline on: it changes nothing
    result, recording, summary = run_up(tmp_path, config, table, "faulty",
                                        env={ENV: str(tmp_path / "windows")})
    loaded = load_config(config)
    # the faults take the run to a set of DERs the test table lacks: tuned on demand, as the
    # CPFC process does
    local = run_local(loaded, GainSchedule(loaded, load_table(table, loaded)))
    expected = sorted(local.messages, key=lambda m: (json.loads(m[1])["t_deliver_ns"], m[0],
                                                     json.loads(m[1])["seq"]))
    assert data_messages(recording) == expected
    kinds = [(e["src"], e["kind"]) for e in events(recording)]
    assert kinds.count(("up", "fault_injected")) == len(faults)
    assert kinds.count(("up", "killed")) == 2 and kinds.count(("up", "rejoined")) == 2
    noted = [json.loads(p.read_text())["agent"] for p in (tmp_path / "windows").glob("*.json")]
    assert noted.count("der/SGen1") == 2 and noted.count("cpfc") == 2   # killed, restarted
    assert noted.count("measurement") == 1                               # neither
    assert "counts not verified" in result.stderr          # the killed processes' keys


def _step_after(recording, summary, t_s: float) -> tuple[dict, float]:
    """The summary's step at ``t_s`` and the residual deviation ``P_IP - P_ref`` just before
    it, W."""
    (step,) = [s for s in summary["steps"] if s["t_s"] == pytest.approx(t_s)]
    samples = [json.loads(m.data) for m in recording.messages
               if m.topic.endswith("/measurement/p_ip")]
    before = [s for s in samples if s["t_send_ns"] < ns(t_s)][-1]
    return step, before["p_ip_w"] - (step["p_ref_w"] - step["step_w"])


def test_an_ict_outage_of_any_length_leaves_no_wind_up(tmp_path: Path) -> None:
    """The opening case of the fault issue: an outage of cpfc_to_der, then a step of P_ref —
    here a short (2 s) and a long (20 s) outage, each before its own step. The DERs fall back
    to their schedules after the watchdog time, the CPFC learns it from their
    acknowledgements, undoes the samples the fault disturbed and switches bumplessly; when the
    outage ends they follow again. Bound: once P_IP is back near P_ref the loop is at a steady
    state of the same operating point, so the step from there is the undisturbed step plus the
    response to the residual deviation r at the step instant; by superposition the overshoot
    can exceed the undisturbed one by at most 100 |r| / |step| %."""
    scenario = {"duration_s": 80, "p_ref_steps": [{"t_s": 20, "delta_w": 1.0e6},
                                                  {"t_s": 70, "delta_w": -1.0e6}],
                "availability": []}
    config, table = write_case(tmp_path, "clean", scenario=scenario)
    _, clean_run, clean = run_up(tmp_path, config, table, "clean")
    faults = [{"kind": "link_outage", "link": "cpfc_to_der", "t_s": 5, "duration_s": 2},
              {"kind": "link_outage", "link": "cpfc_to_der", "t_s": 30, "duration_s": 20}]
    config, table = write_case(tmp_path, "outage", scenario=scenario,
                               runtime={"faults": faults})
    _, faulty_run, faulty = run_up(tmp_path, config, table, "outage")
    fallbacks = [e["t_send_ns"] * 1e-9
                 for e in events(faulty_run, "watchdog_fallback")]
    assert any(5 < t < 7 for t in fallbacks) and any(30 < t < 50 for t in fallbacks)
    limit = load_config(config).constraints.overshoot_max_pct
    for t_step in (20.0, 70.0):
        step, residual = _step_after(faulty_run, faulty, t_step)
        reference, _ = _step_after(clean_run, clean, t_step)
        bound = 100 * abs(residual) / abs(step["step_w"])
        assert reference["figures"]["overshoot_pct"] < limit
        assert step["figures"]["overshoot_pct"] <= reference["figures"]["overshoot_pct"] + \
            bound + 1e-6, (step, residual)
        assert step["figures"]["overshoot_pct"] < limit + bound
        assert abs(step["figures"]["rise_time_s"] - reference["figures"]["rise_time_s"]) < 0.05
