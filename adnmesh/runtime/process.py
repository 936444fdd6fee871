"""An agent process: one :class:`~adnmesh.runtime.node.Node` on a Zenoh session.

:func:`serve` is what every program in ``agents/`` runs after opening its session. It

1. subscribes to the agent's keys, to its clock grants, to ``clock/start`` and ``clock/stop``,
   and to the liveliness of ``adnmesh up``;
2. declares its liveliness token ``alive/<agent>`` and sends its first clock report: the agent is
   ready;
3. waits for ``clock/start``, then runs on the announced clock:

   - ``sim``: a grant is processed as soon as the agent has received the messages it expects —
     every event before ``until_ns``, then a report (:mod:`adnmesh.runtime.clock`) — by the
     Zenoh callback that completes it (the grant, or the last expected message), under the
     inbox lock: no hand-over to another thread on the critical path;
   - ``realtime``: sim time is ``(wall - epoch) * speed``; the main thread sleeps until the next
     event or message and processes what is due (messages that arrive after their delivery time
     are processed at once and counted as late);

4. on ``clock/stop`` (or when ``adnmesh up`` disappears, or on SIGTERM/SIGINT) sends
   ``clock/bye`` with what it published per key, what it rejected and lost, its stats and CPU
   time, waits (5 s at most) until ``adnmesh up`` withdraws its liveliness — it does so once it
   has every goodbye, so no goodbye is dropped by a session closed too early — and returns;
   the caller closes the session.

Everything an agent sends in one window for one key goes out as one sample
(:func:`~adnmesh.runtime.messages.frames`). An injected crash (``runtime.faults.crash``) records
a ``fault`` message and ends the process at once with exit code :data:`EXIT_CRASH`, without a
goodbye.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from collections import deque

import zenoh

from adnmesh.runtime.messages import (
    Keys,
    MessageError,
    decode,
    encode,
    frames,
    message_type,
    split_frame,
)
from adnmesh.runtime.node import AgentCrash, Node

__all__ = ["EXIT_CRASH", "die_with_parent", "load_config_or_exit", "serve"]

EXIT_CRASH = 70
"""Exit code of an agent that crashed on purpose (injected fault)."""

_WAIT_S = 1.0  # longest sleep between checks of the stop flag, s
_BYE_WAIT_S = 5.0  # longest wait after the goodbye for `up` to confirm it, s


def load_config_or_exit(path: str):
    """Load the adnmesh config; on an error print one line and exit with code 2."""
    from adnmesh.config import load_config
    from adnmesh.errors import ConfigError
    try:
        return load_config(path)
    except ConfigError as exc:
        raise SystemExit(f"adnmesh agent: error: {exc}") from None


class _Inbox:
    """What the Zenoh callbacks and the main thread share (guarded by ``cond``)."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.received = 0
        self.grants: deque = deque()
        self.start: dict | None = None
        self.stop: str | None = None
        self.rejected = 0
        self.sim = False          # running on the sim clock: callbacks process grants
        self.realtime = False     # running on the wall clock: data wakes the main thread
        self.window_cpu_s = 0.0   # CPU time spent processing grants (this agent's own work)
        self.up_gone = False      # adnmesh up withdrew its liveliness (it has every goodbye)


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


