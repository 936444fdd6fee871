"""The agent processes of ``adnmesh up``: how each is started, and tracking them by PID.

Every agent runs as ``sys.executable agents/<kind>.py CONFIG --connect ENDPOINT`` in its own
session (so Ctrl-C reaches only ``up``), told to die with ``up`` (environment
:data:`PARENT_ENV`, Linux ``PR_SET_PDEATHSIG``), and is stopped, if it has to be, by PID.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from adnmesh.wire.keys import der_id_of

__all__ = ["AGENTS_DIR", "AGENT_ZENOH_RUNTIME", "PARENT_ENV", "AgentProcesses", "agent_argv"]

AGENTS_DIR = Path(__file__).resolve().parents[2] / "agents"
"""Where the agent programs are (``agents/`` of the source tree)."""

PARENT_ENV = "ADNMESH_PARENT_PID"
"""Environment variable with the PID of ``adnmesh up``; agents die with that process."""

AGENT_ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
"""Zenoh's thread pools in the agent processes (environment ``ZENOH_RUNTIME``, unless it is
set): one receive worker instead of two. An agent has a single link, to the router; the second
worker was woken for work it seldom found, which cost a fifth of a run's context switches and
about 8 % of its CPU time on two cores."""


def agent_argv(agent_id: str, config_path: Path, endpoint: str, table_path: Path,
               p_avail_w: float | None = None) -> list[str]:
    """Command line of the process of ``agent_id`` (a DER may be told its available power, W,
    so that it need not load the grid to learn it)."""
    der_id = der_id_of(agent_id)
    kind = "der" if der_id is not None else agent_id
    argv = [sys.executable, str(AGENTS_DIR / f"{kind}.py"), str(config_path),
            "--connect", endpoint]
    if der_id is not None:
        argv += ["--der", der_id]
        if p_avail_w is not None:
            argv += ["--p-avail-w", repr(float(p_avail_w))]
    if kind == "cpfc":
        argv += ["--table", str(table_path)]
    return argv


class AgentProcesses:
    """The agent processes of a run, by agent id (tracked and stopped by PID only)."""

    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen] = {}

    def spawn(self, agent_id: str, argv: list[str]) -> None:
        """Start ``argv`` as the process of ``agent_id``."""
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
        env.setdefault("ZENOH_RUNTIME", AGENT_ZENOH_RUNTIME)
        self.procs[agent_id] = subprocess.Popen(argv, env=env, start_new_session=True,
                                                stdin=subprocess.DEVNULL)

    def pids(self) -> str:
        """The PIDs, space-separated."""
        return " ".join(str(p.pid) for p in self.procs.values())

    def dead(self) -> list[tuple[str, int]]:
        """``(agent id, exit code)`` of every process that has ended (negative: signal)."""
        return [(a, p.returncode) for a, p in self.procs.items() if p.poll() is not None]

    def running(self) -> set[str]:
        """The agents whose process still runs."""
        return {a for a, p in self.procs.items() if p.poll() is None}

    def describe_death(self, agent_id: str, code: int) -> str:
        """``agent X (pid N) died (exit code C | signal S)``."""
        how = f"signal {-code}" if code < 0 else f"exit code {code}"
        return f"agent {agent_id} (pid {self.procs[agent_id].pid}) died ({how})"

    def wait_all(self, timeout_s: float) -> None:
        """Wait until every process has ended, at most ``timeout_s`` in all."""
        deadline = time.monotonic() + timeout_s
        for proc in self.procs.values():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass

    def kill_all(self) -> list[str]:
        """SIGKILL every process still running (by PID); return their agent ids."""
        killed = []
        for agent_id, proc in self.procs.items():
            if proc.poll() is None:
                try:
                    os.kill(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                killed.append(agent_id)
        for proc in self.procs.values():
            proc.wait()
        return killed
