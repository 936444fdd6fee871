"""``adnmesh up`` with DERs behind real protocols, on the wall clock: SGen1 behind a SunSpec
device simulator that ``up`` starts, SGen2 behind an IEC 104 simulator the test starts, kills
(a device that drops off the net) and starts again (a device restart)."""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from adnmesh.recording import read_recording
from adnmesh.runtime.bus import free_port
from up_runs import alive, descendants_of, processes_mentioning, up_argv, write_case

pytestmark = pytest.mark.slow


def start_simulator(config: Path, der: str, protocol: str) -> subprocess.Popen:
    """``adnmesh device`` for ``der``; returns once it says it listens (bounded)."""
    proc = subprocess.Popen([sys.executable, "-m", "adnmesh", "device", protocol, str(config),
                             "--der", der], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    line = read_line(proc.stdout, "as a", 60)
    assert "listens" in line or " on 127.0.0.1:" in line, line + proc.stderr.read()
    return proc


def read_line(stream, wanted: str, timeout_s: float) -> str:
    """The first line of ``stream`` containing ``wanted`` (all lines read, bounded)."""
    lines = []
    with selectors.DefaultSelector() as selector:
        selector.register(stream, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not selector.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            line = stream.readline()
            lines.append(line)
            if wanted in line or not line:
                break
    return "".join(lines)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()


def test_a_realtime_run_with_ders_behind_both_protocols_survives_a_device_restart(
        tmp_path: Path) -> None:
    sunspec_port, iec104_port = free_port(), free_port()
    ders = [
        {"id": "SGen1", "type": "WT", "p_inst_w": 2e6, "t_delay_s": 0.01, "t_rise_s": 0.515,
         "sgen": "MV1.101 SGen 1",
         "plant": {"protocol": "sunspec", "port": sunspec_port, "simulator": True,
                   "timeout_s": 0.3, "retry_s": 0.2}},
        {"id": "SGen2", "type": "WT", "p_inst_w": 2e6, "t_delay_s": 0.01, "t_rise_s": 0.515,
         "sgen": "MV1.101 MV SGen 2", "p_sched_w": 5e5,
         "plant": {"protocol": "iec104", "port": iec104_port, "timeout_s": 0.3,
                   "retry_s": 0.2}},
    ]
    config, table = write_case(tmp_path, "devices", ders=ders,
                               scenario={"duration_s": 16, "availability": [],
                                         "p_ref_steps": [{"t_s": 9, "delta_w": 1e6}]})
    out = tmp_path / "devices.mcap"
    rtu = start_simulator(config, "SGen2", "iec104")
    up = subprocess.Popen(up_argv(config, table, out, "--clock", "realtime", "--summary-json",
                                  str(tmp_path / "devices.json")),
                          cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True)
    try:
        ready = read_line(up.stderr, "agents ready", 90)
        assert "agents ready" in ready, ready
        spawned = descendants_of(up.pid)
        # the RTU drops off the net 2 s into the run and comes back 2.5 s later (wall clock:
        # the run's input here, not a synchronisation)
        time.sleep(2.0)
        stop(rtu)
        time.sleep(2.5)
        rtu = start_simulator(config, "SGen2", "iec104")
        _, err = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
        stop(rtu)
    assert up.returncode == 0, ready + err
    assert [pid for pid in spawned if alive(pid)] == []          # agents and up's simulator
    assert processes_mentioning(str(config)) == []
    assert "device simulators: 1 started (SGen1 sunspec on 127.0.0.1:" in ready

    run = read_recording(out)
    events = [json.loads(m.data) for m in run.messages if m.topic.endswith("/event/der/SGen2")]
    kinds = [(e["kind"], e["text"]) for e in events if e["kind"].startswith("device_")]
    assert [k for k, _ in kinds] == ["device_lost", "device_back"], kinds
    # the RTU went down mid-request: the connection lost, no answer, or an interrogation cut
    # short by the stopping server
    assert any(f"device {why}:" in kinds[0][1] for why in ("unreachable", "timeout",
                                                            "malformed")), kinds
    weights = [json.loads(m.data).get("w") for m in run.messages if m.topic.endswith("/p_y")]
    alone = [i for i, w in enumerate(weights) if w == {"SGen1": 1.0}]
    both = [i for i, w in enumerate(weights) if w and set(w) == {"SGen1", "SGen2"}]
    assert alone and both and both[-1] > alone[0]                # switched away and back
    summary = json.loads((tmp_path / "devices.json").read_text())
    (step,) = summary["steps"]
    assert step["figures"]["settling_time_s"] is not None, step        # after the restart
    assert step["figures"]["overshoot_pct"] < 1.0 and abs(step["steady_error_w"]) < 1e4
    byes = {json.loads(m.data)["src"]: json.loads(m.data)
            for m in run.messages if "/clock/bye/" in m.topic}
    for der in ("der/SGen1", "der/SGen2"):
        stats = byes[der]["stats"]
        assert stats["device_writes"] > 0 and stats["device_reads"] > 100, stats
        assert 0 < stats["device_read_p50_ms"] < 100
