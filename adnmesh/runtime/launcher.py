"""``adnmesh up`` behind the command line: router, agents, clock, recorder, shutdown.

:func:`run` does, in this order:

1. opens the embedded Zenoh router (a session in mode ``router``, ``tcp/127.0.0.1:<free port>``
   unless told otherwise) and, on that session, one subscriber on ``adn/<grid>/**`` for what
   the agents send — every envelope to MCAP (``log_time`` = delivery time, ``publish_time`` =
   send time), clock reports to the sim clock's coordinator (grants out), goodbyes to the
   shutdown — and liveliness subscriptions that tell when an agent's session appears or dies;
   what ``up`` publishes itself (grants, start, stop) it records as it sends it;
2. spawns one process per agent with ``sys.executable agents/<kind>.py`` as Zenoh clients
   (own session so Ctrl-C reaches only ``up``; told to die with ``up`` on Linux), tracked by PID;
3. waits until every agent is ready (liveliness token and first clock report), announces the
   start on ``clock/start`` and runs the clock (sim: grants; realtime: the wall clock);
4. stops at the end of the scenario, on Ctrl-C / SIGTERM, or when an agent dies: announces
   ``clock/stop``, collects every agent's goodbye (what it published per key), waits for the
   processes and kills by PID whatever is left, closes the router;
5. compares what the agents (and ``up`` itself) published with what was recorded, per key, and
   fails loudly on any difference.

The result (:class:`UpResult`) carries the exit status and the series for the summary.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from adnmesh import __version__
from adnmesh.config import Config
from adnmesh.runtime.bus import DEFAULT_HOST, free_port, router_config
from adnmesh.runtime.clock import ClockError, Coordinator, Report
from adnmesh.runtime.links import ns
from adnmesh.runtime.messages import (
    SCHEMAS,
    MessageError,
    decode,
    encode,
    message_type,
    parse_json,
    split_frame,
)
from adnmesh.runtime.summary import RunSeries
from adnmesh.runtime.topology import Topology

__all__ = ["AGENTS_DIR", "AGENT_ZENOH_RUNTIME", "UpOptions", "UpResult", "agent_argv", "run"]

AGENTS_DIR = Path(__file__).resolve().parents[2] / "agents"
"""Where the agent programs are (``agents/`` of the source tree)."""

PARENT_ENV = "ADNMESH_PARENT_PID"
"""Environment variable with the PID of ``adnmesh up``; agents die with that process."""

AGENT_ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
"""Zenoh's thread pools in the agent processes (environment ``ZENOH_RUNTIME``, unless it is
set): one receive worker instead of two. An agent has a single link, to the router; the second
worker was woken for work it seldom found, which cost a fifth of a run's context switches and
about 8 % of its CPU time on two cores."""

EXIT_OK, EXIT_FAILED, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 130, 143

_SUMMARY_TYPES = frozenset({"p_ip", "p_ref", "p_y", "heartbeat", "fault"})
_TIMES = re.compile(rb'"t_send_ns":(\d+),"t_deliver_ns":(\d+)[,}]')


def _loads(payload: bytes):
    """The JSON value of a recorded payload (NaN and Infinity allowed: the recorder records
    whatever comes and the summary takes what it can)."""
    try:
        return parse_json(payload)
    except MessageError:
        return json.loads(payload)


@dataclass
class UpOptions:
    """How to run.

    Attributes
    ----------
    config : Config
    table_path : Path
        Gain table for the CPFC.
    out : Path
        MCAP file to write.
    clock : str
        ``sim`` or ``realtime``.
    speed : float
        Realtime speed factor (sim seconds per wall second).
    seed : int
        Seed of the ICT random streams (announced to the agents at the start).
    listen : str or None
        Router endpoint; default ``tcp/127.0.0.1:<free port>``.
    metadata : dict
        Extra run metadata for the recording (str -> str).
    startup_timeout_s, shutdown_timeout_s : float
        Bounds for the agents to become ready and to say goodbye, wall s.
    log : callable
        Receives one-line progress messages.
    """

    config: Config
    table_path: Path
    out: Path
    clock: str = "sim"
    speed: float = 1.0
    seed: int = 0
    listen: str | None = None
    metadata: dict = field(default_factory=dict)
    startup_timeout_s: float = 60.0
    shutdown_timeout_s: float = 10.0
    log: Callable[[str], None] = lambda line: None


@dataclass
class UpResult:
    """What a run produced.

    Attributes
    ----------
    exit_code : int
        0 success; 1 failure (agent died, recording incomplete, ...); 130/143 interrupted.
    reason : str
        Why the run ended (``finished``, ``SIGINT``, ``agent der/X died (...)``, ...).
    series : RunSeries
        For the summary.
    wall_time_s : float
        Wall time from the start announcement to the end of the clock, s.
    startup_s : float
        Wall time to get every agent ready, s.
    published, recorded : dict
        Messages per key: what the agents and ``up`` said they published, what was recorded.
    byes : dict
        Agent id -> its goodbye body.
    grants : int
        Clock grants issued (sim).
    problems : list of str
        What went wrong, one line each.
    """

    exit_code: int = EXIT_OK
    reason: str = ""
    series: RunSeries = field(default_factory=RunSeries)
    wall_time_s: float = 0.0
    startup_s: float = 0.0
    end_ns: int = 0
    published: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)
    byes: dict = field(default_factory=dict)
    grants: int = 0
    problems: list = field(default_factory=list)


def agent_argv(agent_id: str, config_path: Path, endpoint: str, table_path: Path) -> list[str]:
    """Command line of the process of ``agent_id``."""
    kind = "der" if agent_id.startswith("der/") else agent_id
    argv = [sys.executable, str(AGENTS_DIR / f"{kind}.py"), str(config_path),
            "--connect", endpoint]
    if kind == "der":
        argv += ["--der", agent_id[4:]]
    if kind == "cpfc":
        argv += ["--table", str(table_path)]
    return argv


class _Children:
    """The agent processes, by PID."""

    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen] = {}

    def spawn(self, agent_id: str, argv: list[str]) -> None:
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
        env.setdefault("ZENOH_RUNTIME", AGENT_ZENOH_RUNTIME)
        self.procs[agent_id] = subprocess.Popen(argv, env=env, start_new_session=True,
                                                stdin=subprocess.DEVNULL)

    def dead(self) -> list[tuple[str, int]]:
        return [(a, p.returncode) for a, p in self.procs.items() if p.poll() is not None]

    def wait_all(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for proc in self.procs.values():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass

    def kill_all(self) -> list[str]:
        """SIGKILL every child still running (by PID); return their agent ids."""
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


class _Run:
    """State shared by the router session's callbacks and the main thread."""

    def __init__(self, options: UpOptions, topology: Topology, recorder) -> None:
        self.options = options
        self.topology = topology
        self.keys = topology.keys
        self.recorder = recorder
        # two locks: `lock` for the clock and the agents' state (held while publishing grants),
        # `record_lock` for the recording and the series; `record_lock` may be taken while
        # holding `lock` (`send` records what it publishes), never the other way round.
        self.lock = threading.Lock()
        self.record_lock = threading.Lock()
        self.event = threading.Event()
        self.series = RunSeries()
        self.alive: set[str] = set()
        self.reported: set[str] = set()
        self.byes: dict[str, dict] = {}
        self.gone: list[str] = []
        self.problems: list[str] = []
        self.foreign = 0
        self.record_errors = 0
        self.own: dict[str, int] = {}
        self.own_seq: dict[str, int] = {}
        self.publishers: dict[str, zenoh.Publisher] = {}
        self.session: zenoh.Session | None = None
        self.up_token = None              # liveliness token of `up` (withdrawn at the end)
        self.coordinator: Coordinator | None = None
        self.finished = False
        self.clock_error: str | None = None
        self.end_ns = ns(options.config.scenario.duration_s)

    def withdraw_liveliness(self) -> None:
        """Withdraw ``up``'s liveliness token (once): agents waiting after their goodbye close."""
        token, self.up_token = self.up_token, None
        if token is not None:
            token.undeclare()

    # -- publishing (callers hold self.lock) ---------------------------------------------------

    def send(self, key: str, body: dict, t_ns: int) -> None:
        """Publish a message of ``up`` itself at sim time ``t_ns`` and record it (the recorder's
        subscriber takes only what comes from the agents)."""
        seq = self.own_seq.get(key, 0)
        self.own_seq[key] = seq + 1
        self.own[key] = self.own.get(key, 0) + 1
        pub = self.publishers.get(key)
        if pub is None:
            pub = self.publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK,
                allowed_destination=zenoh.Locality.REMOTE)
        type_name = message_type(key)
        payload = encode(type_name, "up", seq, t_ns, t_ns, body)
        pub.put(payload)
        with self.record_lock:
            self._record(key, type_name, [(payload, t_ns, t_ns)])

    def grant(self, grants) -> None:
        t = self.coordinator.now_ns() if grants else 0
        for g in grants:
            self.send(self.keys.grant(g.agent), {"until_ns": g.until_ns, "expect": g.expect}, t)
        if self.coordinator.finished and not self.finished:
            self.finished = True
            self.event.set()

    # -- recording (callers hold self.record_lock) ---------------------------------------------

    def _record(self, key: str, type_name: str, records: list[tuple[bytes, int, int]]) -> bool:
        """Write ``(payload, log_time_ns, publish_time_ns)`` envelopes of one key; False if the
        recorder refused them."""
        try:
            self.recorder.write_many(key, type_name, records)
        except (ValueError, RuntimeError) as exc:   # reported at the end of the run
            if not self.record_errors:
                self.problems.append(f"recording failed: {exc}")
            self.record_errors += len(records)
            return False
        return True

    def _record_frame(self, key: str, type_name: str, envelopes: list[bytes]) -> None:
        """Record the envelopes of one sample from an agent; feed the summary's series with
        what it needs (P_IP, P_ref, switches, heartbeats, faults)."""
        summary = type_name in _SUMMARY_TYPES
        records, bodies = [], []
        for payload in envelopes:
            wanted = summary and (type_name != "p_y" or b'"switch"' in payload)
            times = None if wanted else _TIMES.search(payload)  # our encoder's field order
            if times is not None:
                records.append((payload, int(times[2]), int(times[1])))
                continue
            try:
                body = _loads(payload)
                t_send, t_deliver = int(body["t_send_ns"]), int(body["t_deliver_ns"])
            except (ValueError, TypeError, KeyError):
                body, t_send, t_deliver = None, 0, 0
            records.append((payload, max(t_deliver, 0), max(t_send, 0)))
            if wanted and body is not None:
                bodies.append(body)
        if self._record(key, type_name, records):
            for body in bodies:
                self.series.add(type_name, body)

    # -- callbacks (Zenoh threads) -------------------------------------------------------------

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Every sample an agent sends: record its envelopes; clock reports and goodbyes also
        go to the clock and the shutdown."""
        key = str(sample.key_expr)
        try:
            type_name = message_type(key)
        except ValueError:
            with self.record_lock:
                self.foreign += 1
            return
        envelopes = split_frame(sample.payload.to_bytes())
        with self.record_lock:
            self._record_frame(key, type_name, envelopes)
        if type_name == "clock_report":
            for payload in envelopes:
                self.on_report(key, payload)
        elif type_name == "agent_bye":
            for payload in envelopes:
                self.on_bye(key, payload)

    def _decoded(self, key: str, payload: bytes, what: str):
        """The message, or None after noting why ``what`` was rejected."""
        try:
            return decode(key, payload)
        except MessageError as exc:
            with self.lock:
                self.problems.append(f"{key}: rejected {what}: {exc}")
            return None

    def on_report(self, key: str, payload: bytes) -> None:
        message = self._decoded(key, payload, "clock report")
        if message is None:
            return
        body = message.body
        report = Report(message.src, body["next_ns"], body["received"],
                        {k: (v[0], v[1]) for k, v in body["sent"].items()})
        with self.lock:
            self.reported.add(message.src)
            if self.coordinator is None or self.clock_error:
                return
            try:
                self.grant(self.coordinator.on_report(report))
            except ClockError as exc:
                self.clock_error = str(exc)
                self.event.set()

    def on_bye(self, key: str, payload: bytes) -> None:
        message = self._decoded(key, payload, "goodbye")
        if message is None:
            return
        with self.lock:
            self.byes[message.src] = message.body
            self.event.set()

    def on_alive(self, sample: zenoh.Sample) -> None:
        agent = str(sample.key_expr).split("/alive/", 1)[1]
        if agent == "up":
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(agent)
            else:
                self.alive.discard(agent)
                if agent not in self.byes:
                    self.gone.append(agent)
            self.event.set()


def run(options: UpOptions) -> UpResult:
    """Run the scenario of ``options.config`` as processes; see the module docstring."""
    from adnmesh.recording import PUBLISHED_METADATA, Recorder

    config = options.config
    topology = Topology.from_config(config)
    keys = topology.keys
    endpoint = options.listen or f"tcp/{DEFAULT_HOST}:{free_port()}"
    result = UpResult(end_ns=ns(config.scenario.duration_s))
    metadata = {"config": Path(config.path).read_text(), "config_path": str(config.path),
                "config_sha256": config.sha256, "adnmesh_version": __version__,
                "seed": str(options.seed), "clock": options.clock, "t0_ns": "0",
                **{k: str(v) for k, v in options.metadata.items()}}
    recorder = Recorder(options.out, metadata=metadata, schemas=SCHEMAS)
    state = _Run(options, topology, recorder)
    children = _Children()
    interrupted: list[int] = []
    previous = {}

    def on_signal(signum, frame):
        interrupted.append(signum)
        state.event.set()

    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, on_signal)
    try:
        with zenoh.open(router_config([endpoint])) as session:
            state.session = session
            if options.clock == "sim":
                state.coordinator = Coordinator(topology, result.end_ns)
            handles = [
                session.declare_subscriber(keys.all, state.on_sample,
                                           allowed_origin=zenoh.Locality.REMOTE),
                session.liveliness().declare_subscriber(f"{keys.root}/alive/**",
                                                        state.on_alive, history=True),
            ]
            state.up_token = session.liveliness().declare_token(keys.liveliness("up"))
            try:
                _drive(options, state, children, topology, endpoint, result, interrupted)
            finally:
                state.withdraw_liveliness()
                for handle in handles:
                    handle.undeclare()
        with state.lock:
            result.published = _published(state)
        result.recorded = recorder.counts()
        differences = sorted(k for k in set(result.published) | set(result.recorded)
                             if result.published.get(k, 0) != result.recorded.get(k, 0))
        if result.exit_code == EXIT_OK and differences:
            shown = "; ".join(f"{k}: published {result.published.get(k, 0)}, recorded "
                              f"{result.recorded.get(k, 0)}" for k in differences[:3])
            result.problems.append(f"recording incomplete on {len(differences)} key(s): {shown}")
            result.exit_code = EXIT_FAILED
        if state.foreign:
            result.problems.append(f"{state.foreign} message(s) on unknown keys were not recorded")
        if state.record_errors and result.exit_code == EXIT_OK:
            result.exit_code = EXIT_FAILED
        recorder.add_metadata(PUBLISHED_METADATA, {k: str(v) for k, v in result.published.items()})
    finally:
        children.kill_all()
        recorder.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    result.series = state.series
    result.byes = state.byes
    result.problems = state.problems + result.problems
    if state.coordinator is not None:
        result.grants = state.coordinator.grants_issued
    return result


def _published(state: _Run) -> dict[str, int]:
    total: dict[str, int] = dict(state.own)
    for bye in state.byes.values():
        for key, count in bye["published"].items():
            total[key] = total.get(key, 0) + count
    return total


def _drive(options: UpOptions, state: _Run, children: _Children, topology: Topology,
           endpoint: str, result: UpResult, interrupted: list[int]) -> None:
    """Spawn, start, wait for the end, stop. Sets ``result.exit_code`` and ``reason``."""
    log = options.log
    config = options.config
    t0 = time.monotonic()
    for agent_id in topology.agents:
        children.spawn(agent_id, agent_argv(agent_id, Path(config.path), endpoint,
                                            options.table_path))
    log(f"router on {endpoint}; started {len(topology.agents)} agents "
        f"(pids {' '.join(str(p.pid) for p in children.procs.values())})")
    agents = set(topology.agents)

    def died(agent: str, code: int) -> str:
        how = f"signal {-code}" if code < 0 else f"exit code {code}"
        return f"agent {agent} (pid {children.procs[agent].pid}) died ({how})"

    def failure() -> str | None:
        if interrupted:
            return "SIGINT" if interrupted[0] == signal.SIGINT else "SIGTERM"
        dead = [(a, c) for a, c in children.dead() if a not in state.byes]
        if dead:
            return died(*dead[0])
        with state.lock:
            gone = state.gone[0] if state.gone else None
            clock_error = state.clock_error
        if gone is not None:
            proc = children.procs.get(gone)
            if proc is not None:   # its session died: most likely the process, say how
                try:
                    return died(gone, proc.wait(timeout=1.0))
                except subprocess.TimeoutExpired:
                    pass
            return f"agent {gone} lost its session"
        if clock_error:
            return f"clock: {clock_error}"
        return None

    # -- startup: every agent alive and reported ----------------------------------------------
    deadline = t0 + options.startup_timeout_s
    reason = None
    while reason is None:
        with state.lock:
            ready = agents <= state.alive and agents <= state.reported
        if ready:
            break
        reason = failure()
        if reason is None and time.monotonic() > deadline:
            with state.lock:
                missing = sorted(agents - (state.alive & state.reported))
            reason = f"agents not ready after {options.startup_timeout_s:g} s: " \
                     f"{', '.join(missing)}"
        state.event.wait(0.05)
        state.event.clear()
    result.startup_s = time.monotonic() - t0

    # -- run ----------------------------------------------------------------------------------
    t_start = time.perf_counter()
    if reason is None:
        log(f"{len(agents)} agents ready in {result.startup_s:.2f} s; running "
            f"{config.scenario.duration_s:g} s of {options.clock} time")
        epoch_ns = time.time_ns() + 200_000_000
        with state.lock:
            state.send(state.keys.start, {"clock": options.clock, "epoch_ns": epoch_ns,
                                          "speed": float(options.speed),
                                          "end_ns": result.end_ns, "seed": options.seed}, 0)
            if state.coordinator is not None:
                state.grant(state.coordinator.start())
        end_wall = epoch_ns + result.end_ns / options.speed
        if options.clock == "realtime":
            t_start += (epoch_ns - time.time_ns()) * 1e-9   # the run starts at the epoch
        while reason is None:
            if options.clock == "sim":
                with state.lock:
                    done = state.finished
            else:
                done = time.time_ns() >= end_wall
            if done:
                reason = "finished"
                break
            reason = failure()
            if reason is None:
                state.event.wait(0.1)
                state.event.clear()
    result.wall_time_s = time.perf_counter() - t_start
    result.reason = reason
    if reason != "finished":
        result.exit_code = (EXIT_SIGINT if reason == "SIGINT" else
                            EXIT_SIGTERM if reason == "SIGTERM" else EXIT_FAILED)
        result.problems.append(f"run stopped: {reason}")

    # -- shutdown -----------------------------------------------------------------------------
    with state.lock:
        t_stop = state.coordinator.now_ns() if state.coordinator is not None else 0
        state.send(state.keys.stop, {"reason": reason}, t_stop)
    deadline = time.monotonic() + options.shutdown_timeout_s
    while time.monotonic() < deadline:
        with state.lock:
            waiting = {a for a in agents if a not in state.byes}
        running = {a for a, p in children.procs.items() if p.poll() is None}
        if not waiting & running:
            state.withdraw_liveliness()   # every running agent's goodbye is in: they may close
            break
        state.event.wait(0.05)
        state.event.clear()
    children.wait_all(max(0.5, deadline - time.monotonic()))
    killed = children.kill_all()
    if killed:
        result.problems.append(f"killed after the shutdown timeout: {', '.join(killed)}")
    with state.lock:
        missing = sorted(agents - set(state.byes))
    if result.exit_code == EXIT_OK and missing:
        result.exit_code = EXIT_FAILED
        result.problems.append(f"no goodbye from {', '.join(missing)}")
    # wait (bounded) until the recorder has everything the agents say they published
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        with state.lock:
            expected = _published(state)
        if all(state.recorder.counts().get(k, 0) >= v for k, v in expected.items()):
            break
        time.sleep(0.01)
