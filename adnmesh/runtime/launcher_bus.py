"""What ``adnmesh up`` itself puts on the bus: its own messages and the sim clock's grants.

:class:`LauncherOutbox` publishes ``up``'s messages (grants, start, stop) with their envelope
(sender ``up``, ``seq`` per key) and records each as it sends it (the recorder's subscriber
takes only what comes from the agents). :class:`SimClockDriver` feeds clock reports to the
:class:`~adnmesh.sim.clock.Coordinator` and publishes the grants that follow.
"""

from __future__ import annotations

import threading
import time

import zenoh
from msgspec import UNSET

from adnmesh.runtime.tap import RecorderTap
from adnmesh.sim.clock import ClockError, Coordinator, Report
from adnmesh.names import LAUNCHER, der_id_of
from adnmesh.wire.envelope import encode
from adnmesh.wire.keys import Keys
from adnmesh.wire.outbox import Outbox

__all__ = ["LauncherOutbox", "SimClockDriver", "publish_grants"]


class LauncherOutbox:
    """Publishes and records ``up``'s own messages (thread-safe)."""

    def __init__(self, session: zenoh.Session, tap: RecorderTap) -> None:
        self._session = session
        self._tap = tap
        self.lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._outbox = Outbox(LAUNCHER)

    def send(self, key: str, t_ns: int, t_deliver_ns: int | None = None, **body) -> None:
        """Publish a message of ``up`` sent at sim time ``t_ns`` (delivered then, or at
        ``t_deliver_ns``) and record it."""
        with self.lock:
            message = self._outbox.send(key, t_ns, body, t_deliver_ns)
            payload = encode(message)
            self._publisher(key).put(payload)
            self._tap.record_own(key, message, payload)

    def send_together(self, sample_key: str, messages: list[tuple[str, str, int, dict]]
                      ) -> None:
        """Publish several messages of ``up`` in one sample on ``sample_key`` (the grants of
        one hosting process): ``(key, recipient, t_ns, body)`` each, enveloped and recorded
        under its own key as :meth:`send` does; the attachment names the recipients."""
        with self.lock:
            sent = [(key, self._outbox.send(key, t_ns, body, None))
                    for key, _, t_ns, body in messages]
            payloads = [encode(message) for _, message in sent]
            self._publisher(sample_key).put(
                b"\n".join(payloads), attachment="\n".join(r for _, r, _, _ in messages).encode())
            for (key, message), payload in zip(sent, payloads):   # out first, then recorded
                self._tap.record_own(key, message, payload)

    def _publisher(self, key: str) -> zenoh.Publisher:   # with the lock held
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK,
                allowed_destination=zenoh.Locality.REMOTE)
        return publisher

    def counts(self) -> dict[str, int]:
        """Messages sent per key."""
        with self.lock:
            return self._outbox.counts()


