"""The sim clock's coordinator: conservative, event-driven time advance (bus-free).

Every agent processes its events (timers and delivered messages) in time order and only while it
is sure that no message can still arrive for an earlier time. The coordinator tells it how far it
may go:

- After each window an agent **reports** its next event time ``next_ns`` (``None``: none), how
  many messages it has received so far (``received``) and, per key, how many it sent in the window
  and the earliest delivery time among them (``sent``).
- The coordinator keeps, per agent ``p``, a lower bound ``E_p`` on the time of anything ``p`` will
  still do: its reported ``next_ns``, lowered to the earliest delivery time of messages sent to it
  that its report may not account for (*messages in flight*: counted by their senders after its
  last grant, and not yet received when it reported).
- A message chain from ``p`` to ``b`` takes at least ``lookahead(p, b)`` (the least total link
  delay, :class:`~adnmesh.sim.topology.Topology`), so nothing can reach ``b`` before
  ``LBTS(b) = min_p (E_p + lookahead(p, b))`` (lower bound on time stamps; ``p = b`` covers
  cycles through ``b``).
- The coordinator **grants** ``b`` the time ``until_ns = min(LBTS(b), end + 1 ns)`` together
  with ``expect``, the number of messages sent to ``b`` so far. ``b`` first waits until it has
  received ``expect`` messages (so nothing in flight is missed, whatever the order in which the
  router forwards reports and data), then processes every event with ``t < until_ns`` — at equal
  times messages first, in (delivery time, key, seq) order, then its timers — and reports again.

A grant is sent when it lets the agent advance by a whole cycle's lookahead (the least delay
around the shortest cycle through it: ``T_com + T_meas`` = 0.2 s for the CPFC, the DERs and the
measurement): every window is a round trip and costs time, so few large windows beat many small
ones. When no agent can make such a window and none is running, the agents of one kind with the
earliest next event go (on a tie the kind listed last, the DERs); this staggers the stages around
the control loop once, after which CPFC, DERs and measurement take full windows in turn.

Messages in flight to ``b`` were sent after its grant, so they are delivered at or after it and
``E_b`` is a true bound, never a stale one. Because every cycle of the message graph has a
positive delay, the agent with the earliest event can always advance, and the fallback above
grants it when nothing else runs: the run cannot deadlock. The run is finished when no agent has
an event at or before ``end_ns``.

The coordinator is deterministic given the reports, but the *sequence* of grants depends on the
order in which reports arrive; the agents' messages (what they send, and when in sim time) do
not: every agent processes exactly the events with ``t < until_ns`` in a fixed order.

**Agents that die and come back.** An agent killed by an injected fault reports its last window
with ``killed_ns``; one that dies otherwise is declared dead by :meth:`Coordinator.kill`. A dead
agent has no events, receives nothing (messages to it are not expected) and bounds nobody. A
restart planned at ``R`` (:meth:`Coordinator.plan_restart`) is a **barrier**: no grant reaches
beyond ``R`` until the restarted process has reported, and its first report is taken only
once every live agent has processed everything before ``R``; a restarted node rejects
messages sent before ``R``. So whatever the wall-clock time a new process needs to start, every
message of the run is the same. Messages that ``up`` sends to the agents (injected faults) are
counted with :meth:`Coordinator.inject`.

**Quarantined agents.** A receiver's count can hold messages no report accounts for: someone
sending with a quarantined agent's identity, or that agent's own messages of the window in
which the clock declared it dead. Left in, they would let the receiver take a grant before the
messages it waits for have come. So :meth:`Coordinator.quarantine` takes the agent out of
every count: it subtracts what the agent's reports counted for each live receiver, and every
later grant to a receiver of the agent's keys names them (``cut_keys``) with the number of
quarantines so far (``cuts``); the receiver stops counting those keys and takes out what it
counted on them since its first report (the clock's baseline for it: the run's start, or its
rejoin), and says in its reports how many quarantines it has applied. A report from before a
quarantine does not say what the receiver holds: the clock takes it as missing messages until
a grant brings the receiver up to date. A quarantined agent is never taken back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from adnmesh.sim.topology import Topology

__all__ = ["ClockError", "Coordinator", "Grant", "Report"]

_INF = math.inf


class ClockError(RuntimeError):
    """The clock protocol was violated (e.g. a report from an unknown agent) or deadlocked."""


@dataclass(frozen=True, slots=True)
class Grant:
    """Permission for ``agent`` to process every event before ``until_ns`` once it has received
    ``expect`` messages in total, not counting those on ``cut_keys`` (the keys of quarantined
    senders it receives; ``cuts``: the quarantines so far)."""

    agent: str
    until_ns: int
    expect: int
    cut_keys: tuple[str, ...] = ()
    cuts: int = 0


@dataclass(frozen=True, slots=True)
class Report:
    """What an agent reports after a window.

    Attributes
    ----------
    agent : str
    next_ns : int or None
        Time of its next event (None: no event left).
    received : int
        Messages received so far (all keys it subscribes to, valid or not).
    sent : dict
        ``key -> (count, earliest delivery ns)`` of the messages it sent since its last report.
    killed_ns : int or None
        Set when an injected kill ended the agent at that time (this is its last report).
    granted_ns : int or None
        The end of the last grant the agent had taken when it reported, ns (None: not known,
        as in-process). A report behind the coordinator's last grant to the agent is a
        repeated first report that crossed that grant on the bus, and is dropped.
    cuts : int
        How many quarantines (:attr:`Grant.cuts`) it has taken out of ``received``.
    """

    agent: str
    next_ns: int | None
    received: int
    sent: Mapping[str, tuple[int, int]]
    killed_ns: int | None = None
    granted_ns: int | None = None
    cuts: int = 0


class Coordinator:
    """Grants sim time to the agents of a topology (see the module docstring).

    Parameters
    ----------
    topology : Topology
        Agents, receivers of every key, lookahead between agents.
    end_ns : int
        Last instant of the run, ns; events at ``end_ns`` are still processed.
    window_factor : float
        Scales the window a grant must at least give (see :meth:`_grants`).
    on_rejoin : callable, optional
        ``on_rejoin(agent, restart_ns)``, called when a restarted agent is taken back and before
        any grant to it, so that what ``up`` sends it then (:meth:`inject`) is expected.
    """

    def __init__(self, topology: Topology, end_ns: int, window_factor: float = 1.0,
                 on_rejoin=None) -> None:
        self.topology = topology
        self._on_rejoin = on_rejoin   # (agent, restart ns) -> None, before the next grants
        self.end_ns = int(end_ns)
        self.agents = topology.agents
        index = {a: i for i, a in enumerate(self.agents)}
        self._index = index
        n = len(self.agents)
        # for each receiver b: [(p, lookahead(p, b))] over the agents that can reach it,
        # nearest first (one pass over the pairs: 1,003 agents have a million), so that the
        # search for b's LBTS can stop at the first source too far away to lower it (_lbts)
        sources: list[list[tuple[int, int]]] = [[] for _ in range(n)]
        for (p, q), d in topology.lookahead_ns.items():
            sources[index[q]].append((index[p], d))
        self._sources = [tuple(sorted(s, key=lambda pd: (pd[1], pd[0]))) for s in sources]
        self._receivers = {key: tuple(index[a] for a in to)
                           for key, to in topology.receivers.items()}
        # a grant should let an agent advance by its cycle's lookahead (see _grants)
        self._min_window = [int(window_factor * topology.lookahead_ns.get((a, a), 0))
                            for a in self.agents]
        kinds = [a.split("/")[0] for a in self.agents]
        self._kind = kinds
        self._kind_rank = {k: kinds.index(k) for k in kinds}
        self._next = [-_INF] * n          # reported next event (-inf until the first report)
        self._pending = [_INF] * n        # earliest delivery of messages it has not accounted for
        self._pending_new = [_INF] * n    # the same, for messages counted since its last grant
        self._expected = [0] * n          # messages sent to it, as reported by the senders
        self._received = [0] * n          # messages it says it has received
        self._granted = [0] * n           # until_ns of its last grant
        self._grant_expect = [0] * n      # ... and the messages it had to wait for
        self._idle = [False] * n          # reported since its last grant
        self._reported = [False] * n
        self._hello = [False] * n         # its last report is a first one (no grant since):
        #                                   an agent repeats it until the start (a lost one)
        self._dead = [False] * n
        self._restarts: dict[int, int] = {}       # agent -> planned restart time, ns
        self._rejoining: dict[int, Report] = {}   # first reports of restarted agents, held
        self._holds: dict[int, int] = {}          # time no grant may pass -> holds on it
        self.sent_totals: list[dict[str, int]] = [{} for _ in range(n)]
        self._cut_keys: dict[int, tuple[str, ...]] = {}   # receiver -> quarantined keys it gets
        self._quarantined: set[int] = set()
        # for a rejoined agent: what each sender's reports had counted on its keys then
        self._rejoin_totals: dict[int, dict[tuple[int, str], int]] = {}
        self.killed_at: dict[str, int] = {}
        self.rejoined: list[tuple[str, int]] = []   # (agent, restart ns) taken back since
        self._started = False
        self.grants_issued = 0
        self.grants_per_agent = [0] * n
        self.reports_received = 0

    # -- protocol ----------------------------------------------------------------------------

    def on_report(self, report: Report) -> list[Grant]:
        """Take a report; return the grants that follow from it (none before :meth:`start`)."""
        if self.take_report(report):
            return self.grants()
        return []

    def grants(self) -> list[Grant]:
        """The grants that follow from everything taken so far (none before :meth:`start`).
        Taking several reports (:meth:`take_report`) before asking gives the grants of all of
        them at once: fewer searches, and no grant the later reports would have bettered."""
        return self._after_change()

    def take_report(self, report: Report) -> bool:
        """Take a report without granting; return whether it changed anything (False: a
        repeated first report that crossed a grant, or a dead process's late one).

        Raises
        ------
        ClockError
            A report from an unknown agent, a second report without a grant, or one under a
            grant the agent was never given (none of which a genuine agent sends).
        """
        i = self._index.get(report.agent)
        if i is None:
            raise ClockError(f"report from unknown agent {report.agent!r}")
        if report.killed_ns is None and report.granted_ns is not None \
                and report.granted_ns < self._granted[i]:
            return False                          # a repeated first report, crossed a grant
        if self._dead[i]:
            if i in self._restarts and i not in self._rejoining:
                self._rejoining[i] = report      # the restarted process: taken at the barrier
                return True
            return False                          # a dead process's late report
        if self._reported[i] and self._idle[i] and not (self._hello[i] and not report.sent):
            raise ClockError(f"{report.agent}: second report without a grant")
        if report.granted_ns is not None and report.granted_ns > self._granted[i]:
            raise ClockError(f"{report.agent}: report under a grant to {report.granted_ns} ns, "
                             f"but it was granted only to {self._granted[i]} ns")
        self._hello[i] = not self._reported[i] or self._hello[i]   # a first report, or again
        self.reports_received += 1
        self._next[i] = _INF if report.next_ns is None else report.next_ns
        # a report that has not applied every cut does not say what the agent holds
        self._received[i] = report.received if report.cuts >= len(self._quarantined) else -1
        self._idle[i] = True
        self._reported[i] = True
        expected, pending, pending_new = self._expected, self._pending, self._pending_new
        # what i did not account for: nothing if it has every message counted so far; else at
        # most the messages counted after its grant (those before it waited for and processed
        # or holds in next_ns); these are never earlier than its grant, so E stays exact
        pending[i] = _INF if self._received[i] >= expected[i] else pending_new[i]
        dead, totals = self._dead, self.sent_totals[i]
        for key, (count, earliest) in report.sent.items():
            totals[key] = totals.get(key, 0) + count
            for r in self._receivers.get(key, ()):
                if dead[r]:
                    continue
                expected[r] += count
                if earliest < pending[r]:
                    pending[r] = earliest
                if earliest < pending_new[r]:
                    pending_new[r] = earliest
        if report.killed_ns is not None:
            self._die(i, report.killed_ns)
        return True

    def kill(self, agent: str, at_ns: int | None = None) -> list[Grant]:
        """Declare ``agent`` dead (its process ended without a last report); return grants."""
        i = self._index[agent]
        if not self._dead[i]:
            self._die(i, self.now_ns() if at_ns is None else at_ns)
        return self._after_change()

    def quarantine(self, agent: str, at_ns: int) -> list[Grant]:
        """Declare ``agent`` dead at ``at_ns`` and take it out of every count (see the module
        docstring): its keys are cut; return grants."""
        i = self._index[agent]
        if not self._dead[i]:
            self._die(i, int(at_ns))
        self._restarts.pop(i, None)       # never back: a report in its name may be forged
        self._rejoining.pop(i, None)
        if i in self._quarantined:
            return self._after_change()
        self._quarantined.add(i)
        for key in self.topology.publishes(agent):
            for r in self._receivers.get(key, ()):
                self._cut_keys[r] = (*self._cut_keys.get(r, ()), key)
                if not self._dead[r]:
                    self._expected[r] -= self._counted_for(r, i, key)
                    # its last report no longer says what it holds (see take_report)
                    self._received[r] = -1
                    self._pending[r] = min(self._pending[r], self._pending_new[r])
        return self._after_change()

    def _grant(self, b: int, until_ns: int) -> Grant:
        """The grant to ``b`` up to ``until_ns``: every message sent to it, the cut keys."""
        return Grant(self.agents[b], until_ns, self._expected[b], self._cut_keys.get(b, ()),
                     len(self._quarantined))

    def _counted_for(self, r: int, i: int, key: str) -> int:
        """What ``i``'s reports counted on ``key`` since ``r`` last (re)joined."""
        base = self._rejoin_totals.get(r, {})
        return self.sent_totals[i].get(key, 0) - base.get((i, key), 0)

    def plan_restart(self, agent: str, at_ns: int) -> None:
        """A new process of ``agent`` will start at sim time ``at_ns`` (a barrier until then)."""
        self._restarts[self._index[agent]] = int(at_ns)

    def cancel_restart(self, agent: str) -> list[Grant]:
        """The restart of ``agent`` will not happen (e.g. its process failed to start)."""
        i = self._index[agent]
        self._restarts.pop(i, None)
        self._rejoining.pop(i, None)
        return self._after_change()

    def hold(self, at_ns: int) -> None:
        """No grant reaches beyond sim time ``at_ns`` until :meth:`release` (a barrier: the
        run's infrastructure changes there, e.g. a site router restarted). Holds at one time
        add up: each needs its own release."""
        self._holds[int(at_ns)] = self._holds.get(int(at_ns), 0) + 1

    def held_at(self) -> int | None:
        """The hold the run has reached, or None: every live agent idle with everything before
        it processed, and every message sent to it counted in its last report -- nothing of
        the run is in flight. (An agent that has not counted a message sent to it before the
        hold gets a grant that does not advance: it waits for the message and reports,
        :meth:`_grants`.)"""
        at = self._reached_hold()
        if at is None or any(r < x for r, x, dead in zip(self._received, self._expected,
                                                          self._dead) if not dead):
            return None
        return at

    def release(self, at_ns: int) -> list[Grant]:
        """Lift one hold at ``at_ns``; return the grants that follow."""
        at = int(at_ns)
        if self._holds.get(at, 0) > 1:
            self._holds[at] -= 1
        else:
            self._holds.pop(at, None)
        return self._after_change()

    def _reached_hold(self) -> int | None:
        """The earliest hold, if every live agent is idle and has processed everything before
        it; else None."""
        if not self._holds or not self._started or not all(self._idle):
            return None
        at = min(self._holds)
        live = [e for e, dead in zip(self._effective(), self._dead) if not dead]
        return at if all(e >= at for e in live) else None

    def _synced_at_hold(self) -> list[Grant]:
        """At a reached hold, a grant to its last granted time (it does not advance) for each
        live agent that has not counted every message sent to it: the agent waits for them,
        then reports (see :meth:`held_at`)."""
        if self._reached_hold() is None:
            return []
        out = []
        for b, agent in enumerate(self.agents):
            if not self._dead[b] and self._received[b] < self._expected[b]:
                self._grant_expect[b] = self._expected[b]
                self._idle[b] = self._hello[b] = False
                out.append(self._grant(b, self._granted[b]))
        self.grants_issued += len(out)
        return out

    def inject(self, agents) -> None:
        """``up`` sent one message to each of ``agents``: they must receive it (live ones)."""
        for agent in agents:
            i = self._index[agent]
            if not self._dead[i]:
                self._expected[i] += 1

    def take_rejoined(self) -> list[tuple[str, int]]:
        """``(agent, restart ns)`` of the agents taken back since the last call."""
        taken, self.rejoined = self.rejoined, []
        return taken

    def busy(self) -> list[str]:
        """Live agents granted a window whose report has not come yet."""
        return [a for i, a in enumerate(self.agents) if not self._idle[i] and not self._dead[i]]

    def describe_busy(self) -> list[str]:
        """Each agent of :meth:`busy` with its grant: ``"measurement (granted to 412.3 s once
        it has 5123 messages; 5120 at its report before)"`` -- a stalled run says whether the
        agent waits for messages that never came, or got them and did not report."""
        out = []
        for agent in self.busy():
            i = self._index[agent]
            before = (f"{self._received[i]} at its report before" if self._received[i] >= 0
                      else "its report before was made before a quarantine")
            out.append(f"{agent} (granted to {self._granted[i] / 1e9:.6g} s once it has "
                       f"{self._grant_expect[i]} messages; {before})")
        return out

    def is_dead(self, agent: str) -> bool:
        return self._dead[self._index[agent]]

    def granted_ns(self, agent: str) -> int:
        """How far ``agent`` has been granted, ns."""
        return self._granted[self._index[agent]]

    def start(self) -> list[Grant]:
        """Begin granting (after every agent's first report); return the first grants.

        Raises
        ------
        ClockError
            If an agent has not reported yet.
        """
        missing = [a for a, r in zip(self.agents, self._reported) if not r]
        if missing:
            raise ClockError(f"cannot start: no report yet from {', '.join(missing)}")
        self._started = True
        return self._grants()

    @property
    def finished(self) -> bool:
        """True when every agent is idle, none has an event at or before ``end_ns`` and no
        restart is due by then."""
        if not self._started or not all(self._idle):
            return False
        if any(t <= self.end_ns for t in [*self._restarts.values(), *self._holds]):
            return False
        return min(self._effective()) > self.end_ns

    def now_ns(self) -> int:
        """The time before which every agent has processed everything (the global frontier)."""
        earliest = min(self._effective(), default=_INF)
        return int(min(max(earliest, 0), self.end_ns + 1))

    # -- internals ---------------------------------------------------------------------------

    def _die(self, i: int, at_ns: int) -> None:
        self._dead[i] = True
        self._idle[i] = True
        self._next[i] = self._pending[i] = self._pending_new[i] = _INF
        self.killed_at[self.agents[i]] = int(at_ns)

    def _barrier(self) -> float:
        return min([*self._restarts.values(), *self._holds], default=_INF)

    def _after_change(self) -> list[Grant]:
        if not self._started:
            return []
        self._take_rejoins()
        return self._grants()

    def _take_rejoins(self) -> None:
        """Take a restarted agent's first report once every live agent has reached its
        restart time (see the module docstring)."""
        for i, report in sorted(self._rejoining.items()):
            at = self._restarts[i]
            live = [b for b in range(len(self.agents)) if not self._dead[b]]
            if not all(self._idle[b] for b in live):
                return
            e = self._effective()
            if any(e[b] < at for b in live):
                continue
            del self._rejoining[i], self._restarts[i]
            self._dead[i] = False
            self._next[i] = _INF if report.next_ns is None else report.next_ns
            self._pending[i] = self._pending_new[i] = _INF
            self._expected[i] = self._received[i] = report.received
            self._rejoin_totals[i] = {
                (p, key): total for p, totals in enumerate(self.sent_totals)
                for key, total in totals.items() if i in self._receivers.get(key, ())}
            self._granted[i] = at
            self._idle[i] = self._reported[i] = self._hello[i] = True
            self.reports_received += 1
            self.rejoined.append((self.agents[i], at))
            if self._on_rejoin is not None:
                self._on_rejoin(self.agents[i], at)

    def _effective(self) -> list:
        return [n if n < p else p for n, p in zip(self._next, self._pending)]

    def _fallback(self, candidates: list, e: list) -> list:
        """Nothing can make a full window and nothing runs: let the agents of one kind with the
        earliest next event go (the kind listed last, e.g. the DERs, on a tie). Granting one
        stage at a time staggers the stages around the control loop, after which every stage
        makes full windows (one cycle's lookahead) in turn."""
        earliest = min(e[b] for b, _, _ in candidates)
        first = [c for c in candidates if e[c[0]] == earliest]
        kind = max((self._kind[b] for b, _, _ in first), key=self._kind_rank.__getitem__)
        return [c for c in first if self._kind[c[0]] == kind]

    def _lbts(self, b: int, e: list, e_min: float, horizon: int) -> float:
        """``min(horizon, min_p (E_p + lookahead(p, b)))``, ns, given every agent's ``E`` and
        their least ``e_min``.

        No source ``p`` gives less than ``e_min + lookahead(p, b)``, and the sources come
        nearest first: the search stops at the first one with ``e_min + lookahead`` at or
        beyond the bound found so far. Exact; with hundreds of agents each has hundreds of
        sources, and this runs for every idle agent at every report (300 DERs: 13 ms a call
        before, 44.6 of 53 s of an in-process run)."""
        lbts = horizon
        for p, d in self._sources[b]:
            if e_min + d >= lbts:
                break
            t = e[p] + d
            if t < lbts:
                lbts = t
        return lbts

    def _grants(self) -> list[Grant]:
        e = self._effective()
        barrier = self._barrier()
        horizon = int(min(self.end_ns + 1, barrier))
        granted, dead = self._granted, self._dead
        e_min = min(e, default=_INF)
        candidates = []
        for b, idle in enumerate(self._idle):
            if not idle or dead[b]:
                continue
            eb = e[b]
            if eb >= horizon:
                continue
            lbts = self._lbts(b, e, e_min, horizon)
            if eb < lbts and lbts > granted[b]:
                candidates.append((b, int(lbts), lbts - eb >= self._min_window[b]
                                   or lbts == horizon))
        chosen = [c for c in candidates if c[2]]
        if not chosen and candidates and all(self._idle):
            chosen = self._fallback(candidates, e)
        out = []
        for b, until, _ in chosen:
            granted[b] = until
            self._grant_expect[b] = self._expected[b]
            self.grants_per_agent[b] += 1
            self._idle[b] = self._hello[b] = False
            self._pending_new[b] = _INF
            out.append(self._grant(b, until))
        self.grants_issued += len(out)
        if not out and self._holds and all(self._idle):
            return self._synced_at_hold()
        if not out and all(self._idle) and not self.finished and barrier > self.end_ns:
            raise ClockError(
                "deadlock: every agent is idle, none may advance "
                f"(earliest event {min(e)} ns, end {self.end_ns} ns)")
        return out
