"""The secure profile and agents on other hosts, with real processes: a rogue session against a
running secure system achieves nothing; the same attacks against the open profile do what
docs/deployment.md says; two linked routers record what one router records; a missing external
agent is named. Every run is the small runtime case (tests/up_runs.py) in its own temporary directory,
every wait is bounded, every process started here is ended by PID.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.recording import read_recording
from adnmesh.cli import main as adnmesh_main
from adnmesh.runtime.bus import free_port
from adnmesh.runtime.certificates import issue
from adnmesh.runtime.identity import identities
from adnmesh.sim.local import run_local
from adnmesh.sim.topology import Topology
from adnmesh.tuning.table import load_table
from adnmesh.wire.units import ns
from payloads import payload
from rogue import attack, forged_attacks, junk_on_own_keys, rogue_config
from up_runs import (
    REPO,
    data_messages,
    end_all,
    finish,
    processes_mentioning,
    start_long_run,
    up_argv,
    wait_for_line,
    write_case,
)

GRID = "runtime-test"
AT_S = 150.0                 # when the forged messages claim to be delivered, s of sim time
CHANGES = {"scenario": {"duration_s": 200, "p_ref_steps": [{"t_s": 40, "delta_w": 1.0e6}],
                        "availability": [{"t_s": 90, "available": False, "ders": ["SGen2"]}]},
           # a fault from the config: up's faults reach the agents through the access control
           "runtime": {"faults": [{"kind": "link_outage", "link": "cpfc_to_der", "t_s": 60,
                                   "duration_s": 5}]}}


def agents_only(messages) -> list[tuple[str, bytes]]:
    """The agents' messages (``up``'s events name wall-clock moments of fault requests)."""
    return [(k, p) for k, p in messages
            if not k.endswith(("/faults", "/event/up", "/control/fault"))]


@dataclass
class Attacked:
    """The one secure run (one router) of this module, attacked while it ran."""

    tmp: Path
    config: Path
    table: Path
    expected: list          # the in-process run's messages, in recording order
    refused: dict           # what the rogue could not connect with -> refused as expected
    still_running: bool     # the run was still going when the attack was over
    returncode: int
    err: str                # up's stderr
    operator: int           # exit code of the operator's `adnmesh fault`
    operator_out: str
    report: object          # rogue.RogueReport
    sent: int               # attempts the rogue made through its session
    junk: list              # its junk on the DER's own keys


@pytest.fixture(scope="module")
def attacked(tmp_path_factory) -> Attacked:
    """The case, its certificates, the in-process run of it, and its run in the secure profile
    with a rogue session attacking it: without a certificate, with one of another CA, and with
    a DER's certificate (forged messages of every kind, junk on the DER's own keys, a wide
    subscription, ``up``'s liveliness token); the operator requests a fault meanwhile. One run
    for every test here that needs a running secure system (each run costs tens of seconds)."""
    tmp = tmp_path_factory.mktemp("secure")
    config, table = write_case(tmp, "case", **CHANGES)
    loaded = load_config(config)
    issue(tmp / "certs", [*identities(loaded), "router/site"])
    issue(tmp / "other-ca", identities(loaded))      # a CA of another system
    local = run_local(loaded, GainSchedule(loaded, load_table(table, loaded), on_demand=False))
    expected = sorted(local.messages, key=lambda m: (json.loads(m[1])["t_deliver_ns"], m[0],
                                                     json.loads(m[1])["seq"]))
    certs = tmp / "certs"
    proc, agents, run_config = start_long_run(
        tmp, "attacked", "--secure", "--certs", str(certs), "--summary-json",
        str(tmp / "attacked.json"), **CHANGES)
    try:
        endpoint = json.loads((tmp / "attacked.run.json").read_text())["endpoint"]
        refused = {}
        for what, certs_dir, ep in (("no certificate", None, endpoint.replace("tls/", "tcp/")),
                                    ("another CA", tmp / "other-ca", endpoint)):
            try:
                attack(rogue_config(ep, certs_dir, "der/SGen1" if certs_dir else None), [],
                       GRID)
                refused[what] = False
            except Exception as exc:   # zenoh.ZError: the handshake failed
                refused[what] = "Unable to connect" in str(exc)
        forged = forged_attacks(GRID, at_ns=int(AT_S * 1e9))
        junk = junk_on_own_keys(GRID, "SGen1", 25)
        report = attack(rogue_config(endpoint, certs, "der/SGen1"), forged + junk, GRID,
                        listen_to=[f"adn/{GRID}/**", f"adn/{GRID}/measurement/p_ip"],
                        up_token=True)
        # the operator may ask: a fault after the end of the run, answered by up with a
        # refusal (it would change nothing), so the request and its answer pass the router
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            operator = adnmesh_main(["fault", str(tmp / "attacked.mcap"), "ict_outage",
                                     "--at", "5000"])
    finally:      # also if an attack failed: up ends (bounded), every process checked by PID
        still_running = proc.poll() is None
        returncode, err = finish(proc, agents, run_config)
    return Attacked(tmp, config, table, expected, refused, still_running, returncode, err,
                    operator, out.getvalue(), report, len(forged) + len(junk) + 1, junk)


def test_the_secure_run_records_what_the_in_process_run_computes(attacked, tmp_path) -> None:
    """The run of the secure profile completes with exactly the in-process run's messages
    (the rogue session's attempts changed nothing; the config's fault took effect)."""
    assert attacked.still_running, "the run ended before the attack was over"
    assert attacked.returncode == 0, attacked.err
    run = read_recording(attacked.tmp / "attacked.mcap")
    assert run.run["profile"] == "secure (mutual TLS, access control)"
    assert agents_only(data_messages(run)) == agents_only(attacked.expected)
    # the config's fault changes what the agents send: up's faults reached them
    config, table = write_case(tmp_path, "unfaulted", scenario=CHANGES["scenario"])
    loaded = load_config(config)
    unfaulted = run_local(loaded, GainSchedule(loaded, load_table(table, loaded),
                                               on_demand=False))
    assert agents_only(unfaulted.messages) != agents_only(attacked.expected)


def test_a_rogue_session_against_a_running_secure_system_achieves_nothing(attacked) -> None:
    """Without a certificate or with one of another CA it cannot connect; with a DER's
    certificate its forged correcting variable, another DER's state, measurement, SI, clock
    stop, clock grant, fault and fault request are refused by the router, its junk on the DER's
    own keys is rejected and counted by the receivers, its wide subscription gets nothing it may
    not have (the run's messages are the in-process run's: the test above), and ``up`` reports
    the second session with that certificate. The operator's fault request is answered."""
    assert attacked.refused == {"no certificate": True, "another CA": True}
    assert attacked.returncode == 0, attacked.err
    assert attacked.operator == 2 and attacked.operator_out.startswith(
        "adnmesh fault: fault request refused: ict_outage at 5000 s: after the end of the "
        "scenario"), attacked.operator_out
    assert len(attacked.report.sent) == attacked.sent
    assert attacked.report.received == {}, "the rogue received something"
    run = read_recording(attacked.tmp / "attacked.mcap")
    junk = attacked.junk
    rejected = [json.loads(m.data) for m in run.messages if m.topic.endswith("/rejected")]
    assert len(rejected) == len(junk)                       # only the junk got through
    assert {r["key"] for r in rejected} == {a.key for a in junk}
    summary = json.loads((attacked.tmp / "attacked.json").read_text())["extra"]
    assert summary["rejected_by_recorder"] == len(junk)
    receivers = Topology.from_config(load_config(attacked.config)).receivers   # each rejects
    assert summary["rejected_by_agents"] == sum(len(receivers[a.key]) for a in junk)
    assert summary["unexpected_sessions"] == 1
    assert "security: der/SGen1 had 2 links at once" in attacked.err


