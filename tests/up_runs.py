"""Test helper: running ``adnmesh up`` as a real process on the small runtime case.

Every run uses a small config (two wind turbines; 12 s of sim time unless changed) and its own
gain table, writes into the test's temporary directory, and is bounded by a timeout; processes
are found and checked by PID, never by name, and every one a helper starts is ended by PID.
"""

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
import yaml

from adnmesh.config import load_config
from adnmesh.runtime.forkserver import SERVER_NAME
from adnmesh.tuning.table import SchedulingTable, TableEntry, save_table

REPO = Path(__file__).resolve().parent.parent
CASE = REPO / "configs" / "examples" / "runtime-step.yaml"
KP2, KI2 = 5e-8, 1.92e-7      # both WTs (see tests/test_runtime.py: stable, alpha 1.51, 0 %)
RUN_TIMEOUT_S = 120


def write_case(tmp_path: Path, name: str = "case", **changes) -> tuple[Path, Path]:
    """Copy the runtime test case (with ``changes`` merged into its document) to ``tmp_path``,
    with a gain table tuned for exactly that file; return (config path, table path)."""
    document = yaml.safe_load(CASE.read_text())
    for section, values in changes.items():
        if isinstance(values, dict):
            document.setdefault(section, {}).update(values)
        else:
            document[section] = values
    config_path = tmp_path / f"{name}.yaml"
    config_path.write_text(yaml.safe_dump(document, sort_keys=False))
    config = load_config(config_path)
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), KP2, KI2, {"SGen1": 1.0, "SGen2": 1.0}))
    table.add(TableEntry(("SGen1",), 2 * KP2, 2 * KI2, {"SGen1": 1.0}))
    table_path = tmp_path / f"{name}.table.json"
    save_table(table, table_path)
    return config_path, table_path


def up_argv(config: Path, table: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "adnmesh", "up", str(config), "--table", str(table),
            "--out", str(out), *extra]


def run_up(tmp_path: Path, config: Path, table: Path, name: str, *extra: str,
           env: dict[str, str] | None = None):
    """Run ``adnmesh up`` to the end (``env``: more environment for it); return (completed
    process, recording, summary)."""
    from adnmesh.recording import read_recording

    out = tmp_path / f"{name}.mcap"
    summary = tmp_path / f"{name}.summary.json"
    result = subprocess.run(up_argv(config, table, out, "--summary-json", str(summary), *extra),
                            cwd=tmp_path, capture_output=True, text=True,
                            env={**os.environ, **(env or {})},
                            timeout=RUN_TIMEOUT_S, check=False)
    assert result.returncode == 0, result.stderr
    return result, read_recording(out), json.loads(summary.read_text())


def data_messages(recording) -> list[tuple[str, bytes]]:
    """The data plane (everything but the clock's own traffic, rejected payloads, a person's
    fault requests and the recorder's log of events), in a fixed order."""
    messages = [m for m in recording.messages if "/clock/" not in m.topic
                and not m.topic.endswith(("/rejected", "/control/fault"))
                and m.schema_name != "foxglove.Log"]
    messages.sort(key=lambda m: (m.log_time_ns, m.topic, json.loads(m.data)["seq"]))
    return [(m.topic, bytes(m.data)) for m in messages]


def children_of(pid: int) -> set[int]:
    """PIDs of the direct children of ``pid`` (from /proc)."""
    found = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            found |= {int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()}
        except FileNotFoundError:
            continue
    return found


def descendants_of(pid: int) -> set[int]:
    """PIDs of every process below ``pid``: ``up``'s agents are children of its fork server
    (``runtime.agent_start: fork``), or its own children (``exec``)."""
    found, todo = set(), [pid]
    while todo:
        below = children_of(todo.pop()) - found
        found |= below
        todo += below
    return found


def agents_among(pids: set[int]) -> set[int]:
    """Those of ``pids`` that run an agent (not the fork server, named by its ``comm``)."""
    return {pid for pid in pids if process_name(pid) != SERVER_NAME}


def process_name(pid: int) -> str:
    """``/proc/PID/comm``: a forked agent's name (``cpfc``, ``der SGen1``), "" if gone."""
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except FileNotFoundError:
        return ""


def alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def processes_mentioning(text: str) -> list[int]:
    """PIDs whose command line contains ``text`` (to find strays; never used to kill)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                cmdline = Path(f"/proc/{entry}/cmdline").read_bytes()
            except OSError:
                continue
            if text.encode() in cmdline and alive(int(entry)):
                found.append(int(entry))
    return found


def start_long_run(tmp_path: Path, name: str, *extra: str, **changes):
    """Start ``adnmesh up`` on a long sim scenario; return (process, agent pids, config path)
    once every agent is ready."""
    changes.setdefault("scenario", {"duration_s": 3600})
    config, table = write_case(tmp_path, name, **changes)
    proc = subprocess.Popen(up_argv(config, table, tmp_path / f"{name}.mcap", *extra),
                            cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    with selectors.DefaultSelector() as selector:
        selector.register(proc.stderr, selectors.EVENT_READ)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if not selector.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            line = proc.stderr.readline()
            lines.append(line)
            if "agents ready" in line or not line:
                break
    if not any("agents ready" in line for line in lines):
        proc.kill()
        proc.wait()
        pytest.fail("adnmesh up did not get ready: " + "".join(lines))
    agents = descendants_of(proc.pid)      # the agents and the fork server
    assert len(agents_among(agents)) == 5
    return proc, agents, config


FINISH_TIMEOUT_S = 120
"""How long ``adnmesh up`` may take to finish a long run: the stolen-key run (300 s of sim
time, secure profile) takes 7 s alone, but took over 60 s on the shared 2-core machine at a
load average of 15."""


def finish(proc: subprocess.Popen, agents: set[int], config: Path) -> tuple[int, str]:
    """Wait (bounded) for ``adnmesh up`` to exit; check nothing of the run is left."""
    try:
        _, err = proc.communicate(timeout=FINISH_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        for pid in agents:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"adnmesh up did not exit within {FINISH_TIMEOUT_S} s")
    assert [pid for pid in agents if alive(pid)] == []
    assert processes_mentioning(str(config)) == []
    return proc.returncode, err


def end_all(processes) -> list[tuple[str, str]]:
    """Wait (bounded) for every process; SIGKILL by PID what is left; their outputs."""
    outputs = []
    try:
        for p in processes:
            outputs.append(p.communicate(timeout=180))
    finally:
        for p in processes:
            if p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
                p.wait()
    return outputs


def wait_for_line(proc: subprocess.Popen, text: str, timeout_s: float = 150) -> list[str]:
    """Read ``proc``'s stderr until a line contains ``text`` (bounded); the lines read."""
    lines = []
    with selectors.DefaultSelector() as selector:
        selector.register(proc.stderr, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not selector.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            lines.append(proc.stderr.readline())
            if text in lines[-1] or not lines[-1]:
                break
    return lines
