"""An agent process: one :class:`~adnmesh.sim.node.Node` on a Zenoh session.

:class:`AgentProcess` is what every program in ``agents/`` runs once its session is open, in
three named phases:

1. :meth:`~AgentProcess.startup`: subscribe to the agent's keys, to its clock grants, to
   ``clock/start`` and ``clock/stop`` and to the liveliness of ``adnmesh up``; declare the
   liveliness token ``alive/<agent>``; once ``up``'s token is seen (at once if ``up`` runs; an
   agent started on another host may come first), send the first clock report: the agent is
   ready;
2. :meth:`~AgentProcess.run`: wait for ``clock/start``, then run on the announced clock:

   - ``sim``: a grant is processed as soon as the agent has received the messages it expects —
     every event before ``until_ns``, then a report (:mod:`adnmesh.sim.clock`) — by the Zenoh
     callback that completes it (the grant, or the last expected message), under the lock: no
     hand-over to another thread on the critical path;
   - ``realtime``: sim time is ``(wall - epoch) * speed`` (:mod:`adnmesh.runtime.realtime`);
     the main thread sleeps until the next event or message and processes what is due, measuring
     every event's delivery error per link (a message that arrives after its delivery time is
     processed at once and counted as late); an error beyond the announced tolerance is
     published at once as an ``overrun`` event. Its wake-ups are tightened
     (:mod:`adnmesh.runtime.os_scheduling`: timer slack, GIL switch interval, the priority ``up``
     hands over in :data:`~adnmesh.runtime.os_scheduling.PRIORITY_ENV`, an optional spin before
     each event);

   until ``clock/stop``, the disappearance of ``adnmesh up``, or SIGTERM/SIGINT;
3. :meth:`~AgentProcess.goodbye`: send what the agent wants sent at the end
   (:meth:`Agent.finish <adnmesh.control.base.Agent.finish>`), then ``clock/bye`` with what it
   published per key, what it rejected per key and reason, what its links lost, its stats and
   CPU time; wait (5 s at most) until ``adnmesh up`` withdraws its liveliness — it does so once it
   has every goodbye, so no goodbye is dropped by a session closed too early.

:meth:`~AgentProcess.close` undeclares everything; the caller closes the session. Everything an
agent sends in one window for one key goes out as one sample (:func:`adnmesh.wire.frames`).

An injected **kill** (a ``fault`` of kind ``kill``, applied by the node) ends the agent at its
sim time: the window is processed up to it, its messages published, the last clock report sent
with ``killed_ns``; once ``up`` has acknowledged that report on ``clock/kill/<agent>`` (so
that nothing it sent is lost with the process; 2 s at most), the process SIGKILLs itself. A
restarted agent is started with ``--resume-at-ns`` and begins at that sim time.
"""

from __future__ import annotations

import ctypes
import gc
import os
import re
import signal
import sys
import sysconfig
import threading
import time
import traceback
from collections import deque
from pathlib import Path

import zenoh

from adnmesh.runtime.children import EXIT_INTERNAL_ERROR, SESSION_GRACE_S
from adnmesh.runtime.realtime import OverrunWatch, ScaledClock
from adnmesh.runtime.window_times import WindowTimes
from adnmesh.runtime.os_scheduling import (PRIORITIES, PRIORITY_ENV, SpinPlan, freeze_heap,
                                       raise_priority, spin_ns_from_env, tighten_timers)
from adnmesh.sim.node import Node
from adnmesh.wire.envelope import MessageError, decode, encode, frames, split_frame
from adnmesh.wire.keys import Keys
from adnmesh.wire.outbox import Outbox

__all__ = ["AgentProcess", "add_agent_arguments", "die_with_parent", "load_config_or_exit",
           "open_session", "preload_config", "subscription_patterns"]