@pytest.mark.slow
def test_the_same_attacks_against_the_open_profile_are_taken_for_genuine(tmp_path) -> None:
    """Open profile: anyone may send with any identity. A forged measurement of 50 MW sent
    at 150 s is not recorded (the recorder knows the measurement was not granted that far:
    ``ahead_of_clock``) and shuts out none of the genuine ones; a forged clock stop makes every
    agent say goodbye: the run ends at once, every agent lost."""
    proc, agents, config = start_long_run(tmp_path, "open", "--summary-json",
                                          str(tmp_path / "open.json"), **CHANGES)
    endpoint = json.loads((tmp_path / "open.run.json").read_text())["endpoint"]
    forged = {a.name: a for a in forged_attacks(GRID, at_ns=int(AT_S * 1e9))}
    measurement, stop = forged["measurement P_IP = 50 MW"], forged["clock stop"]
    attack(rogue_config(endpoint, None, None), [measurement, stop], GRID)
    returncode, err = finish(proc, agents, config)
    assert returncode == 1, err
    assert "said goodbye before the end of the run" in err
    assert "agent(s) lost during the run: availability, cpfc, der/SGen1, der/SGen2, " \
        "measurement" in err
    ended = json.loads((tmp_path / "open.json").read_text())["extra"]["ended"]
    assert ended.startswith("stopped early: 5 agent(s) stopped at ")     # never "finished"
    assert "but up sent no stop" in ended
    assert f"run stopped: {ended}" in err
    run = read_recording(tmp_path / "open.mcap")
    assert not [m for m in run.messages if bytes(m.data) == measurement.payload]
    genuine = [m for m in data_messages(run) if m[1] != measurement.payload]
    last = max((json.loads(p)["t_send_ns"] for _, p in genuine), default=0)
    assert last < AT_S * 1e9 < ns(CHANGES["scenario"]["duration_s"])   # it stopped early
    reasons = [json.loads(m.data)["reason"] for m in run.messages if m.topic.endswith(
        "/rejected") and json.loads(m.data)["key"] == measurement.key]
    assert reasons == ["ahead_of_clock"]         # and no genuine P_IP taken for a replay