def serve(session: zenoh.Session, node: Node, grid: str) -> int:
    """Run ``node`` on ``session`` until the run stops; return the exit code (0).

    On the sim clock, the callback that completes a grant (the grant itself, or the message that
    brings the received count to what the grant expects) processes the window at once, on its
    own thread, under the inbox lock: no hand-over to the main thread on the critical path.
    """
    die_with_parent()
    keys = Keys(grid)
    agent = node.agent_id
    inbox = _Inbox()
    cond = inbox.cond
    block = zenoh.CongestionControl.BLOCK
    publishers: dict[str, zenoh.Publisher] = {}
    own: dict[str, int] = {}     # what this wrapper publishes itself (clock traffic)
    own_seq: dict[str, int] = {}

    def publish(key: str, payload: bytes) -> None:
        pub = publishers.get(key)
        if pub is None:
            pub = publishers[key] = session.declare_publisher(key, congestion_control=block)
        pub.put(payload)

    def send_own(key: str, body: dict) -> None:
        seq = own_seq.get(key, 0)
        own_seq[key] = seq + 1
        own[key] = own.get(key, 0) + 1
        publish(key, encode(message_type(key), agent, seq, node.now_ns, node.now_ns, body))

    def report() -> None:
        r = node.report()
        send_own(keys.report(agent), {"next_ns": r.next_ns, "granted_ns": node.granted_ns,
                                      "received": r.received,
                                      "sent": {k: list(v) for k, v in r.sent.items()}})

    def run_until(until_ns: int) -> None:  # with cond held
        try:
            out = node.advance(until_ns)
        except AgentCrash:
            for key, payload in node.emit_now(keys.fault(agent), {
                    "fault": "crash", "agent": agent, "active": True}):
                publish(key, payload)
            os._exit(EXIT_CRASH)
        for key, frame in frames(out):
            publish(key, frame)

    def run_granted() -> None:  # with cond held: every grant whose messages are all here
        grants = inbox.grants
        while inbox.sim and grants and inbox.stop is None \
                and inbox.received >= grants[0]["expect"]:
            cpu = time.thread_time()
            grant = grants.popleft()
            run_until(grant["until_ns"])
            report()
            inbox.window_cpu_s += time.thread_time() - cpu

    def on_data(sample: zenoh.Sample) -> None:
        # decoded and queued in the node at once, while other agents still run: a window later
        # only processes events (the node orders them by delivery time, not by arrival)
        key = str(sample.key_expr)
        envelopes = split_frame(sample.payload.to_bytes())
        with cond:
            for payload in envelopes:
                node.receive(key, payload)
            inbox.received += len(envelopes)
            if inbox.sim:
                if inbox.grants:
                    run_granted()
            elif inbox.realtime:
                cond.notify()

    def on_clock(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            message = decode(key, sample.payload.to_bytes())
        except MessageError:
            with cond:
                inbox.rejected += 1
            return
        with cond:
            if message.type == "clock_grant":   # processed here: the main thread sleeps on
                inbox.grants.append(message.body)
                run_granted()
                return
            if message.type == "clock_start":
                inbox.start = message.body
            elif message.type == "clock_stop":
                inbox.stop = inbox.stop or message.body["reason"]
            cond.notify()   # what the main thread waits for

    def on_up_alive(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            with cond:
                inbox.up_gone = True
                inbox.stop = inbox.stop or "adnmesh up is gone"
                cond.notify()

    def on_signal(signum, frame) -> None:
        # no lock in a signal handler: the main thread wakes within _WAIT_S and sees the flag
        inbox.stop = inbox.stop or signal.Signals(signum).name

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)   # run by hand: Ctrl-C stops it the same way
    subscribers = [session.declare_subscriber(key, on_data) for key in node.subscriptions]
    subscribers += [session.declare_subscriber(key, on_clock)
                    for key in (keys.grant(agent), keys.start, keys.stop)]
    subscribers.append(session.liveliness().declare_subscriber(keys.liveliness("up"),
                                                               on_up_alive))
    token = session.liveliness().declare_token(keys.liveliness(agent))
    with cond:
        report()
    try:
        with cond:
            while inbox.start is None and inbox.stop is None:
                cond.wait(_WAIT_S)
            start = inbox.start
            if start is not None and inbox.stop is None:
                node.reseed(start["seed"])
                if start["clock"] == "sim":
                    inbox.sim = True
                    run_granted()
                else:
                    node.strict = False
                    inbox.realtime = True
        if start is not None and start["clock"] == "sim":
            with cond:
                while inbox.stop is None:
                    cond.wait(_WAIT_S)
        elif start is not None:
            _run_realtime(inbox, node, run_until, start)
        with cond:
            inbox.sim = inbox.realtime = False
            bye_key = keys.bye(agent)
            published = {**node.counts.published, **own}
            published[bye_key] = published.get(bye_key, 0) + 1
            stats = {k: float(v) for k, v in getattr(node.agent, "stats", {}).items()}
            stats["cpu_s"] = time.process_time()
            stats["window_cpu_s"] = inbox.window_cpu_s
            stats["late"] = float(node.counts.late)
            stats["received"] = float(node.counts.received)
            send_own(bye_key, {"published": published,
                               "rejected": node.counts.rejected + inbox.rejected,
                               "lost": node.counts.lost, "stats": stats})
            # closing the session at once could drop the goodbye before it is on the wire:
            # `up` withdraws its liveliness once it has every goodbye (bounded wait)
            deadline = time.monotonic() + _BYE_WAIT_S
            while not inbox.up_gone and time.monotonic() < deadline:
                cond.wait(min(_WAIT_S, max(0.0, deadline - time.monotonic())))
    finally:
        token.undeclare()
        for subscriber in subscribers:
            subscriber.undeclare()
    return 0


def _run_realtime(inbox: _Inbox, node: Node, run_until, start: dict) -> None:
    cond = inbox.cond
    epoch_ns, speed, end_ns = start["epoch_ns"], float(start["speed"]), start["end_ns"]

    def sim_now() -> int:
        return int((time.time_ns() - epoch_ns) * speed)

    with cond:
        while inbox.stop is None:
            now = sim_now()
            if now >= 0:
                run_until(min(now, end_ns) + 1)
            next_ns = node.next_event_ns()
            if next_ns is None or next_ns > end_ns:
                wait_s = _WAIT_S
            else:
                wait_s = min(_WAIT_S, (next_ns / speed + epoch_ns - time.time_ns()) * 1e-9)
            if wait_s > 0:
                cond.wait(wait_s)