_WAIT_S = 1.0       # longest sleep between checks of the stop flag, s
_BYE_WAIT_S = 5.0   # longest wait after the goodbye for `up` to confirm it, s
_CATCH_UP_NS = 50_000_000   # realtime: sim time processed at most between two looks at the bus
_LET_IN_S = 5e-5            # ... and how long it then lets them have the lock, s
_KILL_WAIT_S = 2.0  # longest wait for `up` to acknowledge the last report before a kill, s
_UP_GRACE_S = SESSION_GRACE_S  # how long `up` may stay out of sight (a session reconnecting)
                               # before we stop; up waits as long for an external agent


_CRASH_FLUSH_S = 1.0  # longest wait for what an agent that failed had published, s
_CRASHING = threading.Lock()


def _where(exc: Exception) -> str:
    """`` (file.py:line)`` of the innermost frame of the agent's own code in the traceback of
    ``exc`` -- adnmesh's, or any outside the standard library and site-packages (the innermost
    of all if none is) --, or ``""``."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    stdlib = sysconfig.get_paths()["stdlib"]

    def own(filename: str) -> bool:
        parts = set(Path(filename).parts)
        return bool({"adnmesh", "agents"} & parts) or (
            "site-packages" not in parts and not filename.startswith(stdlib))

    frame = ([f for f in frames if own(f.filename)] or frames)[-1]
    return f" ({Path(frame.filename).name}:{frame.lineno})"


def add_agent_arguments(parser) -> None:
    """The arguments every agent program takes besides its own: the connection flags
    (:func:`adnmesh.runtime.bus.add_connection_arguments`), ``--resume-at-ns`` (set by
    ``adnmesh up`` for a restarted agent) and ``--levels FILE --level GRID`` (set by ``adnmesh
    up`` for a hierarchy's run: :mod:`adnmesh.runtime.place`)."""
    from adnmesh.runtime.bus import add_connection_arguments
    add_connection_arguments(parser)
    parser.add_argument("--resume-at-ns", type=int, default=0, metavar="NS",
                        help="begin at this sim time, ns (a restarted agent; set by adnmesh up)")
    parser.add_argument("--connect-timeout", type=float, default=0.0, metavar="S",
                        help="keep trying to reach the router for S seconds (default 0: once)")
    parser.add_argument("--levels", metavar="FILE",
                        help="a hierarchy's run: the levels file adnmesh up wrote "
                        "(adnmesh.runtime.place)")
    parser.add_argument("--level", metavar="GRID",
                        help="with --levels: the grid of this agent's level")


def open_session(args, identity: str) -> zenoh.Session:
    """Open the Zenoh session of agent ``identity`` from its flags (the secure profile with
    ``--certs``); on a bad flag or a router that cannot be reached, print one line and exit
    with code 2 or 1."""
    from adnmesh.errors import UsageError
    from adnmesh.runtime.bus import session_config
    try:
        if not 0 <= args.connect_timeout <= 86400:
            raise UsageError(f"--connect-timeout must be in [0, 86400] s, got "
                             f"{args.connect_timeout:g}")
        config = session_config(args, identity)
        priority = os.environ.get(PRIORITY_ENV)
        if priority in PRIORITIES:    # before the session's threads exist: they inherit it
            raise_priority(priority)  # up has said whether it is granted (the same for all)
        if args.connect_timeout:
            config.insert_json5("connect/timeout_ms", str(int(args.connect_timeout * 1000)))
        return zenoh.open(config)
    except UsageError as exc:
        print(f"adnmesh agent: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except zenoh.ZError as exc:
        where = ", ".join(args.connect or ["the default endpoint"])
        print(f"adnmesh agent {identity}: cannot connect to {where}: "
              f"{str(exc).split(' at ')[0]}", file=sys.stderr)
        raise SystemExit(1) from None


_PRELOADED: dict[str, tuple[tuple, object]] = {}
"""Configs loaded before the agent was forked (:mod:`adnmesh.runtime.forkserver`): absolute
path -> (the file's identity then, the config)."""


def _file_identity(path: str) -> tuple:
    stat = os.stat(path)
    return stat.st_ino, stat.st_size, stat.st_mtime_ns


def preload_config(path: str):
    """Load and validate the config at ``path`` for the agents forked from this process
    (:func:`load_config_or_exit` then takes it while the file is unchanged) and return it; a
    config that does not load is left to each agent to say (None)."""
    from adnmesh.config import load_config
    from adnmesh.errors import ConfigError
    try:
        identity = _file_identity(path)
        config = load_config(path)
    except (OSError, ConfigError):
        return None
    _PRELOADED[os.path.abspath(path)] = (identity, config)
    return config


def load_config_or_exit(path: str):
    """Load the adnmesh config (the one loaded before this agent was forked, if its file is
    unchanged); on an error print one line and exit with code 2."""
    from adnmesh.config import load_config
    from adnmesh.errors import ConfigError
    preloaded = _PRELOADED.get(os.path.abspath(path))
    try:
        if preloaded is not None and preloaded[0] == _file_identity(path):
            return preloaded[1]
    except OSError:
        pass
    try:
        return load_config(path)
    except ConfigError as exc:
        print(f"adnmesh agent: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def die_with_parent() -> None:
    """If started by ``adnmesh up`` (env ``ADNMESH_PARENT_PID``), get SIGKILL when it dies
    (Linux ``PR_SET_PDEATHSIG``), and exit at once if it is already gone."""
    parent = os.environ.get("ADNMESH_PARENT_PID")
    if not parent or not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != int(parent):
        os._exit(1)


_DER_KEY = re.compile(r"^(.+/der/)[^/*$]+(/[^*$]+)$")


def subscription_patterns(keys, wildcards: bool = True) -> dict[str, frozenset | None]:
    """The key expressions to subscribe to for ``keys``: key expression -> the keys it stands
    for (None: the key itself). With ``wildcards``, two or more keys that differ only in the
    DER id (``.../der/<id>/state``) become one ``.../der/*/state``."""
    groups: dict[tuple[str, str], list[str]] = {}
    out: dict[str, frozenset | None] = {}
    for key in keys:
        found = _DER_KEY.match(key) if wildcards else None
        if found is None:
            out[key] = None
        else:
            groups.setdefault(found.groups(), []).append(key)
    for (head, tail), members in groups.items():
        if len(members) == 1:
            out[members[0]] = None
        else:
            out[f"{head}*{tail}"] = frozenset(members)
    return out


def _only(members: frozenset, callback):
    """``callback`` for the samples of a wildcard subscriber on the keys of ``members``
    only (a key of the pattern that is not one of the agent's is not its message)."""
    def on(sample: zenoh.Sample) -> None:
        if str(sample.key_expr) in members:
            callback(sample)
    return on


class AgentProcess:
    """Runs ``node`` on ``session`` (see the module docstring).

    Parameters
    ----------
    session : zenoh.Session
    node : Node
        The agent, its links and counts.
    grid : str
        The config's grid (bus keys ``adn/<grid>/...``).
    publishers : bool
        Declare one publisher per key (default). False: put every sample with its full key
        from the session, as the secure profile does: with Zenoh's access control on
        (eclipse-zenoh 1.10), the router dropped the samples of a publisher declared in the
        first milliseconds of a session in about one session in six (measured: a router with
        the run's access control, a client that declares a publisher as soon as its session
        is open and puts three samples: samples dropped in 3 and in 4 of 20 sessions in two
        trials; in 0 of 20 with ``session.put``, or with the publisher declared 50 ms later).
    """

    def __init__(self, session: zenoh.Session, node: Node, grid: str,
                 publishers: bool = True, hosted: bool = False) -> None:
        self.session = session
        self.hosted = hosted                 # one of several agents of a process (runtime.host)
        self.left = False                    # hosted: ended by an injected kill
        self.publishers = publishers
        self.node = node
        self.keys = Keys(grid)
        self.agent = node.agent_id
        self._grant_key = self.keys.of("clock_grant", self.agent)   # a grant from a host
        self.lock = threading.Condition()    # guards everything below and the node
        self.grants: deque = deque()
        self.start: object | None = None     # the clock_start message
        self.stop: str | None = None         # why the run stopped
        self.mode: str | None = None         # "sim" / "realtime" once started
        self.up_gone = False                 # adnmesh up withdrew its liveliness
        self._up_gone_at: float | None = None   # since when (monotonic s), until it is back
        self.reconnects = 0                  # times up came back into sight
        self.said_bye = False
        self._wake_ns: int | None = None      # realtime: the event time the main thread waits for
        self._sleeping = False               # realtime: ... and it is waiting for it
        self._arrivals: deque = deque()      # realtime: samples not yet taken by the node
        self.dying = False                   # an injected kill was reached
        self.kill_acked = False              # ... and up has the last report
        self.reported = False                # the first report is sent (up was seen)
        self.window_cpu_s = 0.0              # CPU time spent processing grants
        self.window_times = WindowTimes.from_env(self.agent)   # the stage timeline, if asked
        # Zenoh samples put and taken: data, and the clock protocol's own (reports, grants)
        self.samples = {"data_out": 0, "clock_out": 0, "data_in": 0, "clock_in": 0}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._own = Outbox(node.agent_id)    # what this wrapper sends itself (clock protocol)
        self._handles: list = []
        self._signals: dict = {}
        self.overruns: OverrunWatch | None = None
        # the Zenoh callback for the liveliness of adnmesh up (see startup)
        self.on_up_alive = self.guarded(self._on_up_alive)

    # -- phases ------------------------------------------------------------------------------

    def serve(self) -> int:
        """Startup, run, goodbye, close; return the exit code (0)."""
        die_with_parent()
        self.startup()
        try:
            self.run_to_end()
        finally:
            self.close()
        return 0

    def run_to_end(self) -> None:
        """Run, then the goodbye -- or, after an injected kill, the end of the agent (the
        process is SIGKILLed; a hosted agent leaves its process, which goes on)."""
        try:
            self.run()
            if self.dying:
                self._die()
            else:
                self.goodbye()
                self._write_window_times()
        except Exception as exc:   # the agent's own code (realtime: on this thread)
            self._crash(exc)

    def _write_window_times(self) -> None:
        """Write the windows' wall times, if asked (:mod:`.window_times`); a directory that
        cannot take them is said in one line."""
        if self.window_times is None:
            return
        with self.lock:
            try:
                self.window_times.write()
            except OSError as exc:
                self._say(f"cannot write the window times to {self.window_times.directory}: "
                          f"{exc.strerror or exc}")

    def guarded(self, callback):
        """``callback`` for Zenoh: an exception in it ends the process (:meth:`_crash`)."""
        def run(sample: zenoh.Sample) -> None:
            try:
                callback(sample)
            except Exception as exc:
                self._crash(exc)
        return run

    def _crash(self, exc: Exception) -> None:
        """Say in one line where the agent's code failed, give what is already published
        :data:`_CRASH_FLUSH_S` to leave (the session is closed on another thread: the calling
        one may be Zenoh's), and end the process with :data:`EXIT_INTERNAL_ERROR` (see there).
        A second thread that fails meanwhile waits here: one line, one exit."""
        with _CRASHING:
            self._say(f"internal error: {type(exc).__name__}: {exc}{_where(exc)}; the agent "
                      "stops")
            closer = threading.Thread(target=self._close_quietly, daemon=True)
            closer.start()
            closer.join(_CRASH_FLUSH_S)
            os._exit(EXIT_INTERNAL_ERROR)

    def _say(self, text: str) -> None:
        """One line on stderr, at once: ``adnmesh agent <id>: <text>``."""
        print(f"adnmesh agent {self.agent}: {text}", file=sys.stderr, flush=True)

    def _close_quietly(self) -> None:
        try:
            self.session.close()
        except Exception:   # closing a session mid-callback: whatever left, left
            pass

    def routes(self) -> dict[str, object]:
        """What the agent subscribes to: key expression -> its Zenoh callback (data, then the
        clock's). In the open profile the keys of every DER of one kind (``der/<id>/state``
        for the measurement: 1,000 keys with 1,000 DERs) are one wildcard subscriber whose
        callback passes on only those keys (:func:`subscription_patterns`): one Zenoh delivery
        thread instead of one per key. The secure profile's access control names exact keys."""
        keys = self.keys
        on_data, on_clock = self.guarded(self._on_data), self.guarded(self._on_clock)
        found = {}
        for expr, members in subscription_patterns(self.node.subscriptions,
                                                   self.publishers).items():
            found[expr] = on_data if members is None else _only(members, on_data)
        found.update({key: on_clock for key in (
            keys.of("clock_grant", self.agent), keys.of("clock_start"), keys.of("clock_stop"),
            keys.of("clock_kill", self.agent))})
        return found

    def startup(self, subscribe: bool = True) -> None:
        """Subscribe, declare the publishers and liveliness, and send the first report (see
        the module docstring). Hosted (``subscribe`` False), the host subscribes for it
        (:meth:`routes`, :attr:`on_up_alive`) and the agent only declares its publishers and
        liveliness.

        Every key the agent sends gets its publisher here, on the main thread, before the
        agent is ready: not in its first window, on a Zenoh callback thread while samples
        stream in (a 1,000-DER run whose hosts declared 2,000 publishers so in its first window
        could stall there for good; docs/runtime.md#sim-default-deterministic)."""
        if not self.hosted and threading.current_thread() is threading.main_thread():
            self._signals = {s: signal.signal(s, self._on_signal)   # Ctrl-C stops it too
                             for s in (signal.SIGTERM, signal.SIGINT)}
        keys, session = self.keys, self.session
        if self.publishers:   # declared here, not in a window: see above
            for key in self.node.sends():
                self._publisher(key)
        if subscribe:
            self._handles = [session.declare_subscriber(key, callback)
                             for key, callback in self.routes().items()]
        self._handles.append(session.liveliness().declare_token(keys.liveliness(self.agent)))
        # up declares its token after its recorder's subscriber, but behind a site router the
        # token can still arrive before the route: reports before the first one up hears are
        # re-sent until the start and left out of up's counts (launcher.verify)
        if subscribe:
            self._handles.append(session.liveliness().declare_subscriber(
                keys.liveliness("up"), self.on_up_alive, history=True))
        freeze_heap()     # what startup built lives to the end: no collection walks it again

    def run(self) -> None:
        """Wait for the start, then run on its clock until the run stops."""
        with self.lock:
            while self.start is None and not self._up_lost():
                self.lock.wait(_WAIT_S)
                if self.start is None and self.reported and not self._up_lost():
                    self._report()   # again until the start: a first report can be lost
            if self.stop is not None:
                return
            self.node.reseed(self.start.seed)
            self.mode = self.start.clock
            self.node.agent.on_clock(self.mode)
            if self.mode == "sim":
                self._run_granted()
                while not self._up_lost() and not self.dying:
                    self.lock.wait(_WAIT_S)
            else:
                self.node.strict = False
        if self.mode == "realtime":
            self._run_realtime()

    def _die(self) -> None:
        """The injected kill: wait (bounded) until ``up`` has the last report, then SIGKILL
        the process -- or, hosted, leave it: withdraw the agent's liveliness and take nothing
        more (its process goes on with the other agents)."""
        self._write_window_times()   # its windows are done: written before the wait, so
        deadline = time.monotonic() + _KILL_WAIT_S   # the kill follows up's ack at once
        with self.lock:
            while not self.kill_acked and time.monotonic() < deadline:
                self.lock.wait(max(0.0, deadline - time.monotonic()))
            if self.hosted:
                self.left = True
        if not self.hosted:
            os.kill(os.getpid(), signal.SIGKILL)
        self.close()

    def goodbye(self) -> None:
        """Send the agent's last messages and the goodbye; wait (bounded) for ``up``'s ack."""
        with self.lock:
            self._take_arrivals()
            self.mode, self.said_bye = None, True
            self._publish_all(self.node.finish())
            node, counts = self.node, self.node.counts
            bye_key = self.keys.of("agent_bye", self.agent)
            published = {**counts.published, **self._own.counts()}
            published[bye_key] = published.get(bye_key, 0) + 1
            stats = {**node.agent.stats(), "cpu_s": time.process_time(),
                     "window_cpu_s": self.window_cpu_s, "late": float(counts.late),
                     "received": float(counts.received),
                     "overruns": float(self.overruns.count if self.overruns else 0),
                     "reconnects": float(self.reconnects),
                     **{f"samples_{k}": float(v) for k, v in self.samples.items()}}
            self._send_own(bye_key, published=published, rejected=counts.rejected,
                           lost=counts.lost, stats=stats, latency=node.latency.to_wire())
            deadline = time.monotonic() + _BYE_WAIT_S
            while not self.up_gone and time.monotonic() < deadline:
                self.lock.wait(min(_WAIT_S, max(0.0, deadline - time.monotonic())))

    def close(self) -> None:
        """Undeclare subscribers and the liveliness token; restore the signal handlers and
        the collector (a process that goes on, e.g. a test's, collects its objects again)."""
        for handle in reversed(self._handles):
            handle.undeclare()
        self._handles = []
        for signum, handler in self._signals.items():
            signal.signal(signum, handler)
        self._signals = {}
        gc.unfreeze()

    # -- Zenoh callbacks -----------------------------------------------------------------------

    def _on_data(self, sample: zenoh.Sample) -> None:
        # decoded and queued in the node at once, while other agents still run: a window later
        # only processes events (the node orders them by delivery time, not by arrival)
        if self.left:
            return
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        self.samples["data_in"] += 1
        if self.mode == "realtime":
            # never wait for the main thread while it processes (Zenoh's receive thread would
            # back up behind it): queue the sample; wake the main thread only if it sleeps
            # (it drains the queue before it sleeps, after it says so: nothing is missed)
            self._arrivals.append((key, data))
            if self._sleeping:
                with self.lock:
                    self._take_arrivals()
                    if self._due_sooner():
                        self.lock.notify()
            return
        with self.lock:
            self.node.receive_sample(key, data)
            if self.mode == "sim" and self.grants:
                self._run_granted()

    def _take_arrivals(self) -> None:   # with the lock held
        arrivals, receive = self._arrivals, self.node.receive_sample
        while arrivals:
            key, data = arrivals.popleft()
            receive(key, data)

    def _due_sooner(self) -> bool:
        """Realtime: the node's next event is due before the main thread means to wake (a
        message due later need not wake it: most arrive a link delay early)."""
        wake = self._wake_ns
        if wake is None:
            return True
        next_ns = self.node.next_event_ns()
        return next_ns is not None and next_ns < wake

    def _on_clock(self, sample: zenoh.Sample) -> None:
        if self.left:
            return
        key = str(sample.key_expr)
        self.samples["clock_in"] += 1
        for payload in split_frame(sample.payload.to_bytes()):
            self._take_clock_payload(key, payload)

    def take_grant(self, payload: bytes, counted: bool) -> None:
        """A grant of this agent that came in its host's sample of grants
        (:mod:`adnmesh.runtime.host`); ``counted``: count that sample as this agent's (one
        agent of the sample counts it)."""
        if self.left:
            return
        self.samples["clock_in"] += counted
        self._take_clock_payload(self._grant_key, payload)

    def _take_clock_payload(self, key: str, payload: bytes) -> None:
        try:
            message = decode(key, payload)
        except MessageError as exc:
            self.reject(key, exc.reason)
            return
        with self.lock:
            self._take_clock(key, message)

    def reject(self, key: str, reason: str) -> None:
        """Count a message on ``key`` rejected for ``reason`` (by the host, for this agent)."""
        with self.lock:
            self.node.gate.reject(key, reason)

    def _take_clock(self, key: str, message) -> None:   # with the lock held
        if message.type == "clock_grant":      # processed here: the main thread sleeps on
            if self.window_times is not None:
                self.window_times.granted(message.until_ns)
            self.node.take_cut(message.cut_keys, message.cuts)
            self.grants.append(message)
            self._run_granted()
            return
        if message.type == "clock_start" and self.start is None:
            self.start = message
        elif message.type == "clock_stop" and key == self.keys.of("clock_kill", self.agent):
            self.kill_acked = True
        elif message.type == "clock_stop":
            self.stop = self.stop or message.reason
        self.lock.notify()

    def _on_up_alive(self, sample: zenoh.Sample) -> None:
        # the first sight of up's token: the first report (ready). up's token goes when up
        # ends -- or when this session lost the router under load and reconnects: the agent
        # goes on, and stops only if up stays away (_UP_GRACE_S)
        if self.left:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                if not self.up_gone:             # a repeated DELETE: away since the first
                    self.up_gone, self._up_gone_at = True, time.monotonic()
            elif not self.reported:
                self.reported = True
                self._report()
            elif self.up_gone and not self.said_bye:
                away = time.monotonic() - self._up_gone_at
                self.up_gone, self._up_gone_at = False, None
                self.reconnects += 1
                # said at once: messages that crossed the gap are lost, and on the sim clock
                # a run that then stalls waiting for one should say why
                self._say(f"adnmesh up back in sight after {away:.1f} s (the session lost "
                          "the router; what crossed the gap is lost)")
            self.lock.notify()

    def _up_lost(self) -> bool:
        """``up`` has been out of sight longer than the grace (then the run stops)."""
        if self._up_gone_at is not None and time.monotonic() - self._up_gone_at > _UP_GRACE_S:
            self.stop = self.stop or "adnmesh up is gone"
        return self.stop is not None

    def _on_signal(self, signum, frame) -> None:
        # no lock in a signal handler: the main thread wakes within _WAIT_S and sees the flag
        self.stop = self.stop or signal.Signals(signum).name

    # -- internals (with the lock held) --------------------------------------------------------

    def _publish(self, key: str, payload: bytes, attachment: bytes | None = None,
                 clock: bool = False) -> None:
        self.samples["clock_out" if clock else "data_out"] += 1
        if not self.publishers:
            self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK,
                             attachment=attachment)
            return
        self._publisher(key).put(payload, attachment=attachment)

    def _publisher(self, key: str) -> zenoh.Publisher:
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        return publisher

    def _publish_all(self, out: list[tuple[str, bytes]]) -> None:
        for key, frame in frames(out):
            self._publish(key, frame)

    def _send_own(self, key: str, **body) -> None:
        """Send a clock-protocol message of this wrapper (report, goodbye) at the node's time."""
        self._publish(key, self._own_payload(key, body), clock=True)

    def _own_payload(self, key: str, body: dict) -> bytes:
        return encode(self._own.send(key, self.node.now_ns, body))

    def _report_payload(self) -> bytes:
        """The clock report of the window just processed, encoded (sent at the node's time)."""
        r = self.node.report()
        body = {"next_ns": r.next_ns, "granted_ns": self.node.granted_ns,
                "received": r.received, "sent": {k: tuple(v) for k, v in r.sent.items()}}
        if r.killed_ns is not None:
            body["killed_ns"] = r.killed_ns
        if r.cuts:
            body["cuts"] = r.cuts
        return self._own_payload(self.keys.of("clock_report", self.agent), body)

    def _report(self) -> None:
        """Send the clock report on its own key (the first one, a kill in realtime)."""
        self._publish(self.keys.of("clock_report", self.agent), self._report_payload(),
                      clock=True)

    def _run_window(self, until_ns: int) -> None:
        """Process every event before ``until_ns``, publish what the window sent and report.

        The report rides as the Zenoh attachment of the window's last sample (``up``, which
        records every sample, takes it from there: :meth:`RecorderTap.take_attached
        <adnmesh.runtime.tap.RecorderTap.take_attached>`): one sample a window fewer for the
        agent, the router and ``up``; receivers of the sample ignore the attachment. The samples of a session reach
        ``up`` in the order they were put, so the report still comes after the data it counts.
        A window that sent nothing reports on the report's own key."""
        out = frames(self.node.advance(until_ns))
        if self.node.killed:
            self.dying = True
            self.lock.notify()
        report = self._report_payload()
        if not out:
            self._publish(self.keys.of("clock_report", self.agent), report, clock=True)
            return
        for key, frame in out[:-1]:
            self._publish(key, frame)
        key, frame = out[-1]
        self._publish(key, frame, attachment=report)

    def _run_granted(self) -> None:
        """Every grant whose expected messages are all here: process its window, report."""
        grants = self.grants
        while (self.mode == "sim" and grants and self.stop is None and not self.dying
               and self.node.counts.received >= grants[0].expect):
            until_ns, times = grants.popleft().until_ns, self.window_times
            began_ns = 0 if times is None else time.monotonic_ns()
            cpu = time.thread_time_ns()
            self._run_window(until_ns)
            spent = time.thread_time_ns() - cpu
            self.window_cpu_s += spent * 1e-9
            if times is not None:
                times.ran(until_ns, began_ns, time.monotonic_ns(), spent)

    def _run_realtime(self) -> None:
        """Process every event at its time on the scaled wall clock (:mod:`.realtime`); an
        agent with zero-delay inputs (the measurement) processes each instant ``tolerance``
        later, so that what its senders send at that instant is there (:mod:`.realtime`)."""
        start, node = self.start, self.node
        hold = start.tolerance_ns if node.instant_inputs else 0
        clock = ScaledClock(start.epoch_ns + int(hold / start.speed), start.speed)
        watch = self.overruns = OverrunWatch(self.agent, start.tolerance_ns, start.speed)
        tighten_timers()
        spin = SpinPlan(spin_ns_from_env(), time.monotonic_ns)
        with self.lock:
            while not self._up_lost():
                self._take_arrivals()
                now = clock.now_ns()
                if now >= 0:
                    # behind the clock, catch up a slice at a time, letting the callbacks in
                    # between (messages, the stop, Zenoh's own keep-alive traffic)
                    due = node.next_event_ns()
                    until = min(now, start.end_ns) if due is None else \
                        min(now, start.end_ns, due + _CATCH_UP_NS)
                    self._publish_all(node.advance(until + 1, clock.now_ns))
                    self._note_overrun(watch.check(now, node.take_worst_late()))
                    if until < min(now, start.end_ns) and not node.killed:
                        self._let_callbacks_in()
                        continue
                if node.killed:
                    self.dying = True
                    self._report()
                    return
                self._sleep_until(node.next_event_ns(), clock, spin)

    def _sleep_until(self, next_ns: int | None, clock: ScaledClock, spin: SpinPlan) -> None:
        """Realtime: sleep until sim time ``next_ns`` (at most :data:`_WAIT_S`), the last
        ``spin.spin_ns`` of it polling the clock, or until a sample wakes us."""
        if next_ns is None or next_ns > self.start.end_ns:
            wait_s = _WAIT_S
        else:
            target = clock.monotonic_ns(next_ns)
            wait_s = min(_WAIT_S, spin.sleep_s(target))
            if wait_s <= 0:      # within the spin: poll (samples queue meanwhile)
                spin.spin(target, lambda: bool(self._arrivals))
                return
        self._wake_ns = next_ns if wait_s < _WAIT_S else None
        self._sleeping = True
        if not self._arrivals:        # none came since they were taken
            self.lock.wait(wait_s)
        self._sleeping, self._wake_ns = False, None

    def _let_callbacks_in(self) -> None:
        """Release the lock for a moment (the main thread holds it while it processes)."""
        self.lock.wait(_LET_IN_S)

    def _note_overrun(self, body: dict | None) -> None:
        if body is not None:
            self._publish_all(self.node.send_now(self.keys.of("event", self.agent), body))
