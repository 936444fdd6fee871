"""One agent's runtime without the bus: inbox, event order, ICT links, envelopes, counts.

A :class:`Node` wraps an agent state machine (:class:`adnmesh.control.base.Agent`). The agent
process (:mod:`adnmesh.runtime.process`), the in-process runner (:mod:`adnmesh.sim.local`)
and tests all drive agents through it, so the order in which an agent sees its events is the
same everywhere:

- :meth:`Node.receive` takes a payload from the bus and decodes it (validating every field and
  that ``src`` is the key's sender, :func:`adnmesh.wire.decode`) **before anything counts it**:
  a payload that fails, arrives on a key the agent does not subscribe to, or repeats a
  (send time, seq) already seen on its key is rejected, counted per key and reason, and dropped,
  never raised; only genuine messages count toward what the sim clock expects;
- :meth:`Node.advance` processes every event before a time: at equal times delivered messages
  first, ordered by (delivery time, key, seq) and then by arrival, then the agent's timers;
- what the agent returns goes through the sender side of its ICT link (fate and delivery time,
  :class:`~adnmesh.sim.links.Link`), gets its envelope (``seq`` per key, counted also for
  lost messages so that receivers see the gap) and is returned as ``(key, payload)`` to publish;
- :meth:`Node.report` summarises the window for the sim clock.

**Injected faults** (``fault`` messages from ``up`` on ``faults``, :mod:`adnmesh.wire.messages`)
are applied by the node, never seen by the agent: a link fault impairs the node's own sender
side of that link (:class:`~adnmesh.sim.links.Impairment`), ``ict_outage`` every ICT link it
sends on, ``der_offline`` of its own DER every ICT link it sends on *and* every ICT message
delivered to it in the window; ``kill`` of its own agent stops :meth:`Node.advance` at the
kill time for good (:attr:`Node.killed`; the process then dies). A node started late (``start_ns``, a restarted agent)
begins at that time and rejects messages sent before it (it did not exist then).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from msgspec import UNSET

from adnmesh.control.base import Agent
from adnmesh.sim.clock import Report
from adnmesh.sim.latency import Latency
from adnmesh.sim.links import Impairment, Link
from adnmesh.sim.topology import ICT_LINKS, Topology
from adnmesh.wire.envelope import MessageError, decode, encode
from adnmesh.wire.keys import route
from adnmesh.wire.messages import MESSAGE_TYPES, MESSAGE_VERSION

__all__ = ["Node", "NodeCounts", "names_known_ders"]


def names_known_ders(message, der_ids: frozenset[str]) -> bool:
    """False if ``message`` names a DER the run does not have (SI, the CPFC's weights)."""
    if message.type == "si":
        return message.si.keys() <= der_ids
    if message.type == "p_y" and message.w is not UNSET:
        return message.w.keys() <= der_ids
    return True


@dataclass
class NodeCounts:
    """What a node counted.

    Attributes
    ----------
    published : dict
        Messages handed to the bus per key.
    received : int
        Genuine messages received (valid, from the key's sender): what the sim clock counts.
    rejected : dict
        ``key -> {reason -> count}`` of payloads rejected (see :meth:`Node.receive`).
    lost : int
        Messages the ICT link model dropped (never published).
    dropped_offline : int
        Messages delivered while the node was offline (an injected fault): not processed.
    late : int
        Realtime only: messages processed after their delivery time.
    """

    published: dict[str, int] = field(default_factory=dict)
    received: int = 0
    rejected: dict[str, dict[str, int]] = field(default_factory=dict)
    lost: int = 0
    dropped_offline: int = 0
    late: int = 0

    def reject(self, key: str, reason: str) -> None:
        """Count one rejected payload on ``key`` (at most 256 distinct keys are told apart)."""
        rejected = self.rejected
        if key not in rejected and len(rejected) >= 256:
            key = "(other keys)"
        per_key = rejected.setdefault(key, {})
        per_key[reason] = per_key.get(reason, 0) + 1

    @property
    def rejected_total(self) -> int:
        """Every rejected payload."""
        return sum(sum(r.values()) for r in self.rejected.values())


class _Outbox:
    """A node's sender side of one key: its link, message struct and next ``seq``, and what it
    sent on the key in the current clock window (count, earliest delivery, ns)."""

    __slots__ = ("link", "type", "cls", "seq", "window_count", "window_earliest_ns")

    def __init__(self, link: Link, type_name: str) -> None:
        self.link = link
        self.type = type_name
        self.cls = MESSAGE_TYPES[type_name]
        self.seq = 0
        self.window_count = 0
        self.window_earliest_ns = 0


class Node:
    """Drives one agent (see the module docstring).

    Parameters
    ----------
    agent : Agent
        The state machine.
    topology : Topology
        For the links of the keys it publishes.
    seed : int
        Seed of the ICT random streams.
    start_ns : int
        When the node begins (0; later for a restarted agent).
    strict : bool
        Sim clock: reject a message delivered before the node's current time (it would break
        causality). Realtime: a message due before the end of the last :meth:`advance` (its
        instant was processed, so its order among that instant's events may differ from the sim
        run's) is processed at once and counted as late.
    """

    def __init__(self, agent: Agent, topology: Topology, seed: int, *, start_ns: int = 0,
                 strict: bool = True) -> None:
        self.agent = agent
        self.agent_id = agent.agent_id
        self.subscriptions = topology.subscriptions[agent.agent_id]
        self._topology = topology
        self.seed = seed
        self._outboxes = {key: _Outbox(Link(topology.link(agent.agent_id, key), seed,
                                            agent.agent_id), route(key).type)
                          for key in topology.publishes(agent.agent_id)}
        self._subscribed = frozenset(self.subscriptions)
        self._der_ids = topology.der_ids
        self._last: dict[str, tuple[int, int]] = {}   # key -> (t_send, seq) last accepted
        self._window_keys: list[str] = []   # keys sent on in this window, in first-send order
        # held messages (t_deliver, key, seq, receive count, message); sorted latest first
        # (timsort merges the senders' runs; pop() takes the next) when _inbox_sorted
        self._inbox: list = []
        self._inbox_sorted = True
        self._ict_in = frozenset(k for k in self.subscriptions
                                 if topology.inbound_link(k) in ICT_LINKS)
        self._offline: list[tuple[int, int | None]] = []   # windows without ICT in and out
        self._faults_applied: set[int] = set()
        self._link_of = {k: topology.inbound_link(k) or "up" for k in self.subscriptions}
        self.instant_inputs = "physical" in self._link_of.values()
        """The agent receives over the zero-delay ``physical`` path (the measurement)."""
        self.latency = Latency()
        self.worst_late = (0, "")        # the largest delivery error since it was last read
        self.kill_ns: int | None = None
        self.start_ns = self.now_ns = self.granted_ns = int(start_ns)
        self.strict = strict
        self.counts = NodeCounts()
        if start_ns:
            agent.resume(self.start_ns)

    @classmethod
    def for_config(cls, agent: Agent, config, start_ns: int = 0) -> Node:
        """A node for ``agent`` with the topology and seed of ``config``."""
        return cls(agent, Topology.from_config(config), config.runtime.seed, start_ns=start_ns)

    def reseed(self, seed: int) -> None:
        """Restart the ICT random streams with ``seed`` (before the first event only)."""
        self.seed = seed
        for outbox in self._outboxes.values():
            impairments = outbox.link.impairments
            outbox.link = Link(outbox.link.params, seed, self.agent_id)
            for impairment in impairments:
                outbox.link.impair(impairment)

    # -- input ---------------------------------------------------------------------------------

    def receive(self, key: str, payload: bytes) -> None:
        """Take one payload from the bus; reject (count, drop) anything that is not a genuine
        message of a subscribed key, or that repeats one already accepted on the key, or names a DER
  the run does not have."""
        counts = self.counts
        if key not in self._subscribed:
            counts.reject(key, "not_subscribed")
            return
        try:
            message = decode(key, payload)
        except MessageError as exc:
            counts.reject(key, exc.reason)
            return
        if not names_known_ders(message, self._der_ids):
            counts.reject(key, "unknown_der")
            return
        stamp = (message.t_send_ns, message.seq)
        last = self._last.get(key)
        if last is not None and stamp <= last:
            counts.reject(key, "replayed")
            return
        if message.t_send_ns < self.start_ns:
            counts.reject(key, "before_start")
            return
        self._last[key] = stamp
        counts.received += 1
        if message.type == "fault":
            self._apply(message)
            return
        t = message.t_deliver_ns
        if self.strict:
            if t < self.now_ns:
                counts.reject(key, "past")
                return
        elif t < self.granted_ns:   # realtime: its instant was already processed
            counts.late += 1
            t = max(t, self.now_ns)
        self._inbox.append((t, key, message.seq, counts.received, message))
        self._inbox_sorted = False

    def _apply(self, fault) -> None:
        """Take an injected fault (see the module docstring); a fault sent again (to a
        restarted agent) is applied once."""
        if fault.fault_id in self._faults_applied:
            return
        self._faults_applied.add(fault.fault_id)
        kind, me = fault.kind, self.agent_id
        window = (fault.start_ns, fault.end_ns)
        if kind == "kill":
            if fault.agent == me and (self.kill_ns is None or fault.start_ns < self.kill_ns):
                self.kill_ns = max(fault.start_ns, self.now_ns)
            return
        if kind == "der_offline":
            if me != f"der/{fault.der}":
                return
            self._offline.append(window)
        impairment = Impairment(fault.fault_id, {"link_loss": "loss", "link_delay": "delay"}.get(
            kind, "outage"), *window,
            value=fault.probability if kind == "link_loss" else
            fault.delay_ns if kind == "link_delay" else 0.0)
        for outbox in self._outboxes.values():
            name = outbox.link.params.name
            if name in ICT_LINKS and (kind in ("der_offline", "ict_outage") or name == fault.link):
                outbox.link.impair(impairment)

    def _is_offline(self, key: str, t_ns: int) -> bool:
        return key in self._ict_in and any(
            start <= t_ns and (end is None or t_ns < end) for start, end in self._offline)

    # -- time ----------------------------------------------------------------------------------

    def next_event_ns(self) -> int | None:
        """Time of the next event (delivered message or timer), or None."""
        timer = self.agent.next_timer_ns()
        if self._inbox:
            t = self._held()[-1][0]
            return t if timer is None or t < timer else timer
        return timer

    def _held(self) -> list:
        """The held messages, latest first."""
        if not self._inbox_sorted:
            self._inbox.sort(reverse=True)
            self._inbox_sorted = True
        return self._inbox

    def advance(self, until_ns: int, clock=None) -> list[tuple[str, bytes]]:
        """Process every event with ``t < until_ns``; return the ``(key, payload)`` to publish.

        ``clock`` (realtime): the current time, ns; the delivery error of every event (when it
        is processed minus when it was due) is counted per link in :attr:`latency`.

        At an injected kill nothing at or after the kill time is processed, and
        :attr:`killed` becomes true.
        """
        out: list[tuple[str, bytes]] = []
        inbox, agent, emit = self._held(), self.agent, self._emit
        next_timer_ns, on_message, on_timer = agent.next_timer_ns, agent.on_message, \
            agent.on_timer
        kill_ns = self.kill_ns
        stop_ns = until_ns if kill_ns is None else min(until_ns, kill_ns)
        while True:
            timer = next_timer_ns()
            if inbox and (timer is None or inbox[-1][0] <= timer):
                t = inbox[-1][0]
                if t >= stop_ns:
                    break
                _, key, _, _, message = inbox.pop()
                self.now_ns = t
                if clock is not None:   # against the delivery time, also for a late arrival
                    self._late(self._link_of[key], clock() - message.t_deliver_ns)
                if self._offline and self._is_offline(key, t):
                    self.counts.dropped_offline += 1
                    continue
                outgoing = on_message(t, message)
            elif timer is not None and timer < stop_ns:
                self.now_ns = t = timer
                if clock is not None:
                    self._late("timer", clock() - t)
                outgoing = on_timer(timer)
            else:
                break
            for key, body in outgoing:
                emit(t, key, body, out)
        if kill_ns is not None and until_ns > kill_ns:
            self.now_ns = self.granted_ns = kill_ns
        else:
            self.granted_ns = max(self.granted_ns, until_ns)
        return out

    def _late(self, link: str, error_ns: int) -> None:
        self.latency.add(link, error_ns)
        if error_ns > self.worst_late[0]:
            self.worst_late = (error_ns, link)

    def take_worst_late(self) -> tuple[int, str]:
        """The largest delivery error and its link since the last call (then reset)."""
        worst, self.worst_late = self.worst_late, (0, "")
        return worst

    def send_now(self, key: str, body: dict) -> list[tuple[str, bytes]]:
        """Send one message of the agent's at the node's current time (outside an event)."""
        out: list[tuple[str, bytes]] = []
        self._emit(self.now_ns, key, body, out)
        return out

    @property
    def killed(self) -> bool:
        """The node reached an injected kill (it processes nothing more)."""
        return self.kill_ns is not None and self.granted_ns >= self.kill_ns

    def _emit(self, t: int, key: str, body: dict, out: list) -> None:
        outbox = self._outboxes[key]
        seq = outbox.seq
        outbox.seq = seq + 1
        t_deliver = outbox.link.transmit(t)
        if t_deliver is None:
            self.counts.lost += 1
            return
        out.append((key, encode(outbox.cls(MESSAGE_VERSION, outbox.type, self.agent_id, seq, t,
                                           t_deliver, **body))))
        published = self.counts.published
        published[key] = published.get(key, 0) + 1
        if not outbox.window_count:
            self._window_keys.append(key)
            outbox.window_earliest_ns = t_deliver
        elif t_deliver < outbox.window_earliest_ns:
            outbox.window_earliest_ns = t_deliver
        outbox.window_count += 1

    def finish(self) -> list[tuple[str, bytes]]:
        """The agent's last messages at the stop (:meth:`Agent.finish`), ready to publish."""
        out: list[tuple[str, bytes]] = []
        for key, body in self.agent.finish(self.now_ns):
            self._emit(self.now_ns, key, body, out)
        return out

    # -- clock ---------------------------------------------------------------------------------

    def report(self) -> Report:
        """The report after a window; resets the per-window send counts."""
        sent = {}
        for key in self._window_keys:
            outbox = self._outboxes[key]
            sent[key] = (outbox.window_count, outbox.window_earliest_ns)
            outbox.window_count = 0
        self._window_keys = []
        killed = self.kill_ns if self.killed else None
        return Report(self.agent_id, None if killed is not None else self.next_event_ns(),
                      self.counts.received, sent, killed)
