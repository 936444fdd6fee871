"""The site routers of a hierarchy's run of ``adnmesh up`` (docs/hierarchy.md#sites).

Every ADN of a hierarchy is a site: a Zenoh router of its own (``adnmesh router``, a process
``up`` starts, tracks by PID and ends) linked to ``up``'s router, with the ADN's agents and the
upper level's site agent of that ADN as its clients. What the agents of one site say to each
other stays at the site router; what goes to the level above (and to ``up``'s recorders) crosses
the link.

**A site router killed and restarted** (``site_restarts`` of the hierarchy file) at sim time
``T``: the sim clock holds every agent at ``T`` (:meth:`~adnmesh.sim.clock.Coordinator.hold`).
Once the run is there -- every agent idle with everything before ``T`` processed, and every
message the agents say they sent recorded by ``up``, so none is in a router's queue (waited
for at most :data:`RECORDED_WITHIN_S`) -- ``up`` SIGKILLs the router, waits until it has seen
every session of the site go, starts the router again on the same endpoint after ``down_s``
wall seconds and releases the clock once every session is back (Zenoh reconnects them). What
the run's agents send is what they send without the restart (``up`` adds its ``site_down`` and
``site_back`` events). A site whose sessions do not come back within :data:`BACK_WITHIN_S` of
the kill is said and released anyway: its agents, gone, are the injector's (lost; the level
above sees the ADN unavailable). The routers run in sessions of their own (a Ctrl-C in the
terminal is ``up``'s to handle, not theirs).
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
"""How long after the kill a site's sessions may take to come back, wall s (its agents wait as
long for ``up`` before they stop)."""
GONE_WITHIN_S = 2.0
"""How long after ``down_s`` the router is started again even if ``up`` has not seen every
session of the site go, wall s."""
RECORDED_WITHIN_S = 5.0
"""How long the held run may wait for the recorders to have every message the agents reported
sent, wall s (a payload the recorder rejects never counts: then the router goes anyway)."""
_STOP_WAIT_S = 5.0


@dataclass
class PlannedRestart:
    """A restart of the site router at sim time ``at_ns``, down for ``down_s`` wall s; its
    progress: ``state`` (``planned``, ``down``, ``back``, ``done``), since when (held, then
    killed; monotonic s) and the agents whose sessions it waits for (``(launch, agent id)``,
    those alive at the kill)."""

    at_ns: int
    down_s: float
    state: str = "planned"
    since: float = 0.0
    expected: list = field(default_factory=list)


@dataclass
class SiteRouter:
    """One site's router process (see the module docstring).

    Attributes
    ----------
    name : str
        The site's name (its ADN's id; identity ``router/<name>``).
    config : Path
        The ADN's config file (with ``levels``, the access control derives from the levels
        file).
    endpoint : str
        Where it listens (its agents connect there), ``tcp/127.0.0.1:<port>`` (``tls/`` in the
        secure profile).
    members : dict
        Grid -> the agent ids of that level behind this router.
    restarts : list of PlannedRestart
    certs : Path, optional
        The secure profile's certificate directory (its own ``router/<name>``; the access
        control of the hierarchy's levels file on its clients).
    levels : Path, optional
        The levels file (the hierarchy's topology: the access control, the site's recording).
    record_to : Path, optional
        Record what the site's agents publish (:mod:`adnmesh.runtime.site_recorder`) beside
        this recording: ``<stem>.<name>.site.mcap``, ``<stem>.<name>.site.1.mcap`` after a
        restart...; ``recordings`` lists them.
    run_id : str
        The run's id (in the site's recordings).
    """

    name: str
    config: Path
    endpoint: str
    members: dict[str, tuple[str, ...]]
    restarts: list[PlannedRestart] = field(default_factory=list)
    certs: Path | None = None
    levels: Path | None = None
    record_to: Path | None = None
    run_id: str = ""
    recordings: list[Path] = field(default_factory=list)
    proc: subprocess.Popen | None = None
    upstream: str = ""
    said: list[str] = field(default_factory=list)     # its last lines on stderr

    def start(self, upstream: str) -> str | None:
        """Start the router linked to ``upstream`` and wait until it listens; return why it
        did not, or None."""
        self.upstream = upstream
        argv = [sys.executable, "-m", "adnmesh", "router", str(self.config), "--name",
                self.name, "--connect", upstream, "--listen", self.endpoint]
        for flag, path in (("--certs", self.certs), ("--levels", self.levels)):
            if path is not None:
                argv += [flag, str(path)]
        if self.record_to is not None:     # <stem>.<adn>.site[.n].mcap: no grid's name has a .
            n = len(self.recordings)
            path = self.record_to.with_name(
                f"{self.record_to.stem}.{self.name}.site{f'.{n}' if n else ''}.mcap")
            path.unlink(missing_ok=True)    # an earlier run's, never this one's
            self.recordings.append(path)
            argv += ["--record", str(path), "--run-id", self.run_id]
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, start_new_session=True,
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
        restart (before it starts); they are taken in time order."""
        self.restarts.sort(key=lambda r: r.at_ns)
        for restart in self.restarts:
            clock.hold(restart.at_ns)

    def supervise(self, clock, launches) -> None:
        """Take the next planned restart one step on (see the module docstring); ``launches``:
        every level's launch, the upper first (its events say the restart)."""
        restart = next((r for r in self.restarts if r.state != "done"), None)
        if restart is None:
            return
        now = time.monotonic()
        if restart.state == "planned":
            self._when_held(restart, clock, launches, now)
            return
        present = [a in launch.roster.alive_now() for launch, a in restart.expected]
        down_s = now - restart.since
        gone = not any(present) and down_s >= restart.down_s
        if restart.state == "down" and (gone or down_s > restart.down_s + GONE_WITHIN_S):
            failed = self.start(self.upstream)
            if failed is not None:
                launches[0].options.log(failed)
            restart.state = "back"
        elif restart.state == "back" and (all(present) or now - restart.since > BACK_WITHIN_S):
            for (launch, agent), here in zip(restart.expected, present):
                if not here:               # gone for good: the injector's (a back is its own)
                    launch.injector.planned_drops.discard(agent)
            pid = self.proc.pid if self.proc is not None else None
            self._say(launches[0], restart, "INFO" if all(present) else "WARNING", "site_back",
                      f"site router {self.name} back (pid {pid}): {sum(present)} of "
                      f"{len(present)} agents reconnected {now - restart.since:.1f} s after "
                      "the kill; the run goes on")
            restart.state = "done"
            clock.release(restart.at_ns)

    def _when_held(self, restart: PlannedRestart, clock, launches, now: float) -> None:
        """Kill the router once the run is held at the restart and every message the agents
        reported sent is recorded (or :data:`RECORDED_WITHIN_S` after the hold)."""
        if clock.held_at() != restart.at_ns:
            return
        restart.since = restart.since or now      # held since
        if not _all_recorded(clock, launches) and now - restart.since < RECORDED_WITHIN_S:
            return
        by_grid = {launch.config.grid: launch for launch in launches}
        restart.expected = [(by_grid[g], a) for g, agents in self.members.items()
                            for a in agents if a in by_grid[g].roster.alive_now()]
        for launch, agent in restart.expected:
            launch.injector.planned_drops.add(agent)
        pid = self.proc.pid if self.proc is not None else None
        self.kill()
        restart.state, restart.since = "down", now
        self._say(launches[0], restart, "WARNING", "site_down",
                  f"site router {self.name} (pid {pid}) killed at {restart.at_ns / 1e9:g} s "
                  f"(planned); the run waits for its {len(restart.expected)} agents")

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
