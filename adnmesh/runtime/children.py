"""The agent processes of ``adnmesh up``: how each is started, and tracking them by PID.

Every agent runs as ``sys.executable -m adnmesh.agents.<kind> CONFIG --connect ENDPOINT`` in its own
session (so Ctrl-C reaches only ``up``), told to die with ``up`` (environment
:data:`PARENT_ENV`, Linux ``PR_SET_PDEATHSIG``), and is stopped, if it has to be, by PID.

An **external** agent (``adnmesh up --external``) runs elsewhere (``adnmesh agent`` on another
host): it has no PID here; it counts as running until its session ends without a goodbye
(:meth:`AgentProcesses.session_ended`: its host or its link went down) and does not come back
within :data:`SESSION_GRACE_S` (Zenoh reconnects a session that dropped under load; the agent
itself waits as long for ``up``), and then as dead.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from adnmesh.names import der_id_of

EXIT_INTERNAL_ERROR = 70
"""Exit code of an agent whose own code raised (EX_SOFTWARE). The process ends at once with one
line on stderr: an exception in a Zenoh callback is otherwise printed and swallowed by Zenoh,
and the agent lives on without ever reporting its window -- the sim clock then waits for it
until ``up``'s stall timeout ends the whole run; a dead agent is noted and the run goes on."""

__all__ = ["AGENT_PACKAGE", "AGENT_ZENOH_RUNTIME", "EXIT_INTERNAL_ERROR", "PARENT_ENV",
           "SESSION_GRACE_S", "AgentProcesses", "agent_argv", "hosted_ders_argv"]

AGENT_PACKAGE = "adnmesh.agents"
"""Where the agent programs are: ``python -m adnmesh.agents.<kind>``, one module per kind."""

PARENT_ENV = "ADNMESH_PARENT_PID"
"""Environment variable with the PID of ``adnmesh up``; agents die with that process."""

SESSION_GRACE_S = 10.0
"""How long an external agent's session may stay away before it counts as dead, wall s: as
long as an agent waits for ``up`` (:mod:`adnmesh.runtime.process`) before it stops."""

AGENT_ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
"""Zenoh's thread pools in the agent processes (environment ``ZENOH_RUNTIME``, unless it is
set): one receive worker instead of two. An agent has a single link, to the router; the second
worker was woken for work it seldom found, which cost a fifth of a run's context switches and
about 8 % of its CPU time on two cores."""


KILL_WAIT_S = 10.0
"""How long ``up`` waits for an agent it SIGKILLed to be reported ended, wall s; a forked
agent's end comes from the fork server, which is then ended itself if it has not said it."""

CONNECT_TIMEOUT_S = 30.0
"""How long an agent ``up`` starts keeps trying to reach ``up``'s router, s: the router listens
before the agents start, but on a saturated machine (100 agents connecting at once) a first
attempt can fail, and the agent exited on it."""


def _program_argv(kind: str, config_path: Path, endpoint: str) -> list[str]:
    """The agent program of ``kind`` on ``config_path``, connecting to ``endpoint``."""
    return [sys.executable, "-m", f"{AGENT_PACKAGE}.{kind}", str(config_path),
            "--connect", endpoint, "--connect-timeout", f"{CONNECT_TIMEOUT_S:g}"]


def agent_argv(agent_id: str, config_path: Path, endpoint: str, table_path: Path,
               p_avail_w: float | None = None, certs: Path | None = None,
               model_params: str | None = None, q_table_path: Path | None = None
               ) -> list[str]:
    """Command line of the process of ``agent_id`` (a DER may be told its available power, W,
    so that it need not load the grid to learn it, and its model parameters as JSON, so that it
    need not calibrate them; the CPFC its P table and, with reactive power control, its Q
    table; secure profile: with ``--certs``)."""
    der_id = der_id_of(agent_id)
    kind = "der" if der_id is not None else agent_id
    argv = _program_argv(kind, config_path, endpoint)
    if der_id is not None:
        argv += ["--der", der_id]
        if p_avail_w is not None:
            argv += ["--p-avail-w", repr(float(p_avail_w))]
        if model_params is not None:
            argv += ["--model-params", model_params]
    if kind == "cpfc":
        argv += ["--table", str(table_path)]
        if q_table_path is not None:
            argv += ["--q-table", str(q_table_path)]
    if certs is not None:
        argv += ["--certs", str(certs)]
    return argv


