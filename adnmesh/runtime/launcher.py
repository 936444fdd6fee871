"""``adnmesh up`` behind the command line: router, agents, clock, recorder, shutdown.

:func:`run` goes through four named phases:

1. :func:`startup`: spawn one process per agent (:mod:`adnmesh.runtime.children`) as Zenoh
   clients of the embedded router and wait until every agent is ready (liveliness token and
   first clock report);
2. :func:`run_clock`: send the config's faults, announce ``clock/start`` and run the clock —
   sim: grants from the coordinator (:class:`~adnmesh.runtime.launcher_bus.SimClockDriver`);
   realtime: the wall clock — until the scenario's end or Ctrl-C / SIGTERM; faults requested
   meanwhile, injected kills and restarts, and agents that die on their own are the
   :class:`~adnmesh.runtime.injector.FaultInjector`'s (the run goes on without a dead agent);
3. :func:`shutdown`: announce ``clock/stop`` (realtime: again every second to agents without
   a goodbye), collect every agent's goodbye (what it published per key), withdraw ``up``'s
   liveliness so the agents may close, wait for the processes and kill by PID whatever is left;
4. :func:`verify`: compare what the agents (and ``up`` itself) published with what was
   recorded, per key, and fail loudly on any difference -- except, in a realtime run that could
   not keep up, what the overload explains (:mod:`adnmesh.runtime.accounting`: agents without
   a goodbye, messages lost on sessions that dropped), said as faults.

**A recording that fails** (a full disk: :attr:`adnmesh.recording.Recorder.failure`) stops the
run at once, exit code 1, as a stop for any other reason does: a run that cannot be recorded is
not a run. The reason is one line, ``recording failed: FILE: No space left on device``; the
shutdown, the summary (``series``, up to the stop) and ``UpResult.recording_failed`` follow as
usual, and the file keeps what its last successful flush wrote (``UpResult.on_disk``;
``adnmesh inspect`` recovers it).

Around them, the embedded router (a Zenoh session in mode ``router``, ``tcp/127.0.0.1:<free
port>`` unless told otherwise) carries one subscriber on ``adn/<grid>/**`` whose samples go
through the recorder tap (:class:`~adnmesh.runtime.tap.RecorderTap`: validated, then recorded;
clock reports on to the clock, goodbyes to the roster), a liveliness subscriber that tells
the :class:`~adnmesh.runtime.roster.Roster` when a session appears or ends, and a link-events
listener that counts the links per identity (:class:`~adnmesh.runtime.sessions.SessionWatch`).

**Secure profile** (``certs``): the router listens on ``tls/127.0.0.1:<free port>`` with
mutual TLS and the access control derived from the topology (:mod:`adnmesh.runtime.acl`,
:mod:`adnmesh.runtime.security`); every agent gets ``--certs``. **External agents**
(``external``) are not started here: ``up`` waits for them (``adnmesh agent`` on their hosts,
directly or through a site router named in ``routers``) as long as it waits for its own.
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import signal
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import zenoh

from adnmesh import __version__
from adnmesh.config import Config
from adnmesh.recording import PUBLISHED_METADATA, UNCOUNTED_METADATA, Recorder
from adnmesh.runtime import acl
from adnmesh.runtime.accounting import account_agents
from adnmesh.runtime.bus import DEFAULT_HOST, free_port, router_config
from adnmesh.runtime.children import PARENT_ENV, AgentProcesses, agent_argv, hosted_ders_argv
from adnmesh.runtime.device_simulators import DeviceSimulators
from adnmesh.runtime.forkserver import ForkServer
from adnmesh.runtime.identity import router_identity
from adnmesh.runtime.injector import FaultInjector
from adnmesh.runtime.launcher_bus import LauncherOutbox, SimClockDriver
from adnmesh.runtime.realtime import tolerance_ns
from adnmesh.runtime.roster import Roster
from adnmesh.runtime.os_scheduling import PRIORITY_ENV, freeze_heap, raise_priority
from adnmesh.runtime.sessions import SessionReport, SessionWatch
from adnmesh.results.eventlog import EventLog
from adnmesh.results.summary import RunSeries
from adnmesh.runtime.tap import REJECTED_RECORDS_KEPT, RecorderTap, recording_schemas
from adnmesh.sim.clock import Coordinator
from adnmesh.sim.topology import Topology
from adnmesh.names import LAUNCHER, der_id_of
from adnmesh.wire.units import ns

__all__ = ["EXIT_FAILED", "EXIT_NOT_REALTIME", "EXIT_OK", "RECORDING_FAILED", "UpOptions",
           "UpResult", "embedded_router_config", "recording_failure", "run", "run_levels"]

EXIT_OK, EXIT_FAILED, EXIT_NOT_REALTIME, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 3, 130, 143
NOT_REALTIME = "not real time"
"""How the reason of a run stopped by ``--strict`` begins."""
RECORDING_FAILED = "recording failed"
"""How the reason of a run stopped by a recording that failed (a full disk) begins."""
BEFORE_CONTACT_METADATA = "adnmesh.reports_before_contact"
"""Recording metadata: per report key, the ready reports an agent sent before ``up`` heard its
first one (they had no route to the recorder yet; not in the published counts)."""

_POLL_S = 0.1   # longest wait between checks of the processes, s
_BUS_QUEUE = 65536    # samples from the agents queued for up's bus thread (then senders wait)
_BATCH = 4096         # most samples the bus thread takes in one go
_HOLD_SAMPLES = 4096  # most samples taken before what they hold is recorded
_STOP_AGAIN_S = 1.0   # realtime: the stop is said again this often to agents without goodbye
_LATE_BYES = 3        # ... and up to this many shutdown timeouts waited for them, not kept up
_EXIT_GRACE_S = 3.0   # agents with their goodbye in get at least this long to exit, s (103
                      # under load took more than the 0.5 s once left after 10 s of goodbyes)


@dataclass
class UpOptions:
    """How to run.

    Attributes
    ----------
    config : Config
    table_path : Path
        Gain table for the CPFC.
    q_table_path : Path, optional
        Its Q table (reactive power control).
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
    run_id : str
        The run's id (for ``adnmesh fault``).
    run_file : Path, optional
        Where to describe the running run (endpoint, grid, pid) for ``adnmesh fault``;
        removed when the run ends.
    available_w : dict
        DER id -> its available power, W, handed to the DER processes.
    strict : bool
        Realtime: stop the run at the first overrun (exit code 3).
    certs : Path, optional
        The secure profile: the certificate directory (``adnmesh certs``).
    external : frozenset of str
        Agent ids started elsewhere (``adnmesh agent``); ``up`` waits for them.
    routers : tuple of str
        Names of the site routers (``adnmesh router --name``) that may link to this one.
    view : adnmesh.results.live.LiveView, optional
        Gets every recorded message (``--view``); the caller starts and closes it.
    progress : callable, optional
        Called with the sim time reached, ns, about every 0.1 s wall while the clock runs.
    stall_timeout_s : float
        Sim clock: stop the run when no grant was issued for this long, wall s (0: never).
        Nothing legitimate stalls the clock for long (a restarted process rejoins in seconds);
        in the open profile a forged message can (docs/deployment.md#a-rogue-session-tried).
    rt_priority : str
        Realtime: the scheduling priority of ``up`` and its agents
        (:data:`adnmesh.runtime.os_scheduling.PRIORITIES`: ``off``, ``nice``, ``fifo``); if the
        OS refuses it the run goes on at the ordinary priority and says so.
    features : frozenset of str
        Protocol features the config does not say (``hierarchy``: a level of a hierarchy).
    agent_args : tuple of str
        Arguments every agent process gets besides its own (a level of a hierarchy:
        ``--levels FILE --level GRID``, :mod:`adnmesh.runtime.place`).
    shared_clock : SharedClock, optional
        The sim clock of several levels (:mod:`adnmesh.runtime.level_clock`): this run joins
        it instead of running one of its own (:func:`run_levels`).
    wake : threading.Event, optional
        The event the run's waits wait on (default: its own; shared by the levels).
    endpoints : dict
        Agent id -> the router its process connects to (its site's,
        :mod:`adnmesh.runtime.site_router`; default: ``up``'s).
    access_control : dict, optional
        Secure profile: the router's access control (a hierarchy's, over every level; default
        derived from the config's topology and ``routers``).
    identities : tuple of str, optional
        Secure profile: who may link to the router, for :class:`SessionWatch` (default: the
        config's agents and ``routers``); with several levels only the lead watches (None
        elsewhere: ``watch_sessions``).
    watch_sessions : bool
        Count the router's links (the lead level of a hierarchy only: one router).
    """

    config: Config
    table_path: Path
    out: Path
    q_table_path: Path | None = None
    clock: str = "sim"
    speed: float = 1.0
    seed: int = 0
    listen: str | None = None
    metadata: dict = field(default_factory=dict)
    startup_timeout_s: float = 60.0
    shutdown_timeout_s: float = 10.0
    log: Callable[[str], None] = lambda line: None
    run_id: str = ""
    run_file: Path | None = None
    available_w: dict = field(default_factory=dict)
    strict: bool = False
    certs: Path | None = None
    external: frozenset = frozenset()
    routers: tuple = ()
    stall_timeout_s: float = 60.0
    rt_priority: str = "off"
    view: object | None = None
    progress: Callable[[int], None] | None = None
    features: frozenset = frozenset()
    agent_args: tuple = ()
    shared_clock: object | None = None
    wake: threading.Event | None = None
    endpoints: dict = field(default_factory=dict)
    access_control: dict | None = None
    identities: tuple | None = None
    watch_sessions: bool = True


@dataclass
class UpResult:
    """What a run produced.

    Attributes
    ----------
    exit_code : int
        0 success; 1 failure (agent died, recording incomplete, ...); 3 stopped by ``--strict``
        (not real time); 130/143 interrupted.
    reason : str
        Why the run ended (``finished``, ``SIGINT``, ``agent der/X died (...)``, ...).
    series : RunSeries
        For the summary.
    wall_time_s : float
        Wall time from the start announcement to the end of the clock, s.
    startup_s : float
        Wall time to get every agent ready, s.
    end_ns : int
        The scenario's end, ns.
    reached_ns : int
        How far the run got, ns (the end, unless it stopped early).
    published, recorded : dict
        Messages per key: what the agents and ``up`` said they published, what was recorded.
    byes : dict
        Agent id -> its goodbye (an ``agent_bye`` message).
    rejected : dict
        ``key -> {reason -> count}`` of what the recorder tap rejected.
    grants : int
        Clock grants issued (sim).
    sessions : SessionReport
        The links the router accepted, per identity, and the unexpected ones.
    problems : list of str
        What went wrong, one line each.
    tolerance_ns : int
        The realtime overrun tolerance, ns of sim time.
    recording_failed : str
        Why the recording failed (``FILE: No space left on device``), or empty.
    on_disk : tuple of int
        ``(messages, last log time ns)`` the file holds when the recording failed (module
        docstring).
    """

    exit_code: int = EXIT_OK
    reason: str = ""
    series: RunSeries = field(default_factory=RunSeries)
    wall_time_s: float = 0.0
    startup_s: float = 0.0
    end_ns: int = 0
    reached_ns: int = 0
    published: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)
    byes: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    grants: int = 0
    sessions: SessionReport = field(default_factory=SessionReport)
    problems: list = field(default_factory=list)
    tolerance_ns: int = 0
    recording_failed: str = ""
    on_disk: tuple = (0, 0)


class _Launch:
    """Everything one run of ``up`` holds, shared by the phases and the Zenoh callbacks."""

    def __init__(self, options: UpOptions) -> None:
        self.options = options
        self.config = options.config
        self.topology = Topology.from_config(self.config, options.features)
        self.keys = self.topology.keys
        scheme = "tcp" if options.certs is None else "tls"
        self.endpoint = options.listen or f"{scheme}/{DEFAULT_HOST}:{free_port()}"
        self.result = UpResult(end_ns=ns(self.config.scenario.duration_s))
        self.roster = Roster(self.topology.agents, options.wake)
        self.children = AgentProcesses(options.external)
        self.peers = tuple(router_identity(n) for n in options.routers)
        self.sessions = SessionWatch(options.identities if options.identities is not None
                                     else (*self.topology.agents, *self.peers))
        self.interrupted: list[int] = []
        events = EventLog()
        self.recorder = Recorder(options.out, metadata=_metadata(options),
                                 schemas=recording_schemas(), events_topic=f"{self.keys.root}/log",
                                 events=events.observe, events_quiet=events.quiet)
        self.clock: SimClockDriver | None = None
        self.tap = RecorderTap(self.recorder, self.topology, self.result.series,
                               lambda: self.clock.recent_ns if self.clock else 0,
                               view=options.view, clock_reach_ns=self._clock_reach_ns,
                               on_suspect=lambda agent, why: self.injector.quarantine(agent,
                                                                                      why))
        self.outbox: LauncherOutbox | None = None
        self.injector = FaultInjector(self)
        self.epoch_ns = 0
        self.result.tolerance_ns = tolerance_ns(self.config.runtime.realtime_tolerance_s,
                                                self.topology)
        self.not_realtime: str | None = None      # the first overrun, with --strict
        self.overrun_reports = 0                  # overrun events seen
        self.dropped: set[str] = set()            # agents whose session ended before the bye
        self.killed_at_shutdown: set[str] = set()
        self._overrun_log = [0.0, 0]              # next wall time to say one, how many unsaid
        self._start_body: dict | None = None
        self._bus: threading.Thread | None = None
        self.bus_error: str | None = None         # the bus thread failed (a bug: the run stops)
        self._handles: list = []
        self._token = None

    # -- the router session --------------------------------------------------------------------

    def open(self, session: zenoh.Session) -> None:
        """Declare the recorder's subscriber, the liveliness subscriber and ``up``'s token."""
        self.outbox = LauncherOutbox(session, self.tap)
        if self.options.shared_clock is not None:
            self.clock = self.options.shared_clock.join(
                self.config.grid, self.keys, self.outbox, self.children.host_of,
                on_violation=self.injector.quarantine, on_rejoin=self.injector.on_rejoin)
        elif self.options.clock == "sim":
            coordinator = Coordinator(self.topology, self.result.end_ns,
                                      on_rejoin=self.injector.on_rejoin)
            self.clock = SimClockDriver(coordinator, self.keys, self.outbox,
                                        self.roster.changed.set,
                                        on_violation=self.injector.quarantine,
                                        host_of=self.children.host_of)
        bus = session.declare_subscriber(self.keys.all, zenoh.handlers.FifoChannel(_BUS_QUEUE),
                                         allowed_origin=zenoh.Locality.REMOTE)
        self._bus = threading.Thread(target=self._take_bus, args=(bus.handler,),
                                     name="adnmesh-up-bus", daemon=True)
        self._bus.start()
        self._handles = [
            bus,
            session.liveliness().declare_subscriber(f"{self.keys.root}/alive/**",
                                                    _weak_callback(self.on_alive),
                                                    history=True),
        ]
        if self.options.watch_sessions:
            self.sessions.declare(session)
        self._token = session.liveliness().declare_token(self.keys.liveliness("up"))
        if self.options.run_file is not None:
            certs = self.options.certs
            self.options.run_file.parent.mkdir(parents=True, exist_ok=True)
            self.options.run_file.write_text(json.dumps({
                "run_id": self.options.run_id, "endpoint": self.endpoint,
                "grid": self.config.grid, "pid": os.getpid(), "clock": self.options.clock,
                "certs": None if certs is None else str(Path(certs).resolve())}))

    def router_config(self):
        """The Zenoh config of the embedded router (secure profile: mTLS and access control)."""
        return embedded_router_config(self.options, self.endpoint)

    def withdraw_liveliness(self) -> None:
        """Withdraw ``up``'s liveliness token (once): agents waiting after their goodbye close."""
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()

    def close(self) -> None:
        if self.options.run_file is not None:
            self.options.run_file.unlink(missing_ok=True)
        self.withdraw_liveliness()
        self.sessions.undeclare()
        for handle in self._handles:
            handle.undeclare()
        self._handles = []
        if self._bus is not None:      # the channel is closed: the thread ends once it is empty
            self._bus.join(10.0)

    def on_alive(self, sample: zenoh.Sample) -> None:
        """Liveliness: to the roster; an external agent whose session ended (and does not come
        back within the grace) is dead."""
        self.roster.on_alive(sample)
        agent = str(sample.key_expr).split("/alive/", 1)[1]
        if sample.kind == zenoh.SampleKind.PUT:
            self.children.session_back(agent)
        elif agent not in self.roster.byes and agent in self.topology.agents:
            self.dropped.add(agent)
            self.children.session_ended(agent)

    def _take_bus(self, channel) -> None:
        """The bus thread: every sample the agents send, in order, taken in batches of what
        has queued (:meth:`_take_samples`); ends when the subscriber is undeclared and its
        queue is empty. A failure here is a bug: said, and the run stops (:meth:`failure`).

        Each batch is recorded once the grants that follow it are out
        (:meth:`RecorderTap.writes_after`). On the sim clock, what the batches accept is
        recorded once the queue is empty (or after :data:`_HOLD_SAMPLES` samples): a sample
        that comes while ``up`` would record is taken first, so that the grants its report
        lets out are not behind the recording. On the realtime clock, which has no grants,
        each batch is recorded at once (the live view and the shutdown's counts see it)."""
        try:
            sample = None
            while True:
                if sample is None:
                    try:
                        sample = channel.recv()
                    except zenoh.ZError:             # closed and empty
                        return
                hold = _HOLD_SAMPLES if self.clock is not None else 1
                held = 0
                with self.tap.writes_after():
                    while sample is not None and held < hold:
                        batch = [sample]
                        while len(batch) < _BATCH and (sample := _queued(channel)) is not None:
                            batch.append(sample)
                        self._take_samples(batch)
                        held += len(batch)
                        sample = _queued(channel) if held < hold else None
        except Exception as exc:
            self.bus_error = f"{type(exc).__name__}: {exc}"
            self.roster.changed.set()

    def _take_samples(self, samples) -> None:
        """Samples from the agents, in the order they came: each through the tap (and a clock
        report that rides it, :meth:`RecorderTap.take_attached`); the batch's clock reports
        to the sim clock at once, after the rest. What the tap accepts is recorded by the
        caller's :meth:`RecorderTap.writes_after`."""
        reports = []
        for sample in samples:
            key = str(sample.key_expr)
            messages = self.tap.take(key, sample.payload.to_bytes())
            attachment = sample.attachment   # an agent's clock report rides its last sample
            if attachment is not None:
                messages += self.tap.take_attached(key, attachment.to_bytes())
            reports += self._take_messages(messages)
        if reports and self.clock is not None:
            self.clock.on_reports(reports)
            for message in reports:
                if message.killed_ns is not msgspec.UNSET:
                    self.injector.on_killed(message)

    def _take_messages(self, messages) -> list:
        """What ``up`` does with the agents' messages; return the clock reports (for the sim
        clock; on the realtime clock a kill's last report is taken here)."""
        reports = []
        for message in messages:
            if message.type == "clock_report":
                self.roster.note_report(message.src, message.seq)
                if self.clock is not None:
                    reports.append(message)
                elif message.killed_ns is not msgspec.UNSET:
                    self.injector.on_killed(message)
            elif message.type == "agent_bye":
                self.roster.note_bye(message)
            elif message.type == "fault_request":
                self.injector.on_request(message)
            elif message.type == "event" and message.kind == "overrun":
                self.on_overrun(message)
        return reports

    def on_overrun(self, message) -> None:
        """An agent cannot keep up: say so at once (at most once a second, with the count of
        those not said); with ``--strict`` stop the run."""
        self.overrun_reports += 1
        now, (next_s, unsaid) = time.monotonic(), self._overrun_log
        if now < next_s:
            self._overrun_log[1] = unsaid + 1
        else:
            more = f" (and {unsaid} more overrun report(s))" if unsaid else ""
            self.options.log(f"warning: {message.text}{more}")
            self._overrun_log[:] = [now + 1.0, 0]
        if self.options.strict and self.not_realtime is None:
            self.not_realtime = f"{message.text} (--strict)"
            self.roster.changed.set()

    # -- for the phases and the injector -------------------------------------------------------

    def overloaded(self) -> bool:
        """Realtime: an agent fell behind the tolerance (an overrun event, or one counted in
        a goodbye): the run is not real time."""
        return self.overrun_reports > 0 or any(
            bye.stats.get("overruns", 0) > 0 for bye in list(self.roster.byes.values()))

    def spawn(self, agent_id: str, resume_ns: int = 0) -> None:
        """Start the process of ``agent_id`` (a restarted one begins at ``resume_ns``); for an
        external agent, say how to start it on its host."""
        if agent_id in self.options.external:
            self.children.expect_again(agent_id)
            self.options.log(f"external agent {agent_id}: start it on its host with "
                             f"{self.agent_command(agent_id, resume_ns)}")
            return
        der_id = der_id_of(agent_id)
        p_avail_w = self.options.available_w.get(der_id)
        argv = agent_argv(agent_id, Path(self.config.path), self.endpoint_of(agent_id),
                          self.options.table_path, p_avail_w, self.options.certs,
                          self._model_params(der_id, p_avail_w), self.options.q_table_path)
        argv += self.options.agent_args
        if resume_ns:
            argv += ["--resume-at-ns", str(resume_ns)]
        self.children.spawn(agent_id, argv)

    def endpoint_of(self, agent_id: str) -> str:
        """The router ``agent_id``'s process connects to."""
        return self.options.endpoints.get(agent_id, self.endpoint)

    def process_groups(self, agents: list[str]) -> list[list[str]]:
        """The agents of each process to start: one each, but the DERs in groups of
        ``runtime.ders_per_process`` in config order (:mod:`adnmesh.runtime.host`), those of
        one router together."""
        size = self.config.runtime.ders_per_process
        groups = [[a] for a in agents if der_id_of(a) is None]
        by_router: dict[str, list[str]] = {}
        for a in agents:
            if der_id_of(a) is not None:
                by_router.setdefault(self.endpoint_of(a), []).append(a)
        for ders in by_router.values():
            groups += [ders[i:i + size] for i in range(0, len(ders), size)]
        return groups

    def spawn_hosting(self, group: list[str]) -> None:
        """Start one process for the agents of ``group`` (several DERs: a hosting process)."""
        if len(group) == 1:
            self.spawn(group[0])
            return
        ders = []
        for agent_id in group:
            der_id = der_id_of(agent_id)
            p_avail_w = self.options.available_w.get(der_id)
            ders.append((der_id, p_avail_w, self._model_params(der_id, p_avail_w)))
        self.children.spawn_hosting(group, [*hosted_ders_argv(ders, Path(self.config.path),
                                                              self.endpoint_of(group[0])),
                                            *self.options.agent_args])

    def _model_params(self, der_id: str | None, p_avail_w: float | None) -> str | None:
        """A DER's model parameters as JSON, calibrated here (the WT and CHP models by a root
        finder: the DER process then loads no scipy); None for another agent or a DER whose
        available power ``up`` was not given."""
        if der_id is None or p_avail_w is None:
            return None
        from adnmesh.control.der_model import der_params, params_json, usable_available_w
        (der,) = self.config.ders_by_id([der_id])
        return params_json(der_params(der, self.config, usable_available_w(der, p_avail_w)))

    def agent_command(self, agent_id: str, resume_ns: int = 0) -> str:
        """The ``adnmesh agent`` command line that runs ``agent_id`` against this router."""
        kind, _, der = agent_id.partition("/")
        words = ["adnmesh agent", kind, *(["--id", der] if der else []), str(self.config.path),
                 "--connect", self.endpoint]
        if self.options.certs is not None:
            words += ["--certs", "DIR"]
        if resume_ns:
            words += ["--resume-at-ns", str(resume_ns)]
        return "'" + " ".join(words) + "'"

    def _clock_reach_ns(self, agent: str) -> int | None:
        """How far the sim clock granted ``agent``, ns (None on the realtime clock). Read
        without the clock's lock (the tap asks under its own, and the clock records its grants
        under the tap's): a grant is issued before the messages it lets an agent send."""
        return None if self.clock is None else self.clock.coordinator.granted_ns(agent)

    def announce_start(self) -> None:
        """Publish ``clock/start`` (again, for an agent that restarted)."""
        self.outbox.send(self.keys.of("clock_start"), 0, **self._start_body)

    def clock_lock(self):
        """The sim clock's lock (held while a fault is injected), or a dummy one."""
        return self.clock.lock if self.clock is not None else contextlib.nullcontext()

    # -- reasons to stop -----------------------------------------------------------------------

    def failure(self) -> str | None:
        """Why the run must stop now (interrupted, the clock failed), or None. A dead agent is
        not a reason: the injector notes it and the run goes on."""
        if self.interrupted:
            return "SIGINT" if self.interrupted[0] == signal.SIGINT else "SIGTERM"
        if self.recorder.failure is not None:
            return f"{RECORDING_FAILED}: {recording_failure(self.recorder)}"
        if self.bus_error is not None:
            return f"internal error: up's bus thread failed: {self.bus_error}"
        if self.clock is not None and self.clock.error:
            return f"clock: {self.clock.error}"
        if self.not_realtime is not None:
            return f"{NOT_REALTIME}: {self.not_realtime}"
        timeout = self.options.stall_timeout_s
        if self.clock is not None and timeout and self.clock.stalled_s() > timeout:
            with self.clock.lock:
                busy = self.clock.coordinator.describe_busy()
            return (f"clock: no progress for {timeout:g} s (waiting for the report of "
                    f"{', '.join(busy) or 'nobody'})")
        return None

    def startup_failure(self) -> str | None:
        """Why the startup must stop: as :meth:`failure`, or an agent died before it was
        ready."""
        dead = [(a, c) for a, c in self.children.dead() if a in self.roster.not_ready()]
        if dead:
            return self.children.describe_death(*dead[0])
        return self.failure()


def embedded_router_config(options: UpOptions, endpoint: str) -> zenoh.Config:
    """The Zenoh config of ``up``'s router listening on ``endpoint``: in the secure profile
    with ``up``'s certificate and the access control derived from the topology."""
    if options.certs is None:
        return router_config([endpoint])
    return router_config([endpoint], certs=options.certs, identity=LAUNCHER,
                         access_control=_access_control(options))


def _access_control(options: UpOptions) -> dict:
    """The router's access control: the topology's rules, the site routers as peers (or the
    one given, a hierarchy's)."""
    if options.access_control is not None:
        return options.access_control
    return acl.access_control(Topology.from_config(options.config),
                              [router_identity(n) for n in options.routers])


def _metadata(options: UpOptions) -> dict[str, str]:
    config = options.config
    security = {"profile": "open"}
    if options.certs is not None:
        security = {"profile": "secure (mutual TLS, access control)",
                    "zenoh_access_control": json.dumps(_access_control(options))}
    return {"config": Path(config.path).read_text(), "config_path": str(config.path),
            "config_sha256": config.sha256, "adnmesh_version": __version__,
            "seed": str(options.seed), "clock": options.clock, "t0_ns": "0", **security,
            **{k: str(v) for k, v in options.metadata.items()}}


# -- phases ------------------------------------------------------------------------------------


def startup(*launches: _Launch) -> str | None:
    """Spawn every agent (of every level) and wait until all are ready; return why that
    failed, or None. The start-up time counts from the first agent process started: the fork
    server, if used."""
    started = [_spawn_agents(launch) for launch in launches]
    reason = None
    for launch, (_, spawned) in zip(launches, started):
        deadline = spawned + launch.options.startup_timeout_s
        while reason is None and launch.roster.not_ready():
            reason = launch.startup_failure()
            if reason is None and time.monotonic() > deadline:
                reason = _not_ready(launch)
            launch.roster.wait(_POLL_S)
    startup_s = time.monotonic() - min(t0 for t0, _ in started)   # every level ready
    for launch in launches:
        launch.result.startup_s = startup_s
    return reason


def _spawn_agents(launch: _Launch) -> tuple[float, float]:
    """Start the launch's agents; return when their start began (the fork server's, if used)
    and when they were spawned, monotonic s."""
    options, t0 = launch.options, time.monotonic()
    _raise_priority(launch)
    local = [a for a in launch.topology.agents if a not in options.external]
    for group in launch.process_groups(local):
        launch.spawn_hosting(group)
    server, spawned = launch.children.forkserver, t0
    if server is not None and server.failed is None:
        t0 = min(t0, server.started_at)     # the agents' start began with the server's
    elif server is not None:
        t0 = spawned = time.monotonic()     # programs after a failed server: the full timeout
    profile = "" if options.certs is None else " (secure: mutual TLS, access control)"
    level = f" of {launch.config.grid}" if options.shared_clock is not None else ""
    options.log(f"router on {launch.endpoint}{profile}; started {len(local)} agents{level} "
                f"(pids {launch.children.pids()})")
    if options.external:
        options.log(f"waiting up to {options.startup_timeout_s:g} s for "
                    f"{len(options.external)} external agent(s): "
                    f"{', '.join(sorted(options.external))}")
    return t0, spawned


def _raise_priority(launch: _Launch) -> None:
    """Realtime with ``rt_priority``: raise ``up``'s own (its router forwards every message);
    if granted, its agents raise theirs as they start, else say once that it was refused."""
    priority = launch.options.rt_priority
    if launch.options.clock != "realtime" or priority == "off":
        return
    granted = raise_priority(priority)
    if granted.granted:
        launch.children.env[PRIORITY_ENV] = priority
        launch.options.log(f"realtime priority: {granted.text} for up and its agents")
    else:
        launch.options.log(f"warning: {granted.text}")


def _not_ready(launch: _Launch) -> str:
    """Who is missing after the startup timeout, external agents with how to start them."""
    missing = launch.roster.not_ready()
    alive = launch.roster.alive_now()
    external = [a for a in missing if a in launch.options.external and a not in alive]
    named = [f"{a} (connected, no clock report)" if a in alive else a for a in missing]
    text = f"agents not ready after {launch.options.startup_timeout_s:g} s: {', '.join(named)}"
    if external:
        text += (f" (external, not connected: {', '.join(external)}; start each on its host, "
                 f"e.g. {launch.agent_command(external[0])})")
    return text


def run_clock(lead: _Launch, *others: _Launch, poll: Callable[[], None] | None = None) -> str:
    """Announce the start and run the clock to the end; return why it ended. With ``others``
    (the other levels of a hierarchy, on the lead's shared clock) for all of them at once;
    ``poll()`` as often as the launches are supervised (the site routers' restarts)."""
    launches = (lead, *others)
    options, result = lead.options, lead.result
    agents = sum(len(launch.topology.agents) for launch in launches)
    options.log(f"{agents} agents ready in {result.startup_s:.2f} s; "
                f"running {lead.config.scenario.duration_s:g} s of {options.clock} time")
    for launch in launches:
        launch.injector.start_faults()
    freeze_heap()         # the grid model, config and recorder live to the end (rt_tuning)
    t_start = time.perf_counter()
    epoch_ns = time.time_ns() + 200_000_000
    for launch in launches:
        launch.epoch_ns = epoch_ns
        launch._start_body = {"clock": options.clock, "epoch_ns": epoch_ns,
                              "speed": float(options.speed), "end_ns": result.end_ns,
                              "seed": launch.options.seed,
                              "tolerance_ns": launch.result.tolerance_ns}
        launch.announce_start()
    if lead.clock is not None:
        lead.clock.start()
    else:
        t_start += (epoch_ns - time.time_ns()) * 1e-9   # the run starts at the epoch
    end_wall_ns = epoch_ns + result.end_ns / options.speed
    reason = None
    while reason is None:
        done = lead.clock.finished if lead.clock is not None else \
            time.time_ns() >= end_wall_ns
        reason = "finished" if done else _first(launch.failure() for launch in launches)
        if reason in (None, "finished"):     # nobody left: not finished, whatever the clock
            reason = _early_end(launches) or reason
        if reason is None:
            if options.progress is not None:
                options.progress(lead.clock.now_ns() if lead.clock is not None else
                                 min(result.end_ns, lead.injector.realtime_ns()))
            for launch in launches:
                launch.injector.supervise()
                for agent in sorted(launch.roster.byes):   # gone before up said stop
                    launch.injector.said_bye_early(agent)
            if poll is not None:
                poll()
            lead.roster.wait(_POLL_S)
    for launch in launches:
        _reached(launch, reason, time.perf_counter() - t_start)
    return reason


def _first(reasons) -> str | None:
    """The first reason that is not None (evaluated one by one), or None."""
    return next((r for r in reasons if r is not None), None)


def _early_end(launches) -> str | None:
    """Why the run ends before its time: nobody left of the lead level, or of any level (a
    level of a hierarchy whose agents are all gone is an actuator lost to the level above,
    and the run goes on without it)."""
    ends = [launch.injector.early_end() for launch in launches]
    if ends[0] is not None or all(end is not None for end in ends):
        return next(end for end in ends if end is not None)
    return None


def _reached(launch: _Launch, reason: str, wall_time_s: float) -> None:
    """Note in the launch's result how long the clock ran and how far the run got."""
    result = launch.result
    result.wall_time_s = wall_time_s
    if reason == "finished":
        result.reached_ns = result.end_ns
    elif launch.injector.early_end() is not None:
        result.reached_ns = min(result.end_ns, max(launch.injector.gone_at.values()))
    elif launch.clock is not None:
        result.reached_ns = launch.clock.now_ns()
    else:
        result.reached_ns = min(result.end_ns, launch.injector.realtime_ns())


def shutdown(launch: _Launch, reason: str) -> None:
    """Announce the stop, collect the goodbyes, end every process (see the module docstring)."""
    options, roster, children = launch.options, launch.roster, launch.children
    t_stop = launch.clock.now_ns() if launch.clock is not None else 0
    launch.outbox.send(launch.keys.of("clock_stop"), t_stop, reason=reason)
    deadline = time.monotonic() + options.shutdown_timeout_s
    # realtime, not kept up: agents far behind, and the router's queue to the recorder, drain
    # their backlog first; while goodbyes or recorded messages still come, wait on, up to
    # _LATE_BYES times the timeout in all
    last = time.monotonic() + _LATE_BYES * options.shutdown_timeout_s
    again, heard = time.monotonic() + _STOP_AGAIN_S, _progress(launch)
    while time.monotonic() < deadline:
        # an external agent can say goodbye only while its session is up
        waiting = children.running() - (options.external - roster.alive_now())
        if not roster.without_bye() & waiting:
            break
        if options.clock == "realtime" and time.monotonic() > again:
            # a session that dropped under load and came back missed the stop: say it again
            launch.outbox.send(launch.keys.of("clock_stop"), t_stop, reason=reason)
            again = time.monotonic() + _STOP_AGAIN_S
            if _progress(launch) > heard and launch.overloaded():
                heard = _progress(launch)
                deadline = min(last, max(deadline, time.monotonic()
                                         + options.shutdown_timeout_s / 2))
        roster.wait(0.05)
    launch.withdraw_liveliness()   # every running agent's goodbye is in: they may close
    children.wait_all(max(_EXIT_GRACE_S, deadline - time.monotonic()))
    killed = children.kill_all()
    launch.killed_at_shutdown = set(killed)
    unsaid = [a for a in killed if a not in roster.byes]
    if unsaid:
        launch.result.problems.append(f"killed after the shutdown timeout: {', '.join(unsaid)}")
    if len(unsaid) < len(killed):
        options.log(f"{len(killed) - len(unsaid)} agent(s) still closing their sessions "
                    f"{_EXIT_GRACE_S:g} s after the shutdown timeout were ended (their goodbyes, "
                    "and everything before them, are in)")
    # wait (bounded) until the recorder has everything the agents say they published
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline and launch.recorder.failure is None:
        expected = roster.published(launch.outbox.counts())
        recorded = launch.recorder.counts()
        if all(recorded.get(k, 0) >= v for k, v in expected.items()):
            break
        roster.wait(0.01)


def _progress(launch: _Launch) -> tuple[int, int]:
    """Goodbyes heard and messages recorded so far (they grow while a backlog drains)."""
    return len(launch.roster.byes), sum(launch.recorder.counts().values())


def verify(launch: _Launch) -> None:
    """Compare published and recorded counts per key; record the agents' counts."""
    result = launch.result
    excused = _overloaded_agents(launch)
    unverified = _keys_of(launch, launch.injector.killed | excused)
    not_counted = unverified | {launch.keys.of("fault_request")}  # a person's commands: uncounted
    result.published = {k: v for k, v in launch.roster.published(launch.outbox.counts()).items()
                        if k not in not_counted}
    # the ready reports an agent sent before up heard its first one had no route to the
    # recorder yet (re-sent until heard): not counted, and the recording says how many
    before_contact = {launch.keys.of("clock_report", a): n
                      for a, n in launch.roster.unheard.items() if n}
    for key, n in before_contact.items():
        if key in result.published:
            result.published[key] -= n
    result.recorded = {k: v for k, v in launch.recorder.counts().items()
                       if k != launch.tap.rejected_key and k not in not_counted}
    if launch.injector.killed:
        result.problems.append(f"counts not verified on the {len(unverified)} key(s) of "
                               f"{', '.join(sorted(launch.injector.killed))} (a process of "
                               "theirs died and could not say what it sent)")
    missing = sorted(launch.roster.without_bye() - launch.injector.killed
                     - set(launch.injector.lost) - excused)
    if result.exit_code == EXIT_OK and missing:
        result.exit_code = EXIT_FAILED
        result.problems.append(f"no goodbye from {', '.join(missing)}")
    differences = sorted(k for k in set(result.published) | set(result.recorded)
                         if result.published.get(k, 0) != result.recorded.get(k, 0))
    differences = _short_by_overload(launch, differences)
    if result.exit_code == EXIT_OK and differences:
        shown = "; ".join(f"{k}: published {result.published.get(k, 0)}, recorded "
                          f"{result.recorded.get(k, 0)}" for k in differences[:3])
        result.problems.append(f"recording incomplete on {len(differences)} key(s): {shown}")
        result.exit_code = EXIT_FAILED
    if launch.tap.record_errors and result.exit_code == EXIT_OK:
        result.exit_code = EXIT_FAILED
    lost = sorted(set(launch.injector.lost) - excused)
    if lost:
        if result.exit_code == EXIT_OK:
            result.exit_code = EXIT_FAILED     # the run went on, but an agent died unplanned
        result.problems.append(f"agent(s) lost during the run: {', '.join(lost)}")
    uncounted = {launch.tap.rejected_key: "payloads the recorder rejected",
                 launch.keys.of("fault_request"): "a person's fault requests",
                 **{k: "a process of its agent died" for k in unverified}}
    records = [(PUBLISHED_METADATA, {k: str(v) for k, v in result.published.items()}),
               (UNCOUNTED_METADATA, uncounted)]
    if before_contact:      # per report key: ready reports sent before up heard the agent
        records.append((BEFORE_CONTACT_METADATA, {k: str(n) for k, n in before_contact.items()}))
    for name, data in records:
        if launch.recorder.failure is not None:     # nothing more can be written: said at
            return                                  # the close (_close_recording)
        try:
            launch.recorder.add_metadata(name, data)
        except RuntimeError:
            if launch.recorder.failure is None:
                raise


def _overloaded_agents(launch: _Launch) -> set[str]:
    """A realtime run that could not keep up: the agents without a goodbye, or lost, that
    did not crash -- faults of the overload, said as such, not failures of the run
    (:mod:`adnmesh.runtime.accounting`). None otherwise."""
    if launch.options.clock != "realtime" or not launch.overloaded():
        return set()
    codes = {a: p.returncode for a, p in launch.children.procs.items()}
    crashed = {a for a in launch.injector.lost if codes.get(a) not in (0, None)
               and a not in launch.killed_at_shutdown}
    recorded = launch.recorder.counts()
    per_agent = {a: sum(recorded.get(k, 0) for k in _keys_of(launch, [a]))
                 for a in launch.topology.agents}
    planned = launch.injector.killed - set(launch.injector.lost)   # injected kills: said
    account = account_agents(set(launch.topology.agents) - planned, set(launch.roster.byes),
                             set(launch.injector.lost), crashed, overloaded=True,
                             recorded=per_agent)
    launch.result.problems.extend(account.lines)
    launch.options.log(f"{len(account.said_bye)} of {len(launch.topology.agents) - len(planned)}"
                       f" agents said goodbye; {len(account.overloaded)} lost to the overload "
                       "(not real time)")
    return set(account.overloaded)


def _short_by_overload(launch: _Launch, differences: list[str]) -> list[str]:
    """The count differences that fail the run: in a realtime run that could not keep up,
    a key of an agent whose session dropped (what it sent while it was down is lost) with
    fewer recorded than published is a fault of the overload, said in one line instead."""
    if launch.options.clock != "realtime" or not launch.overloaded():
        return differences
    result, dropped = launch.result, _keys_of(launch, launch.dropped)
    short = [k for k in differences if k in dropped
             and result.recorded.get(k, 0) < result.published.get(k, 0)]
    if short:
        lost = sum(result.published.get(k, 0) - result.recorded.get(k, 0) for k in short)
        result.problems.append(
            f"{lost} message(s) on {len(short)} key(s) of {len(launch.dropped)} agent(s) whose "
            f"session dropped under the overload were lost while it was down (not real time): "
            f"{', '.join(sorted(launch.dropped))}")
    return [k for k in differences if k not in short]


def _keys_of(launch: _Launch, agents) -> set[str]:
    keys = launch.keys
    found = set()
    for agent in agents:
        found |= set(launch.topology.publishes(agent))
        found |= {keys.of("clock_report", agent), keys.of("agent_bye", agent)}
    return found


def _weak_callback(method: Callable[[zenoh.Sample], None]) -> Callable[[zenoh.Sample], None]:
    """``method`` as a Zenoh callback that does not keep its object alive: Zenoh may drop a
    callback after its undeclare without the GIL, and pyo3 then defers the decref to whenever
    it next holds the GIL, so a bound method would keep the whole run (its launch, roster,
    clock) alive after ``run`` returned. Calls after the object is gone do nothing."""
    ref = weakref.WeakMethod(method)

    def call(sample: zenoh.Sample) -> None:
        bound = ref()
        if bound is not None:
            bound(sample)
    return call


def _queued(channel):
    """The next sample queued on ``channel``, or None (none queued, or the subscriber was
    undeclared: Zenoh's ``try_recv`` raises once the channel is closed and empty)."""
    try:
        return channel.try_recv()
    except zenoh.ZError:
        return None


def run(options: UpOptions) -> UpResult:
    """Run the scenario of ``options.config`` as processes; see the module docstring."""
    return run_levels([options])[0]


def run_levels(levels: list[UpOptions], sites: tuple | list = ()) -> list[UpResult]:
    """Run several configs as processes around one router on one clock: the levels of a
    hierarchy (docs/hierarchy.md; every level's options with the same ``shared_clock`` and
    ``wake``, the first the lead: its router, endpoint, clock and progress), or one config
    alone. Each level has its own recorder, roster and faults; the run ends for all at once.
    ``sites``: the site routers (:class:`~adnmesh.runtime.site_router.SiteRouter`) linked to
    the lead's router before any agent starts, their planned restarts held on the clock."""
    launches = [_Launch(options) for options in levels]
    lead = launches[0]
    for launch in launches[1:]:           # one router, one interruption, one end for all
        launch.endpoint, launch.interrupted = lead.endpoint, lead.interrupted
        launch.result.end_ns = lead.result.end_ns
    previous = _catch_signals(lead.interrupted, lead.roster.changed)
    simulators = [DeviceSimulators(o.config, o.log) for o in levels]
    try:
        for launch in launches:
            _start_forkserver(launch)
        devices_down = _first(s.start(o.available_w, launch._model_params, o.startup_timeout_s)
                              for s, o, launch in zip(simulators, levels, launches))
        with zenoh.open(lead.router_config()) as session:
            try:
                for launch in launches:
                    launch.open(session)
                reason = devices_down or _first(s.start(lead.endpoint) for s in sites)
                for site in sites:
                    site.hold(lead.options.shared_clock)
                reason = reason or startup(*launches) or run_clock(
                    *launches, poll=lambda: [site.supervise(lead.options.shared_clock, launches)
                                             for site in sites])
                for launch in launches:
                    _stopped(launch.result, reason)
                    shutdown(launch, reason)
            finally:
                for launch in launches:
                    launch.close()
        for launch in launches:
            verify(launch)
    finally:
        for launch in launches:
            launch.children.kill_all()
            if launch.children.forkserver is not None:
                launch.children.forkserver.close()
        for simulator in simulators:
            simulator.stop()
        for site in sites:
            site.stop()
        for launch in launches:
            _close_recording(launch)
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        gc.unfreeze()     # run_clock froze the run's objects: collectable again once it ends
    return [_result(launch) for launch in launches]


def _result(launch: _Launch) -> UpResult:
    """The launch's result, completed from its roster, tap, sessions and clock."""
    result = launch.result
    result.byes = dict(launch.roster.byes)
    result.rejected = launch.tap.rejected
    result.sessions = launch.sessions.report()
    result.problems = launch.tap.problems + result.problems + [
        f"security: {line}" for line in result.sessions.unexpected]
    if launch.tap.rejected_unrecorded:
        result.problems.append(
            f"recording: {launch.tap.rejected_unrecorded} rejected payloads counted, not "
            f"recorded (a run keeps {REJECTED_RECORDS_KEPT} rejected-payload records)")
    if launch.clock is not None:
        result.grants = launch.clock.grants_issued
    return result


def _start_forkserver(launch: _Launch) -> None:
    """``runtime.agent_start: fork``: start the fork server now, so that it loads while ``up``
    opens its router (:mod:`adnmesh.runtime.forkserver`)."""
    if launch.config.runtime.agent_start != "fork" or \
            not set(launch.topology.agents) - set(launch.options.external):
        return
    server = ForkServer(say=launch.options.log)
    server.start(str(launch.config.path), dict(os.environ, **{PARENT_ENV: str(os.getpid())}))
    launch.children.forkserver = server


def recording_failure(recorder: Recorder) -> str:
    """``FILE: what failed`` of a recorder whose recording failed, in one line."""
    failure = recorder.failure
    what = (failure.strerror or str(failure)) if isinstance(failure, OSError) else \
        f"{type(failure).__name__}: {failure}"
    return " ".join(f"{recorder.path}: {what}".split())


def _close_recording(launch: _Launch) -> None:
    """Finish the recording; if it failed (during the run or now, finishing the file), say so
    in the result: exit code 1, one line, what the file keeps."""
    recorder, result = launch.recorder, launch.result
    try:
        recorder.close()
    except RuntimeError:
        if recorder.failure is None:
            raise
    if recorder.failure is None:
        return
    result.recording_failed = recording_failure(recorder)
    result.on_disk = recorder.on_disk
    if not result.reason.startswith(RECORDING_FAILED):     # it failed after the run ended
        result.problems.append(f"{RECORDING_FAILED} while finishing the file: "
                               f"{result.recording_failed}")
    if result.exit_code == EXIT_OK:
        result.exit_code = EXIT_FAILED


def _stopped(result: UpResult, reason: str) -> None:
    result.reason = reason
    if reason != "finished":
        result.exit_code = (EXIT_SIGINT if reason == "SIGINT" else
                            EXIT_SIGTERM if reason == "SIGTERM" else
                            EXIT_NOT_REALTIME if reason.startswith(NOT_REALTIME) else
                            EXIT_FAILED)
        result.problems.append(f"run stopped: {reason}")


def _catch_signals(interrupted: list[int], wake: threading.Event) -> dict:
    """Note SIGINT/SIGTERM in ``interrupted`` (main thread only); return the old handlers."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def on_signal(signum, frame):
        interrupted.append(signum)
        wake.set()

    return {signum: signal.signal(signum, on_signal) for signum in (signal.SIGINT,
                                                                    signal.SIGTERM)}
