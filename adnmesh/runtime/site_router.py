"""The site routers of a hierarchy's run of ``adnmesh up`` (docs/hierarchy.md#sites).

Every ADN of a hierarchy is a site: a Zenoh router of its own (``adnmesh router``, a process
``up`` starts, tracks by PID and ends) linked to ``up``'s router, with the ADN's agents and the
upper level's site agent of that ADN as its clients. What the agents of one site say to each
other stays at the site router; what goes to the level above (and to ``up``'s recorders) crosses
the link.

**A site router killed and restarted** (``site_restarts`` of the hierarchy file) at sim time
``T``: the sim clock holds every agent at ``T`` (:meth:`~adnmesh.sim.clock.Coordinator.hold`);
once the run is there -- every agent idle with everything before ``T`` processed, and every
message the agents say they sent recorded by ``up`` (so none is in a router's queue) -- ``up``
SIGKILLs the router, waits until it has seen every session of the site go, starts the router
again on the same endpoint after ``down_s`` wall seconds and releases the clock once every
session is back (Zenoh reconnects them). What the run sends is what it sends without the
restart. A site whose sessions do not come back within :data:`BACK_WITHIN_S` is said and
released anyway: its agents, gone, are the injector's (lost; the level above sees the ADN
unavailable).
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from adnmesh.names import LAUNCHER
from adnmesh.runtime.children import PARENT_ENV, SESSION_GRACE_S

__all__ = ["BACK_WITHIN_S", "PlannedRestart", "SiteRouter"]

READY_WITHIN_S = 15.0
"""How long a site router may take to listen, wall s."""
BACK_WITHIN_S = SESSION_GRACE_S
"""How long a restarted site's sessions may take to come back, wall s (its agents wait as long
for ``up`` before they stop)."""
_STOP_WAIT_S = 5.0


@dataclass
class PlannedRestart:
    """A restart of the site router at sim time ``at_ns``, down for ``down_s`` wall s; its
    progress (``state``: ``planned``, ``down``, ``back``, ``done``)."""

    at_ns: int
    down_s: float
    state: str = "planned"
    since: float = 0.0


@dataclass
class SiteRouter:
    """One site's router process (see the module docstring).

    Attributes
    ----------
    name : str
        The site's name (its ADN's id; identity ``router/<name>``).
    config : Path
        The ADN's config file (the router's access control derives from it).
    endpoint : str
        Where it listens (its agents connect there), ``tcp/127.0.0.1:<port>``.
    members : dict
        Grid -> the agent ids of that level behind this router.
    restarts : list of PlannedRestart
    """

    name: str
    config: Path
    endpoint: str
    members: dict[str, tuple[str, ...]]
    restarts: list[PlannedRestart] = field(default_factory=list)
    proc: subprocess.Popen | None = None
    upstream: str = ""
    said: list[str] = field(default_factory=list)     # its last lines on stderr

    def start(self, upstream: str) -> str | None:
        """Start the router linked to ``upstream`` and wait until it listens; return why it
        did not, or None."""
        self.upstream = upstream
        argv = [sys.executable, "-m", "adnmesh", "router", str(self.config), "--name",
                self.name, "--connect", upstream, "--listen", self.endpoint]
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True,
                                     env=dict(os.environ, **{PARENT_ENV: str(os.getpid())}))
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, args=(self.proc, lines), daemon=True,
                         name=f"adnmesh-site-{self.name}").start()
        deadline = time.monotonic() + READY_WITHIN_S
        while time.monotonic() < deadline:
            try:
                line = lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            if line is None:
                break
            if "listening on" in line:
                return None
        self.kill()
        last = self.said[-1] if self.said else "no word from it"
        return f"site router {self.name} did not start within {READY_WITHIN_S:g} s ({last})"

    def _read(self, proc: subprocess.Popen, lines: queue.Queue) -> None:
        for line in proc.stderr:
            self.said = [*self.said[-9:], line.strip()]
            lines.put(line)
        lines.put(None)

    def kill(self) -> None:
        """SIGKILL the router (by PID) and reap it."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()

    def stop(self) -> None:
        """End the router (SIGTERM, then SIGKILL after :data:`_STOP_WAIT_S`), by PID."""
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(_STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            self.kill()

    def hold(self, clock) -> None:
        """Hold ``clock`` (:class:`~adnmesh.runtime.level_clock.SharedClock`) at every planned
        restart (before it starts)."""
        for restart in self.restarts:
            clock.hold(restart.at_ns)

    def supervise(self, clock, launches) -> None:
        """Take the next planned restart one step on (see the module docstring); ``launches``:
        every level's launch, the upper first (its events say the restart)."""
        restart = next((r for r in self.restarts if r.state != "done"), None)
        if restart is None:
            return
        by_grid = {launch.config.grid: launch for launch in launches}
        members = [(by_grid[g], a) for g, agents in self.members.items() for a in agents]
        alive = {id(launch): launch.roster.alive_now() for launch in launches}
        present = [a in alive[id(launch)] for launch, a in members]
        now = time.monotonic()
        if restart.state == "planned":
            if clock.held_at() != restart.at_ns or not _all_recorded(clock, launches):
                return
            for launch, agent in members:
                launch.injector.planned_drops.add(agent)
            self.kill()
            restart.state, restart.since = "down", now
            self._say(launches[0], restart, "WARNING", "site_down",
                      f"site router {self.name} killed at {restart.at_ns / 1e9:g} s (planned); "
                      f"the run waits for its {len(members)} agents")
        elif restart.state == "down":
            if (not any(present) and now - restart.since >= restart.down_s) or \
                    now - restart.since > BACK_WITHIN_S:
                failed = self.start(self.upstream)
                if failed is not None:
                    launches[0].options.log(failed)
                restart.state, restart.since = "back", now
        elif restart.state == "back" and (all(present) or now - restart.since > BACK_WITHIN_S):
            for launch, agent in members:
                launch.injector.planned_drops.discard(agent)
            back = sum(present)
            self._say(launches[0], restart, "INFO" if all(present) else "WARNING", "site_back",
                      f"site router {self.name} back: {back} of {len(members)} agents "
                      f"reconnected after {now - restart.since:.1f} s; the run goes on")
            restart.state = "done"
            clock.release(restart.at_ns)

    def _say(self, lead, restart: PlannedRestart, level: str, kind: str, text: str) -> None:
        lead.options.log(text)
        lead.outbox.send(lead.keys.of("event", LAUNCHER), restart.at_ns, level=level,
                         kind=kind, subject=f"router/{self.name}", text=text)


def _all_recorded(clock, launches) -> bool:
    """Every message the agents reported sent is recorded (none in a router's queue)."""
    recorded: dict[str, int] = {}
    for launch in launches:
        recorded.update(launch.recorder.counts())
    return all(recorded.get(k, 0) >= n for k, n in clock.sent_per_key().items())