def hosted_ders_argv(ders: list[tuple[str, float | None, str | None]], config_path: Path,
                     endpoint: str) -> list[str]:
    """Command line of one process hosting several DER agents (``runtime.ders_per_process``,
    :mod:`adnmesh.runtime.host`): ``ders`` is ``(DER id, available power W or None, model
    parameters JSON or None)`` each; the powers and parameters go along only if every DER has
    them (the program takes them once per DER or not at all)."""
    argv = _program_argv("der", config_path, endpoint)
    with_power = all(p is not None for _, p, _ in ders)
    with_params = with_power and all(m is not None for _, _, m in ders)
    for der_id, p_avail_w, model_params in ders:
        argv += ["--der", der_id]
        if with_power:
            argv += ["--p-avail-w", repr(float(p_avail_w))]
        if with_params:
            argv += ["--model-params", model_params]
    return argv


class AgentProcesses:
    """The agent processes of a run, by agent id (tracked and stopped by PID only), and the
    external agents (see the module docstring)."""

    def __init__(self, external=(), grace_s: float = SESSION_GRACE_S) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.external = frozenset(external)
        self.grace_s = grace_s
        self._ended: dict[str, float] = {}   # external agent -> when its session ended (mono s)
        self._lock = threading.Lock()        # _ended: changed by Zenoh callbacks
        self.env: dict[str, str] = {}        # more environment for the processes
        self.left: set[str] = set()          # hosted agents that left their running process
        self.forkserver = None               # a started ForkServer: agents are forked from it
        self._hosts: dict[str, str | None] = {}   # agent -> first agent of its hosting process

    def session_ended(self, agent_id: str) -> None:
        """An agent's session ended without a goodbye: an external one is dead unless it is
        back within the grace."""
        if agent_id in self.external:
            with self._lock:
                self._ended.setdefault(agent_id, time.monotonic())

    def session_back(self, agent_id: str) -> None:
        """An agent's session is (back) up: an external one is not dead, unless it was
        already (it stays dead: the run went on without it)."""
        with self._lock:
            ended = self._ended.get(agent_id)
            if ended is not None and time.monotonic() - ended <= self.grace_s:
                del self._ended[agent_id]

    def expect_again(self, agent_id: str) -> None:
        """An external agent is to be started again (a restart): it is no longer dead."""
        with self._lock:
            self._ended.pop(agent_id, None)

    def describe(self, agent_id: str) -> str:
        """``pid N``, or ``external`` for an agent that runs elsewhere."""
        proc = self.procs.get(agent_id)
        return "external" if proc is None else f"pid {proc.pid}"

    def spawn(self, agent_id: str, argv: list[str]) -> None:
        """Start ``argv`` as the process of ``agent_id``."""
        self.spawn_hosting([agent_id], argv)

    def spawn_hosting(self, agent_ids: list[str], argv: list[str]) -> None:
        """Start ``argv`` as the one process of every agent of ``agent_ids``."""
        env = dict(os.environ, **self.env, **{PARENT_ENV: str(os.getpid())})
        env.setdefault("ZENOH_RUNTIME", AGENT_ZENOH_RUNTIME)
        proc = None if self.forkserver is None else \
            self.forkserver.spawn(argv, env, _process_name(agent_ids))
        if proc is None:
            proc = subprocess.Popen(argv, env=env, start_new_session=True,
                                    stdin=subprocess.DEVNULL)
        host = agent_ids[0] if len(agent_ids) > 1 else None
        for agent_id in agent_ids:
            self._hosts[agent_id] = host
            self.procs[agent_id] = proc
            self.left.discard(agent_id)

    def host_of(self, agent_id: str) -> str | None:
        """The first agent of the process that hosts ``agent_id`` with others (the name of its
        grant sample, :meth:`~adnmesh.wire.keys.Keys.host_grants`), None for an agent in a
        process of its own or one that left its host."""
        host = self._hosts.get(agent_id)
        return None if agent_id in self.left else host

    def shares_process(self, agent_id: str) -> bool:
        """``agent_id``'s process hosts other agents that have not left it."""
        proc = self.procs.get(agent_id)
        return proc is not None and any(
            p is proc and a != agent_id and a not in self.left for a, p in self.procs.items())

    def leave(self, agent_id: str) -> None:
        """A hosted agent ended (an injected kill) while its process goes on: it no longer
        runs, and its process is not waited for on its account."""
        self.left.add(agent_id)

    def _processes(self) -> list[subprocess.Popen]:
        """Every process once (a hosting process is the process of several agents)."""
        return list({id(p): p for p in self.procs.values()}.values())

    def _ended_processes(self) -> set[int]:
        """``id()`` of every process that has ended (each polled once)."""
        return {id(p) for p in self._processes() if p.poll() is not None}

    def pids(self) -> str:
        """The PIDs, space-separated."""
        return " ".join(str(p.pid) for p in self._processes())

    def dead(self) -> list[tuple[str, int | None]]:
        """``(agent id, exit code)`` of every process that has ended (negative: signal; None:
        an external agent whose session ended)."""
        ended = self._ended_processes()
        return [(a, p.returncode) for a, p in self.procs.items() if id(p) in ended] + \
            [(a, None) for a in sorted(self.gone())]

    def running(self) -> set[str]:
        """The agents whose process still runs (external ones: whose session has not ended
        for longer than the grace)."""
        ended = self._ended_processes()
        return {a for a, p in self.procs.items() if id(p) not in ended and a not in self.left} \
            | (self.external - self.gone())

    def gone(self) -> set[str]:
        """External agents whose session ended longer than the grace ago."""
        now = time.monotonic()
        with self._lock:
            return {a for a, t in self._ended.items() if now - t > self.grace_s}

    def describe_death(self, agent_id: str, code: int | None) -> str:
        """``agent X (pid N) died (exit code C | signal S)``, or that an external agent's
        session ended."""
        if code is None:
            return (f"external agent {agent_id}: its session ended without a goodbye and did "
                    f"not come back within {self.grace_s:g} s (its process, host or link is "
                    "down)")
        how = f"signal {-code}" if code < 0 else f"exit code {code}"
        if code == EXIT_INTERNAL_ERROR:
            how += ": an internal error, its line above says where"
        return f"agent {agent_id} (pid {self.procs[agent_id].pid}) died ({how})"

    def wait_all(self, timeout_s: float) -> None:
        """Wait until every process has ended, at most ``timeout_s`` in all."""
        deadline = time.monotonic() + timeout_s
        for proc in self._processes():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass

    def kill_all(self) -> list[str]:
        """SIGKILL every process still running (by PID); return their agent ids."""
        killed = [a for a, p in self.procs.items() if p.poll() is None and a not in self.left]
        for proc in self._processes():
            proc.kill()      # by PID, unless it has ended (and been reaped) already
        for proc in self._processes():
            try:
                proc.wait(timeout=KILL_WAIT_S)
            except subprocess.TimeoutExpired:   # a fork server that does not answer: end it,
                if self.forkserver is not None:  # and its children with it
                    self.forkserver.abort()
                proc.wait()
        return killed


def _process_name(agent_ids: list[str]) -> str:
    """The name a forked agent process takes (``/proc/PID/comm``, 15 bytes): ``der SGen1``,
    ``cpfc``, ``der x50`` for a process hosting 50 DERs."""
    if len(agent_ids) > 1:
        return f"der x{len(agent_ids)}"
    return agent_ids[0].replace("/", " ")
