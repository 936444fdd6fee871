"""One agent's runtime without the bus: inbox, event order, ICT links, envelopes, counts.

A :class:`Node` wraps an agent state machine (:class:`adnmesh.control.base.Agent`). The agent
process (:mod:`adnmesh.runtime.process`), the in-process runner (:mod:`adnmesh.sim.local`)
and tests all drive agents through it, so the order in which an agent sees its events is the
same everywhere:

- :meth:`Node.receive` lets a payload from the bus in through the node's gate
  (:mod:`adnmesh.wire.gate`: the accept rules every receiver applies) **before anything counts
  it**: a payload the gate rejects is counted per key and reason and dropped, never raised; only
  genuine messages count toward what the sim clock expects;
- :meth:`Node.advance` processes every event before a time: at equal times delivered messages
  first, ordered by (delivery time, key, seq) and then by arrival, then the agent's timers;
- what the agent returns goes through the sender side of its ICT link (fate and delivery time,
  :class:`~adnmesh.sim.links.Link`), gets its envelope from the node's outbox
  (:mod:`adnmesh.wire.outbox`) and is returned as ``(key, payload)`` to publish;
- :meth:`Node.report` summarises the window for the sim clock.

**Injected faults** (``fault`` messages from ``up`` on ``faults``, :mod:`adnmesh.wire.messages`)
are applied by the node, never seen by the agent: a link fault impairs the node's own sender
side of that link (:class:`~adnmesh.sim.links.Impairment`), ``ict_outage`` every ICT link it
sends on, ``der_offline`` of its own DER every ICT link it sends on *and* every ICT message
delivered to it in the window; ``kill`` of its own agent stops :meth:`Node.advance` at the
kill time for good (:attr:`Node.killed`; the process then dies); a kill that is a quarantine
(``origin`` ``quarantine``: ``up`` found someone sending with that agent's identity) of
another agent cuts that agent off in the node's gate from the kill on; the grant that names the
agent's keys (``cut_keys``, :meth:`Node.take_cut`) takes them out of the node's count. A node
started late (``start_ns``, a restarted agent) begins at that time and rejects messages sent
before it (it did not exist then).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from adnmesh.control.base import Agent
from adnmesh.names import ICT_LINKS, der_agent_id
from adnmesh.sim.clock import Report
from adnmesh.sim.latency import Latency
from adnmesh.sim.links import Impairment, Link
from adnmesh.sim.topology import Topology
from adnmesh.wire.envelope import MessageError, encode
from adnmesh.wire.gate import Gate
from adnmesh.wire.outbox import Outbox

__all__ = ["Node", "NodeCounts"]


@dataclass
class NodeCounts:
    """What a node counted.

    Attributes
    ----------
    published : dict
        Messages handed to the bus per key.
    received : int
        Genuine messages received (valid, from the key's sender), and those dropped because
        their sender is quarantined, less those on keys the clock cut (a quarantined sender's,
        :meth:`Node.take_cut`): what the sim clock counts.
    rejected : dict
        ``key -> {reason -> count}`` of payloads rejected (the node's gate's counts).
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

    @property
    def rejected_total(self) -> int:
        """Every rejected payload."""
        return sum(sum(r.values()) for r in self.rejected.values())


class _Sending:
    """A node's sender side of one key: its link, and what it sent on the key in the current
    clock window (count, earliest delivery, ns)."""

    __slots__ = ("link", "window_count", "window_earliest_ns")

    def __init__(self, link: Link) -> None:
        self.link = link
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
    node_id : str, optional
        The agent's name in ``topology`` and to the clock, if not its agent id (a hierarchy
        of ADNs: ``<grid>:<agent id>``, :mod:`adnmesh.sim.hierarchy_topology`).
    """

    def __init__(self, agent: Agent, topology: Topology, seed: int, *, start_ns: int = 0,
                 strict: bool = True, node_id: str | None = None) -> None:
        self.agent = agent
        self.agent_id = agent.agent_id
        self.node_id = node_id = node_id or agent.agent_id
        self.subscriptions = topology.subscriptions[node_id]
        self._topology = topology
        self.seed = seed
        self._sending = {key: _Sending(Link(topology.link(node_id, key), seed,
                                            agent.agent_id))
                         for key in topology.publishes(node_id)}
        self.outbox = Outbox(agent.agent_id)
        self.gate = Gate(self.subscriptions, topology.der_ids, outside_reason="not_subscribed",
                         start_ns=start_ns, capacity_w=topology.capacity_w)
        self.counts = NodeCounts(rejected=self.gate.rejected)
        self._window_keys: list[str] = []   # keys sent on in this window, in first-send order
        # held messages (t_deliver, key, seq, receive count, message); sorted latest first
        # (timsort merges the senders' runs; pop() takes the next) when _inbox_sorted
        self._inbox: list = []
        self._inbox_sorted = True
        self._ict_in = frozenset(k for k in self.subscriptions
                                 if topology.inbound_link(k) in ICT_LINKS)
        self._offline: list[tuple[int, int | None]] = []   # windows without ICT in and out
        self._faults_applied: set[tuple] = set()       # what each applied fault said
        self._link_of = {k: topology.inbound_link(k) or "up" for k in self.subscriptions}
        self.instant_inputs = "physical" in self._link_of.values()
        """The agent receives over the zero-delay ``physical`` path (the measurement)."""
        self.latency = Latency()
        self.worst_late = (0, "")        # the largest delivery error since it was last read
        self.kill_ns: int | None = None
        self.start_ns = self.now_ns = self.granted_ns = int(start_ns)
        self.strict = strict
        self._arrivals = 0                 # messages held so far: the inbox's last tie-break
        self._counted: dict[str, int] = {}   # per key, counted since the first report
        self._reported_once = False
        self._cut_keys: set[str] = set()     # keys not counted (quarantined senders')
        self.cuts = 0                        # the quarantines taken out of the count
        if start_ns:
            agent.resume(self.start_ns)

    @classmethod
    def for_config(cls, agent: Agent, config, start_ns: int = 0,
                   topology: Topology | None = None) -> Node:
        """A node for ``agent`` with the topology (``topology``, if given: one for the agents
        of a process) and seed of ``config``."""
        return cls(agent, topology or Topology.from_config(config), config.runtime.seed,
                   start_ns=start_ns)

    def reseed(self, seed: int) -> None:
        """Restart the ICT random streams with ``seed`` (before the first event only)."""
        self.seed = seed
        for sending in self._sending.values():
            impairments = sending.link.impairments
            sending.link = Link(sending.link.params, seed, self.agent_id)
            for impairment in impairments:
                sending.link.impair(impairment)

    # -- input ---------------------------------------------------------------------------------

    def receive(self, key: str, payload: bytes) -> None:
        """Take one envelope from the bus; what the gate rejects (:mod:`adnmesh.wire.gate`) is
        counted and dropped. A message dropped because its sender is quarantined counts as
        received: its sender's clock reports count it (whether it came before or after the
        quarantine reached this node, the count is the same)."""
        try:
            message = self.gate.admit(key, payload, hold=True)
        except MessageError as exc:
            if exc.reason == "quarantined":
                self._count(key, 1)
            return
        self._count(key, 1)
        self._take(key, message)

    def receive_sample(self, key: str, sample: bytes) -> None:
        """Take one sample from the bus (one or more envelopes of ``key``,
        :func:`~adnmesh.wire.envelope.frames`); its rejects count once per reason, and those
        of a quarantined sender count as received (:meth:`receive`)."""
        accepted, rejects = self.gate.admit_sample(key, sample, hold=True)
        n = len(accepted)
        for reject in rejects:
            if reject.reason == "quarantined":
                n += reject.envelopes
        if n:
            self._count(key, n)
        for _, message in accepted:
            self._take(key, message)

    def _count(self, key: str, n: int) -> None:
        """Count ``n`` messages on ``key`` for the clock (none on a cut key)."""
        if key in self._cut_keys:
            return
        self.counts.received += n
        counted = self._counted
        counted[key] = counted.get(key, 0) + n

    def take_cut(self, cut_keys, cuts: int) -> None:
        """A grant's cut (:class:`~adnmesh.sim.clock.Grant`): stop counting ``cut_keys`` and
        take out what was counted on them since the first report; ``cuts`` quarantines are
        taken. Call on every grant, before comparing the count with its ``expect``."""
        if cuts <= self.cuts:
            return
        for key in cut_keys:
            if key not in self._cut_keys:
                self._cut_keys.add(key)
                self.counts.received -= self._counted.pop(key, 0)
        self.cuts = cuts

    def _take(self, key: str, message) -> None:
        """Hold a genuine message until its delivery time (apply a fault at once)."""
        counts = self.counts
        if message.type == "fault":
            self.gate.taken_unordered(key, message)
            self._apply(message)
            return
        t = message.t_deliver_ns
        if self.strict:
            if t < self.now_ns:
                self.gate.consumed(key, message)
                self.gate.reject(key, "past")
                return
        elif t < self.granted_ns:   # realtime: its instant was already processed
            counts.late += 1
            t = max(t, self.now_ns)
        self._arrivals += 1
        self._inbox.append((t, key, message.seq, self._arrivals, message))
        self._inbox_sorted = False

    def _apply(self, fault) -> None:
        """Take an injected fault (see the module docstring); a fault sent again (to a
        restarted agent, or replayed) is applied once. A fault is known by all it says, not by
        its number alone: in the open profile anyone may send one, and one under a number
        ``up`` uses must not make an agent ignore ``up``'s own (a quarantine's kill, say)."""
        said = (fault.fault_id, fault.kind, fault.start_ns, fault.end_ns, fault.link,
                fault.der, fault.agent, fault.probability, fault.delay_ns, fault.origin)
        if said in self._faults_applied:
            return
        self._faults_applied.add(said)
        kind, me = fault.kind, self.agent_id
        window = (fault.start_ns, fault.end_ns)
        if kind == "kill":
            if fault.agent == me and (self.kill_ns is None or fault.start_ns < self.kill_ns):
                self.kill_ns = max(fault.start_ns, self.now_ns)
            elif fault.origin == "quarantine":
                self.gate.cut_off(fault.agent, fault.start_ns)
            return
        if kind == "der_offline":
            if me != der_agent_id(fault.der):
                return
            self._offline.append(window)
        impairment = Impairment(fault.fault_id, {"link_loss": "loss", "link_delay": "delay"}.get(
            kind, "outage"), *window,
            value=fault.probability if kind == "link_loss" else
            fault.delay_ns if kind == "link_delay" else 0.0)
        for sending in self._sending.values():
            name = sending.link.params.name
            if name in ICT_LINKS and (kind in ("der_offline", "ict_outage") or name == fault.link):
                sending.link.impair(impairment)

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
                self.gate.consumed(key, message)
                self.now_ns = t
                if clock is not None:   # against the delivery time, also for a late arrival
                    self._late(self._link_of[key], clock() - message.t_deliver_ns)
                if self._offline and self._is_offline(key, t):
                    self.counts.dropped_offline += 1
                    continue
                if self.gate.is_cut_off(message):     # held from before a quarantine
                    self.gate.reject(key, "quarantined")
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

    def sends(self) -> tuple[str, ...]:
        """Every key the agent sends, clock protocol included (its topology's)."""
        return self._topology.sends(self.node_id)

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
        sending = self._sending[key]
        seq = self.outbox.take_seq(key)       # counted also if lost: receivers see the gap
        t_deliver = sending.link.transmit(t)
        if t_deliver is None:
            self.counts.lost += 1
            return
        out.append((key, encode(self.outbox.message(key, seq, t, t_deliver, body))))
        published = self.counts.published
        published[key] = published.get(key, 0) + 1
        if not sending.window_count:
            self._window_keys.append(key)
            sending.window_earliest_ns = t_deliver
        elif t_deliver < sending.window_earliest_ns:
            sending.window_earliest_ns = t_deliver
        sending.window_count += 1

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
            sending = self._sending[key]
            sent[key] = (sending.window_count, sending.window_earliest_ns)
            sending.window_count = 0
        self._window_keys = []
        killed = self.kill_ns if self.killed else None
        if not self._reported_once:      # the clock's baseline (a restarted agent: its first)
            self._counted.clear()
            self._reported_once = True
        return Report(self.node_id, None if killed is not None else self.next_event_ns(),
                      self.counts.received, sent, killed, cuts=self.cuts)
