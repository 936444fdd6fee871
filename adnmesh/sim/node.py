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
"""

from __future__ import annotations

from dataclasses import dataclass, field

from adnmesh.control.base import Agent
from adnmesh.sim.clock import Report
from adnmesh.sim.links import Link
from adnmesh.sim.topology import Topology
from adnmesh.wire.envelope import MessageError, decode, encode
from adnmesh.wire.keys import route
from adnmesh.wire.messages import MESSAGE_TYPES, MESSAGE_VERSION

__all__ = ["AgentCrash", "Node", "NodeCounts"]


class AgentCrash(Exception):
    """Raised by :meth:`Node.advance` when the agent reaches its injected crash time."""


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
    late : int
        Realtime only: messages processed after their delivery time.
    """

    published: dict[str, int] = field(default_factory=dict)
    received: int = 0
    rejected: dict[str, dict[str, int]] = field(default_factory=dict)
    lost: int = 0
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
    crash_ns : int, optional
        Injected crash time: :meth:`advance` raises :class:`AgentCrash` instead of processing an
        event at or after it.
    strict : bool
        Sim clock: reject a message delivered before the node's current time (it would break
        causality). Realtime: process it at once and count it as late.
    """

    def __init__(self, agent: Agent, topology: Topology, seed: int, *, crash_ns: int | None = None,
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
        self._last: dict[str, tuple[int, int]] = {}   # key -> (t_send, seq) last accepted
        self._window_keys: list[str] = []   # keys sent on in this window, in first-send order
        # held messages (t_deliver, key, seq, receive count, message); sorted latest first
        # (timsort merges the senders' runs; pop() takes the next) when _inbox_sorted
        self._inbox: list = []
        self._inbox_sorted = True
        self.crash_ns = crash_ns
        self.strict = strict
        self.now_ns = 0
        self.granted_ns = 0
        self.counts = NodeCounts()

    @classmethod
    def for_config(cls, agent: Agent, config) -> Node:
        """A node for ``agent`` with the topology, seed and injected crash of ``config``."""
        crash = [c.t_s for c in config.runtime.faults.crash if c.agent == agent.agent_id]
        return cls(agent, Topology.from_config(config), config.runtime.seed,
                   crash_ns=int(round(min(crash) * 1e9)) if crash else None)

    def reseed(self, seed: int) -> None:
        """Restart the ICT random streams with ``seed`` (before the first event only)."""
        self.seed = seed
        for outbox in self._outboxes.values():
            outbox.link = Link(outbox.link.params, seed, self.agent_id)

    # -- input ---------------------------------------------------------------------------------

    def receive(self, key: str, payload: bytes) -> None:
        """Take one payload from the bus; reject (count, drop) anything that is not a genuine
        message of a subscribed key, or that repeats one already accepted on the key."""
        counts = self.counts
        if key not in self._subscribed:
            counts.reject(key, "not_subscribed")
            return
        try:
            message = decode(key, payload)
        except MessageError as exc:
            counts.reject(key, exc.reason)
            return
        stamp = (message.t_send_ns, message.seq)
        last = self._last.get(key)
        if last is not None and stamp <= last:
            counts.reject(key, "replayed")
            return
        self._last[key] = stamp
        counts.received += 1
        t = message.t_deliver_ns
        if t < self.now_ns:
            if self.strict:
                counts.reject(key, "past")
                return
            counts.late += 1
            t = self.now_ns
        self._inbox.append((t, key, message.seq, counts.received, message))
        self._inbox_sorted = False

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

    def advance(self, until_ns: int) -> list[tuple[str, bytes]]:
        """Process every event with ``t < until_ns``; return the ``(key, payload)`` to publish.

        Raises
        ------
        AgentCrash
            If the next event is at or after the injected crash time.
        """
        out: list[tuple[str, bytes]] = []
        inbox, agent, emit = self._held(), self.agent, self._emit
        next_timer_ns, on_message, on_timer = agent.next_timer_ns, agent.on_message, \
            agent.on_timer
        crash_ns = self.crash_ns
        while True:
            timer = next_timer_ns()
            if inbox and (timer is None or inbox[-1][0] <= timer):
                t = inbox[-1][0]
                if t >= until_ns:
                    break
                if crash_ns is not None and t >= crash_ns:
                    self._crash()
                message = inbox.pop()[4]
                self.now_ns = t
                outgoing = on_message(t, message)
            elif timer is not None and timer < until_ns:
                if crash_ns is not None and timer >= crash_ns:
                    self._crash()
                self.now_ns = t = timer
                outgoing = on_timer(timer)
            else:
                break
            for key, body in outgoing:
                emit(t, key, body, out)
        self.granted_ns = max(self.granted_ns, until_ns)
        return out

    def _crash(self) -> None:
        self.now_ns = self.crash_ns
        raise AgentCrash(f"{self.agent_id}: injected crash at {self.crash_ns} ns")

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

    def emit_now(self, key: str, body: dict) -> list[tuple[str, bytes]]:
        """Send one message at the current time outside :meth:`advance` (e.g. a fault record)."""
        out: list[tuple[str, bytes]] = []
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
        return Report(self.agent_id, self.next_event_ns(), self.counts.received, sent)
