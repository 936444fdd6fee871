"""Faults in a running ``adnmesh up``: injecting them, killing and restarting agents, and
surviving agents that die on their own.

:class:`FaultInjector` is ``up``'s side of :mod:`adnmesh.sim.faults`:

- the config's faults are sent (``faults``) before the clock starts, requests from
  ``adnmesh fault`` (``control/fault``) while it runs — in sim time at the requested instant or,
  if the run has passed it, at the earliest instant no agent has reached yet; in real time at
  once — each acknowledged by an event of ``up`` naming the request;
- an agent that reaches an injected kill reports its last window; ``up`` acknowledges it (the
  agent then SIGKILLs itself), notes the death in the sim clock and, if the fault has an end,
  starts a new process at the end's sim time (the clock's barrier keeps the run deterministic);
- an agent whose process ends otherwise is declared dead in the clock (the others go on) and
  said to have been lost;
- a restarted agent gets the run's start announcement and every fault still to come.

Everything it does is an event on ``event/up``.
"""

from __future__ import annotations

import subprocess
import threading
import time
import uuid

from adnmesh.sim.faults import FaultError, FaultPlan, PlannedFault, fault_events, resend_body
from adnmesh.names import LAUNCHER

__all__ = ["FaultInjector", "new_request_id"]


def new_request_id() -> str:
    """A fresh id for a fault request."""
    return uuid.uuid4().hex[:16]