def start_split(tmp: Path, config: Path, table: Path, out: Path, *router_flags: str):
    """``up`` with its router (CPFC, one DER, the monitor) and a site router linked to it
    (``adnmesh router``) with the other DER and the measurement (``adnmesh agent``), secure
    profile; return (up's process, [site router, DER, measurement])."""
    certs = str(tmp / "certs")
    central, site = (f"tls/127.0.0.1:{free_port()}" for _ in range(2))
    up = subprocess.Popen(up_argv(config, table, out, "--secure", "--certs", certs, "--listen",
                                  central, "--external", "der:SGen2,measurement", "--routers",
                                  "site", "--startup-timeout", "120"),
                          cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    others = [subprocess.Popen([sys.executable, "-m", "adnmesh", *argv], cwd=tmp,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
              for argv in (["router", str(config), "--name", "site", "--connect", central,
                            "--listen", site, "--certs", certs, *router_flags],
                           ["agent", "der", "--id", "SGen2", str(config), "--connect", site,
                            "--certs", certs],
                           ["agent", "measurement", str(config), "--connect", site, "--certs",
                            certs])]
    return up, others


@pytest.mark.slow
def test_two_linked_routers_with_agents_split_record_what_one_router_records(attacked) -> None:
    """Two routers on two ports, agents split between them, secure profile: the recorded
    payloads equal the in-process run's, as the single-router run's do."""
    tmp, config, table = attacked.tmp, attacked.config, attacked.table
    out = tmp / "split.mcap"
    up, others = start_split(tmp, config, table, out, "--until-run-ends")
    outputs = end_all([up, *others])
    (_, up_err), (_, router_err), *_ = outputs
    assert up.returncode == 0, "\n".join(err for _, err in outputs)
    assert [p.returncode for p in others] == [0, 0, 0]
    assert "waiting up to 120 s for 2 external agent(s): der/SGen2, measurement" in up_err
    assert "adnmesh up is reachable" in router_err
    assert "security:" not in up_err
    assert data_messages(read_recording(out)) == attacked.expected
    assert processes_mentioning(str(config)) == []


@pytest.mark.slow
def test_a_site_router_that_drops_loses_its_agents_and_the_run_goes_on(attacked) -> None:
    """The site router killed while the run goes: its agents lose ``up`` and exit; ``up``
    names them lost and runs to the end without them (the CPFC holds without measurements,
    the monitor reports the DER unavailable)."""
    tmp, config, table = attacked.tmp, attacked.config, attacked.table
    out = tmp / "dropped.mcap"
    up, (router, *agents) = start_split(tmp, config, table, out)
    ready = wait_for_line(up, "agents ready")
    os.kill(router.pid, signal.SIGKILL)
    outputs = end_all([*agents, up, router])
    up_err = "".join(ready) + outputs[2][1]
    assert any("agents ready" in line for line in ready), up_err
    assert [a.returncode for a in agents] == [0, 0], [e for _, e in outputs[:2]]
    assert up.returncode == 1, up_err
    for agent in ("der/SGen2", "measurement"):
        assert f"external agent {agent}: its session ended without a goodbye" in up_err
    assert "agent(s) lost during the run: der/SGen2, measurement" in up_err
    run = read_recording(out)
    last_p_y = max(m.publish_time_ns for m in run.messages if m.topic.endswith("/cpfc/p_y"))
    assert last_p_y == ns(CHANGES["scenario"]["duration_s"])      # the run reached its end
    kinds = {json.loads(m.data)["kind"] for m in run.messages if "/event/" in m.topic}
    assert {"agent_lost", "hold", "unavailable"} <= kinds
    assert processes_mentioning(str(config)) == []


@pytest.mark.slow
def test_an_agent_told_to_stop_on_its_host_is_lost_and_the_run_goes_on(tmp_path) -> None:
    """SIGTERM to one DER's process (not by ``up``): it says goodbye and exits; ``up`` counts
    it lost and runs to the end (it used to wait for that agent's reports for ever)."""
    proc, agents, config = start_long_run(tmp_path, "told", **CHANGES)
    victim = max(agents)
    os.kill(victim, signal.SIGTERM)
    returncode, err = finish(proc, agents, config)
    assert returncode == 1, err
    assert "said goodbye before the end of the run (pid " in err
    run = read_recording(tmp_path / "told.mcap")
    last_p_ip = max(m.publish_time_ns for m in run.messages if m.topic.endswith("/p_ip"))
    assert last_p_ip == ns(CHANGES["scenario"]["duration_s"])


def test_an_external_agent_that_never_comes_is_named(tmp_path) -> None:
    """Every agent external (none started here: no agent to wait for at the shutdown), none
    comes: up names each and says how to start them."""
    config, table = write_case(tmp_path, "lonely")
    everyone = "cpfc,measurement,availability,der:SGen1,der:SGen2"
    result = subprocess.run(up_argv(config, table, tmp_path / "lonely.mcap", "--external",
                                    everyone, "--startup-timeout", "3"),
                            cwd=tmp_path, capture_output=True, text=True, timeout=120,
                            check=False)
    assert result.returncode == 1, result.stderr
    missing = "availability, cpfc, der/SGen1, der/SGen2, measurement"
    assert f"agents not ready after 3 s: {missing} (external, not connected: {missing}; " \
        f"start each on its host, e.g. 'adnmesh agent availability {config} --connect tcp/" \
        in result.stderr, result.stderr
    assert processes_mentioning(str(config)) == []


@pytest.mark.parametrize("argv, code, message", [
    (["agent", "der", "CONFIG", "--connect", "tcp/127.0.0.1:1"], 2, "der needs --id"),
    (["agent", "cpfc", "CONFIG", "--id", "x", "--connect", "tcp/127.0.0.1:1"], 2,
     "cpfc takes no --id"),
    (["agent", "measurement", "CONFIG", "--connect", "tls/127.0.0.1:1"], 2, "needs certificates"),
    (["agent", "measurement", "CONFIG", "--connect", "tcp/127.0.0.1:1", "--connect-timeout",
      "0.5"], 1, "cannot connect to tcp/127.0.0.1:1"),
    (["up", "CONFIG", "--secure", "--certs", "nowhere"], 2, "no certificate directory"),
    (["up", "CONFIG", "--external", "der:Nope"], 2, "--external: no agent 'der/Nope'"),
    (["up", "CONFIG", "--routers", "site"], 2, "--routers is for the secure profile"),
])
def test_multi_host_and_secure_usage_errors_are_one_line(argv, code, message, capsys) -> None:
    config = REPO / "configs" / "examples" / "runtime-step.yaml"
    assert adnmesh_main([str(config) if a == "CONFIG" else a for a in argv]) == code
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def steal_and_send(config, keys) -> int:
    """With der/SGen2's certificate: wait (bounded) until the run is 20 s in (the P_Y that
    SGen2 may receive says how far), then send 16 states of 10 MW and 16 heartbeats on SGen2's
    own keys, with sequence numbers from 10^9 and send times 5 s ahead, and two clock reports
    of SGen2's (one claiming 1,000 states nobody sent, one out of turn); return how many."""
    import threading

    import zenoh

    seen_ns, running = [0], threading.Event()

    def on_p_y(sample) -> None:
        seen_ns[0] = max(seen_ns[0], json.loads(sample.payload.to_bytes().split(b"\n")[-1])[
            "t_send_ns"])
        if seen_ns[0] >= 20 * 10 ** 9:
            running.set()

    sent = 0
    with zenoh.open(config) as session:
        subscriber = session.declare_subscriber(keys.of("p_y"), on_p_y)
        assert running.wait(60), "the run did not reach 20 s"
        at_ns = seen_ns[0] + 5 * 10 ** 9
        for i in range(16):
            for kind, body in (("der_state", {"p_w": 1e7, "setpoint_w": 1e7, "mode": "control"}),
                               ("heartbeat", {"available": True, "mode": "control"})):
                key = keys.of(kind, "SGen2")
                session.put(key, payload(key, body, seq=10 ** 9 + i, t_send_ns=at_ns + i),
                            congestion_control=zenoh.CongestionControl.BLOCK)
                sent += 1
        report = keys.of("clock_report", "der/SGen2")
        for i, claimed in enumerate(({keys.of("der_state", "SGen2"): (1000, at_ns)}, {})):
            session.put(report, payload(report, {"next_ns": None, "granted_ns": at_ns,
                                                 "received": 0, "sent": claimed},
                                        seq=10 ** 9 + i, t_send_ns=seen_ns[0]),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            sent += 1
        subscriber.undeclare()
    return sent


@pytest.mark.slow
def test_a_stolen_der_key_costs_that_der_and_nothing_else(tmp_path) -> None:
    """Someone with der/SGen2's certificate sends 32 valid messages on SGen2's own keys (the
    access control lets them through: the keys are that DER's), with high sequence numbers,
    send times in the future and 10 MW on a 2 MW plant. The run completes; SGen2 is
    quarantined (a fault in the summary, an event), its DER counts as unavailable, the CPFC
    switches to SGen1's gains, and the step after it is followed by SGen1 alone; no other
    agent misses a message."""
    changes = {"scenario": {"duration_s": 300, "p_ref_steps": [{"t_s": 200, "delta_w": 5e5}],
                            "availability": []}}
    config, _ = write_case(tmp_path, "stolen", **changes)
    loaded = load_config(config)
    issue(tmp_path / "certs", identities(loaded))
    proc, agents, run_config = start_long_run(
        tmp_path, "stolen", "--secure", "--certs", str(tmp_path / "certs"), "--summary-json",
        str(tmp_path / "stolen.json"), **changes)
    try:
        endpoint = json.loads((tmp_path / "stolen.run.json").read_text())["endpoint"]
        keys = Topology.from_config(loaded).keys
        sent = steal_and_send(rogue_config(endpoint, tmp_path / "certs", "der/SGen2"), keys)
    finally:
        returncode, err = finish(proc, agents, run_config)
    assert sent == 34, err
    assert returncode == 0, err
    assert "der/SGen2 quarantined" in err
    run = read_recording(tmp_path / "stolen.mcap")
    faults = [json.loads(m.data) for m in run.messages if m.topic == keys.of("fault")]
    assert [(f["kind"], f["agent"], f["origin"]) for f in faults] == [
        ("kill", "der/SGen2", "quarantine")]
    quarantined_ns = faults[0]["start_ns"]
    assert 20 * 10 ** 9 <= quarantined_ns < 200 * 10 ** 9   # mid-run, before the step
    # nothing SGen2 "sent" after its quarantine was taken; the CPFC switched to SGen1 alone
    late = [m for m in run.messages if m.topic.startswith(f"{keys.root}/der/SGen2/")
            and json.loads(m.data)["t_send_ns"] >= quarantined_ns]
    assert late == []
    weights = [json.loads(m.data).get("w") for m in run.messages if m.topic == keys.of("p_y")]
    assert {"SGen1": 1.0} in [w for w in weights if w]
    rejected = [json.loads(m.data) for m in run.messages if m.topic.endswith("/rejected")]
    assert {r["reason"] for r in rejected} <= {"ahead_of_clock", "implausible", "quarantined",
                                               "replayed"}
    assert len(rejected) <= 34                       # one per rogue message at most
    # nothing else lost a message: the forged ones SGen2's receivers counted stood in for
    # messages still in flight until the clock cut SGen2's keys (the CPFC then missed SI)
    kinds = {json.loads(m.data)["kind"] for m in run.messages if "/event/" in m.topic}
    assert not kinds & {"si_stale", "hold", "overrun"}, kinds
    summary = json.loads((tmp_path / "stolen.json").read_text())
    (step,) = summary["steps"]
    figures = step["figures"]
    assert step["t_s"] == 200.0 and figures["settling_time_s"] is not None
    assert figures["overshoot_pct"] < 5.0 and abs(step["steady_error_w"]) < 0.01 * 5e5