class SimClockDriver:
    """The sim clock of a run: reports in, grants out (thread-safe).

    Parameters
    ----------
    coordinator : Coordinator
    keys : Keys
    outbox : LauncherOutbox
        Where grants go.
    on_change : callable
        Called when the run finished or the clock failed.
    on_violation : callable, optional
        ``(agent, what)``: a DER's report broke the clock protocol (a second report without a
        grant: someone else reports with its identity). Without it, or for another agent, the
        clock fails.
    host_of : callable, optional
        ``agent -> host or None``: the process hosting ``agent`` with other agents
        (:mod:`adnmesh.runtime.host`): the grants of one batch to the agents of one host go in
        one sample (:meth:`~adnmesh.wire.keys.Keys.host_grants`), each recorded as before.
    """

    def __init__(self, coordinator: Coordinator, keys: Keys, outbox: LauncherOutbox,
                 on_change, on_violation=None, host_of=None) -> None:
        self.coordinator = coordinator
        self._host_of = host_of or (lambda agent: None)
        self._keys = keys
        self._outbox = outbox
        self._on_change = on_change
        self._on_violation = on_violation
        self.lock = threading.RLock()
        self._started = False
        self.finished = False
        self.error: str | None = None
        self.last_grant_s = time.monotonic()   # when the clock last moved, monotonic s
        self.recent_ns = 0       # now_ns at the last grants: read without the lock (the tap)

    def on_reports(self, messages, name=None) -> None:
        """Take clock reports (in the order they came); publish the grants that follow from
        all of them (one search for a batch: ``up`` takes what has queued on the bus at once).
        ``name(sender)``: the clock's name of a report's sender (default: its id)."""
        with self.lock:
            changed = False
            for message in messages:
                if self.error is not None:
                    return
                killed = None if message.killed_ns is UNSET else message.killed_ns
                agent = message.src if name is None else name(message.src)
                report = Report(agent, message.next_ns, message.received,
                                {k: (v[0], v[1]) for k, v in message.sent.items()}, killed,
                                message.granted_ns, message.cuts)
                try:
                    changed = self.coordinator.take_report(report) or changed
                except ClockError as exc:
                    if self._on_violation is not None and der_id_of(message.src) is not None:
                        self._on_violation(agent, f"clock report out of protocol: {exc}")
                        continue
                    self.error = str(exc)
                    self._on_change()
                    return
            if changed and self._started:
                self._send(self.coordinator.grants())

    def start(self) -> None:
        """Begin granting (every agent has reported)."""
        with self.lock:
            self._started = True
            self._send(self.coordinator.start())

    def now_ns(self) -> int:
        """The time before which every agent has processed everything, ns."""
        with self.lock:
            return self.coordinator.now_ns()

    def earliest_unprocessed_ns(self) -> int:
        """The earliest time no live agent may have processed yet, ns (for a fault to take
        effect there for all of them)."""
        with self.lock:
            c = self.coordinator
            granted = [c.granted_ns(a) for a in c.agents if not c.is_dead(a)]
            return max([c.now_ns(), *granted])

    def inject(self, agents) -> None:
        """``up`` sends one message to each of ``agents`` (count it)."""
        with self.lock:
            self.coordinator.inject(agents)

    def kill(self, agent: str, at_ns: int | None = None) -> None:
        """``agent``'s process ended without a last report: it is dead; grants follow."""
        with self.lock:
            self._send(self.coordinator.kill(agent, at_ns))

    def quarantine(self, agent: str, at_ns: int) -> None:
        """``agent`` is quarantined at ``at_ns``: dead, and out of every count
        (:meth:`Coordinator.quarantine <adnmesh.sim.clock.Coordinator.quarantine>`); grants
        follow."""
        with self.lock:
            self._send(self.coordinator.quarantine(agent, at_ns))

    def cancel_restart(self, agent: str) -> None:
        with self.lock:
            self._send(self.coordinator.cancel_restart(agent))

    @property
    def grants_issued(self) -> int:
        return self.coordinator.grants_issued

    def stalled_s(self) -> float:
        """Wall seconds since the last grant (0 before the start)."""
        with self.lock:
            return time.monotonic() - self.last_grant_s if self._started else 0.0

    def _send(self, grants) -> None:   # with the lock held
        t = 0
        if grants:
            self.last_grant_s = time.monotonic()
            t = self.recent_ns = self.coordinator.now_ns()
        self._publish(grants, t)
        if self.coordinator.finished and not self.finished:
            self.finished = True
            self._on_change()

    def _publish(self, grants, t: int) -> None:   # with the lock held
        """Publish ``grants`` (sent at sim time ``t``, ns)."""
        publish_grants(self._keys, self._outbox, self._host_of,
                       [(g.agent, g) for g in grants], t)


def publish_grants(keys: Keys, outbox: LauncherOutbox, host_of, grants, t: int) -> None:
    """Publish ``grants`` (``(agent id, Grant)`` each, ids of the grid of ``keys``) at sim time
    ``t``, ns: each on its agent's grant key, or those of one hosting process (``host_of``)
    in one sample."""
    hosted: dict[str, list] = {}
    for agent, g in grants:
        key = keys.of("clock_grant", agent)
        host = host_of(agent)
        body = {"until_ns": g.until_ns, "expect": g.expect}
        if g.cuts:
            body.update(cut_keys=g.cut_keys, cuts=g.cuts)
        if host is None:
            outbox.send(key, t, **body)
        else:
            hosted.setdefault(host, []).append((key, agent, t, body))
    for host, messages in hosted.items():
        outbox.send_together(keys.host_grants(host), messages)