class FaultInjector:
    """See the module docstring. ``launch`` is the launcher's run state (``_Launch``)."""

    def __init__(self, launch) -> None:
        self.launch = launch
        self.keys = launch.keys
        self.plan = FaultPlan(launch.config, launch.topology.agents)
        self._lock = threading.Lock()
        self.dying: dict[str, int] = {}        # agent -> kill ns (a death we expect)
        self.killed: set[str] = set()          # agents that lost a process (counts unverified)
        self._restart_at: dict[str, int] = {}  # agent -> restart ns still to come
        self._spawned: set[str] = set()        # restarted, start not yet re-announced
        self._attempts: dict[str, int] = {}    # unplanned deaths per agent
        self.lost: list[str] = []
        self.left_early: set[str] = set()      # lost by a goodbye up did not ask for
        self.gone_at: dict[str, int] = {}      # agent -> when it died or stopped for good, ns
        self.quarantined: set[str] = set()     # agents someone else sent as
        self.planned_drops: set[str] = set()   # agents whose session a planned site router
        #                                        restart drops (said by the site, not here)

    # -- before the start ----------------------------------------------------------------------

    def start_faults(self) -> None:
        """Send the config's faults and plan their restarts (before the clock starts)."""
        self.plan.from_config(self.launch.config)
        for planned in self.plan.faults:
            self._send(planned, 0)
        for agent, at in self.plan.restarts():
            self._plan_restart(agent, at)

    # -- Zenoh callbacks -----------------------------------------------------------------------

    def on_request(self, request) -> None:
        """A fault request from ``adnmesh fault`` (validated by the tap): inject it or say
        why not."""
        self._request(request)

    def quarantine(self, agent: str, why: str) -> None:
        """Someone else sends with ``agent``'s identity (the recorder found traffic of its that
        no genuine agent sends: :data:`~adnmesh.wire.gate.SUSPICIOUS`, or a clock report out
        of the protocol): cut it off in every receiver and end it at the earliest instant no
        agent has reached, as a kill without restart (origin ``quarantine``); its DER counts
        as unavailable from then on and the run goes on without it.

        On the sim clock the agent is dead for the clock at once, and its process (one of its
        own) is killed by PID: from now on a report in its name may be the forger's, so the
        clock must not wait for one (a forged report taken while the genuine agent was busy
        once left the clock waiting for a window that never came)."""
        with self._lock:
            if agent in self.quarantined:
                return
            self.quarantined.add(agent)
            self.killed.add(agent)              # its counts cannot be verified
            self._restart_at.pop(agent, None)   # never back (the clock takes none either)
        launch = self.launch
        with launch.clock_lock():
            at = self._earliest_ns()
            planned = self.plan.add("kill", at, None, earliest_ns=at, origin="quarantine",
                                    agent=agent)
            launch.tap.cut_off(agent, at)
            self._send(planned, at)
            if launch.clock is not None:
                with self._lock:
                    self.dying[agent] = at      # its process's end is ours, not a loss
                    self.gone_at[agent] = at
                launch.clock.quarantine(agent, at)
        if launch.clock is not None:
            self._end_process(agent)
        text = (f"{agent} quarantined at {at / 1e9:g} s: {why}; nothing it sends from then on "
                "is taken, the run goes on without it")
        self.launch.options.log(text)
        self._event(at, "ERROR", "quarantined", text[:500], subject=agent)

    def _end_process(self, agent: str) -> None:
        """SIGKILL ``agent``'s process by PID if it is its own and still runs (a process that
        hosts other agents goes on: the agent is dead for the clock and never granted
        again; an external agent is not ours to end)."""
        children = self.launch.children
        proc = children.procs.get(agent)
        if proc is None or children.shares_process(agent):
            return
        proc.kill()     # by PID, unless it has ended already

    def on_killed(self, message) -> None:
        """An agent's last report before its injected kill."""
        agent = message.src
        with self._lock:
            self.dying[agent] = message.killed_ns
            self.killed.add(agent)
            restart = self._restart_at.get(agent)
        launch = self.launch
        if restart is None:
            self.gone_at[agent] = message.killed_ns
        if launch.children.shares_process(agent):   # a hosted agent leaves; its process stays
            launch.children.leave(agent)
        launch.outbox.send(self.keys.of("clock_kill", agent), message.killed_ns, reason="killed")
        self._event(message.killed_ns, "WARNING", "killed", f"{agent} killed at "
                    f"{message.killed_ns / 1e9:g} s (injected fault)", subject=agent)
        if restart is not None and launch.clock is not None:
            self._respawn(agent, restart)

    def on_rejoin(self, agent: str, at_ns: int) -> None:
        """The sim clock took a restarted agent back at ``at_ns`` (under the clock's lock)."""
        with self._lock:
            self._restart_at.pop(agent, None)
        self._event(at_ns, "INFO", "rejoined", f"{agent} restarted and rejoined at "
                    f"{at_ns / 1e9:g} s", subject=agent)
        for planned in self.plan.faults:
            body = resend_body(planned, at_ns)
            if body is not None:
                self._send(planned, at_ns, body, announce=False)

    # -- the main thread -----------------------------------------------------------------------

    def supervise(self) -> None:
        """Deaths, restarts due (real time), start announcements for restarted agents."""
        launch = self.launch
        for agent, code in launch.children.dead():
            if agent in self.lost or agent in launch.roster.byes:
                continue
            with self._lock:
                expected = agent in self.dying
            if not expected:
                self._lost(agent, code)
        with self._lock:
            due = [(a, t) for a, t in self._restart_at.items()
                   if launch.clock is None and a in self.dying and t <= self.realtime_ns()]
        for agent, at in due:
            with self._lock:
                self._restart_at.pop(agent, None)
            self._respawn(agent, at)
        alive = launch.roster.alive_now()   # before the changes: a restart's token is among them
        self._sessions(launch.roster.session_changes())
        for agent in sorted(self._spawned & alive):
            self._spawned.discard(agent)
            launch.announce_start()

    # -- internals -----------------------------------------------------------------------------

    def _sessions(self, changes) -> None:
        """A running agent whose session dropped (under load) is a fault the run survives:
        say it and when it is back (Zenoh reconnects; what was sent meanwhile is late or
        lost and counted)."""
        running = self.launch.children.running()
        for agent, back in changes:
            if agent in self.planned_drops:     # a site router's planned restart: said there
                if back:
                    self.planned_drops.discard(agent)
                continue
            with self._lock:
                expected = agent in self.dying or agent in self._spawned
            if agent not in running or expected:
                continue      # a death or a restart: the injector's own business
            what = "is back" if back else \
                "dropped (the process runs): waiting for it to reconnect" \
                if agent in self.launch.children.procs else \
                f"dropped: waiting up to {self.launch.children.grace_s:g} s for it to reconnect"
            self.launch.options.log(f"{agent}'s Zenoh session {what}")
            self._event(self._earliest_ns(), "INFO" if back else "WARNING",
                        "session_back" if back else "session_lost",
                        f"{agent}'s Zenoh session {what}", subject=agent)

    def _request(self, request) -> None:
        rid = request.request_id
        target = {k: getattr(request, k) for k in ("link", "der", "agent", "probability",
                                                   "delay_ns")}
        try:
            with self.launch.clock_lock():
                earliest = self._earliest_ns()
                at = earliest if request.at_ns is None else request.at_ns
                planned = self.plan.add(request.kind, at, request.for_ns, earliest_ns=earliest,
                                        **target)
                self._send(planned, earliest, request_id=rid)
                if planned.body["kind"] == "kill" and planned.body["end_ns"] is not None:
                    self._plan_restart(planned.body["agent"], planned.body["end_ns"])
        except FaultError as exc:
            self._event(self._earliest_ns(), "ERROR", "fault_refused",
                        f"fault request refused: {exc}", request_id=rid)
            return
        self.launch.options.log(fault_events(planned)["text"])

    def _send(self, planned: PlannedFault, t_send: int, body: dict | None = None,
              request_id: str | None = None, announce: bool = True) -> None:
        """Send a fault to every agent (counted by the sim clock) and, the first time, say so."""
        launch = self.launch
        body = planned.body if body is None else body
        if launch.clock is not None:
            launch.clock.inject(launch.topology.agents)
        launch.outbox.send(self.keys.of("fault"), t_send,
                           t_deliver_ns=max(body["start_ns"], t_send),
                           **body)
        if announce:
            event = fault_events(planned)
            if request_id is not None:
                event["request_id"] = request_id
            launch.outbox.send(self.keys.of("event", LAUNCHER), t_send, **event)

    def _plan_restart(self, agent: str, at_ns: int) -> None:
        with self._lock:
            self._restart_at[agent] = at_ns
        if self.launch.clock is not None:
            self.launch.clock.coordinator.plan_restart(agent, at_ns)

    def _respawn(self, agent: str, at_ns: int) -> None:
        launch = self.launch
        old = launch.children.procs.get(agent)
        if old is not None and old.poll() is None and agent not in launch.children.left:
            # it should have killed itself (a hosted agent has left its process instead)
            try:
                old.wait(timeout=3.0)
            except subprocess.TimeoutExpired:   # still there: kill it by PID
                old.kill()
                old.wait()
        launch.spawn(agent, resume_ns=at_ns)
        with self._lock:
            self.dying.pop(agent, None)
        self._spawned.add(agent)
        launch.options.log(f"{agent} restarting at {at_ns / 1e9:g} s "
                           f"({launch.children.describe(agent)})")

    def said_bye_early(self, agent: str) -> None:
        """``agent`` said goodbye while the run goes on (it was told to stop: SIGTERM on its
        host, or a clock stop or a withdrawn liveliness of ``up`` that ``up`` did not send):
        it is lost, the run goes on without it."""
        if agent not in self.lost:
            self.left_early.add(agent)
            self._lost(agent, None, f"agent {agent} said goodbye before the end of the run "
                       f"({self.launch.children.describe(agent)}; it was told to stop, but "
                       "not by up)")

    def early_end(self) -> str | None:
        """Why the run ends before its end although nobody stopped it, or None: every agent
        is gone for good (died, killed without restart, or said goodbye to a stop ``up`` did
        not send). Such a run is not finished, whatever the clock says: its clock runs out
        because nobody is left."""
        with self._lock:
            gone = set(self.gone_at) - set(self._restart_at)
            early = sorted(self.left_early & gone)
            at = max(self.gone_at.values(), default=0)
        if not gone >= set(self.launch.topology.agents):
            return None
        end = self.launch.result.end_ns
        if early:
            return (f"stopped early: {len(early)} agent(s) stopped at {at / 1e9:g} s of "
                    f"{end / 1e9:g} s, told to stop (a clock stop or a withdrawn liveliness of "
                    "up from someone else) but up sent no stop")
        return f"stopped early: every agent died by {at / 1e9:g} s of {end / 1e9:g} s"

    def _lost(self, agent: str, code: int | None, description: str | None = None) -> None:
        """A process ended without an injected kill (or its last report never came)."""
        launch = self.launch
        self.lost.append(agent)
        self.killed.add(agent)
        description = description or launch.children.describe_death(agent, code)
        now = self._earliest_ns()
        with self._lock:
            restart = self._restart_at.get(agent)
            self._attempts[agent] = self._attempts.get(agent, 0) + 1
            again = restart is not None and self._attempts[agent] <= 2
            if not again:
                self.gone_at[agent] = now
        if launch.clock is not None:
            launch.clock.kill(agent)
            if restart is not None and not again:
                launch.clock.cancel_restart(agent)
        what = "the run goes on without it"
        if again:
            what = f"restarting it at {restart / 1e9:g} s as planned"
            self.lost.remove(agent)
        launch.options.log(f"{description}; {what}")
        self._event(now, "ERROR", "agent_lost", f"{description}; {what}", subject=agent)
        if again and launch.clock is not None:
            self._respawn(agent, restart)

    def _earliest_ns(self) -> int:
        clock = self.launch.clock
        if clock is None:
            return self.realtime_ns() + 10_000_000
        return clock.earliest_unprocessed_ns()

    def realtime_ns(self) -> int:
        """Sim time on the realtime clock now, ns (0 before the start)."""
        epoch, speed = self.launch.epoch_ns, self.launch.options.speed
        return max(0, int((time.time_ns() - epoch) * speed)) if epoch else 0

    def _event(self, t_ns: int, level: str, kind: str, text: str, **extra) -> None:
        self.launch.outbox.send(self.keys.of("event", LAUNCHER), t_ns, level=level, kind=kind,
                                text=text, **extra)
