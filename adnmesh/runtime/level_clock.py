"""One sim clock for every level of a hierarchy's run of ``adnmesh up`` (docs/hierarchy.md).

Each level of a hierarchy runs as a launch of its own (:mod:`adnmesh.runtime.launcher`: its
subscriptions on ``adn/<grid>/**``, roster, recorder, fault injector, agent ids as its config
has them), but all on one clock: one :class:`~adnmesh.sim.clock.Coordinator` over the
hierarchy's topology, whose agents are named ``<grid>:<agent id>``
(:mod:`adnmesh.sim.hierarchy_topology`), as in the in-process run. :class:`SharedClock` drives
it; each launch joins it and gets a :class:`LevelClock`, the interface of
:class:`~adnmesh.runtime.launcher_bus.SimClockDriver` in that launch's own agent ids. Grants go
out on each level's own keys, recorded by that level's recorder.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from adnmesh.runtime.launcher_bus import LauncherOutbox, SimClockDriver, publish_grants
from adnmesh.sim.clock import Coordinator
from adnmesh.sim.hierarchy_topology import grid_of, qualified
from adnmesh.wire.keys import Keys

__all__ = ["LevelClock", "SharedClock"]


@dataclass
class _Level:
    """What the clock needs of one level's launch: its keys, the outbox its grants go through,
    ``host_of(agent)`` (its hosting process or None), and where a DER's report out of protocol
    and a restarted agent's rejoin go (``(agent id, why)``, ``(agent id, ns)``)."""

    keys: Keys
    outbox: LauncherOutbox
    host_of: Callable[[str], str | None]
    on_violation: Callable[[str, str], None] | None
    on_rejoin: Callable[[str, int], None] | None


class SharedClock(SimClockDriver):
    """The sim clock of a hierarchy's run (see the module docstring).

    Parameters
    ----------
    topology : Topology
        The hierarchy's topology (qualified agent names).
    end_ns : int
        The run's end, ns.
    wake : threading.Event
        Set when the run finished or the clock failed (the event every level's roster sets).
    """

    def __init__(self, topology, end_ns: int, wake: threading.Event) -> None:
        self._levels: dict[str, _Level] = {}
        super().__init__(Coordinator(topology, end_ns, on_rejoin=self._rejoined), None, None,
                         wake.set, on_violation=self._violation)

    def join(self, grid: str, keys, outbox, host_of=None, on_violation=None,
             on_rejoin=None) -> LevelClock:
        """The clock of level ``grid``: its grants on ``keys`` through ``outbox`` (those of
        one hosting process, ``host_of``, in one sample); a DER's report out of protocol to
        ``on_violation(agent, why)``, a restarted agent's rejoin to ``on_rejoin(agent, now)``."""
        self._levels[grid] = _Level(keys, outbox, host_of or (lambda agent: None),
                                    on_violation, on_rejoin)
        return LevelClock(self, grid)

    def hold(self, at_ns: int) -> None:
        """No grant beyond sim time ``at_ns`` until :meth:`release`."""
        with self.lock:
            self.coordinator.hold(at_ns)

    def held_at(self) -> int | None:
        """The hold the run has reached (:meth:`~adnmesh.sim.clock.Coordinator.held_at`)."""
        with self.lock:
            return self.coordinator.held_at()

    def release(self, at_ns: int) -> None:
        """Lift one hold at ``at_ns``; the grants that follow go out."""
        with self.lock:
            self.last_grant_s = time.monotonic()     # the hold was no stall
            self._send(self.coordinator.release(at_ns))

    def stalled_s(self) -> float:
        """Wall seconds since the last grant, 0 while the run is at a hold (a site router's
        restart takes its time there: no stall)."""
        with self.lock:
            if self.coordinator.held_at() is not None:
                self.last_grant_s = time.monotonic()
            return super().stalled_s()

    def sent_per_key(self) -> dict[str, int]:
        """Messages the agents reported sent so far, per key."""
        with self.lock:
            total: dict[str, int] = {}
            for sent in self.coordinator.sent_totals:
                for key, count in sent.items():
                    total[key] = total.get(key, 0) + count
            return total

    def _publish(self, grants, t: int) -> None:   # with the lock held
        per_level: dict[str, list] = {}
        for g in grants:
            grid, agent = grid_of(g.agent)
            per_level.setdefault(grid, []).append((agent, g))
        for grid, mine in per_level.items():
            level = self._levels[grid]
            publish_grants(level.keys, level.outbox, level.host_of, mine, t)

    def _violation(self, name: str, why: str) -> None:
        grid, agent = grid_of(name)
        level = self._levels[grid]
        if level.on_violation is None:
            raise RuntimeError(why)
        level.on_violation(agent, why)

    def _rejoined(self, name: str, now: int) -> None:
        grid, agent = grid_of(name)
        level = self._levels.get(grid)
        if level is not None and level.on_rejoin is not None:
            level.on_rejoin(agent, now)


class _LevelCoordinator:
    """The shared coordinator in one level's agent ids (what a launch asks of it)."""

    def __init__(self, coordinator: Coordinator, grid: str) -> None:
        self._c, self._grid = coordinator, grid

    def granted_ns(self, agent: str):
        """How far ``agent`` has been granted, ns."""
        return self._c.granted_ns(qualified(self._grid, agent))

    def plan_restart(self, agent: str, at_ns: int) -> None:
        """A new process of ``agent`` starts at ``at_ns`` (a barrier until then)."""
        self._c.plan_restart(qualified(self._grid, agent), at_ns)

    def describe_busy(self):
        """Every level's agents the clock waits for (qualified names)."""
        return self._c.describe_busy()

    def now_ns(self) -> int:
        """The run's frontier, ns."""
        return self._c.now_ns()


class LevelClock:
    """The :class:`SharedClock` as one level's launch sees it: its own agent ids."""

    def __init__(self, shared: SharedClock, grid: str) -> None:
        self.shared, self.grid = shared, grid
        self.coordinator = _LevelCoordinator(shared.coordinator, grid)
        self.lock = shared.lock

    def _name(self, agent: str) -> str:
        return qualified(self.grid, agent)

    def on_reports(self, messages) -> None:
        """Clock reports of this level's agents (see :meth:`SimClockDriver.on_reports`)."""
        self.shared.on_reports(messages, self._name)

    def kill(self, agent: str, at_ns: int | None = None) -> None:
        """``agent`` of this level is dead (see :meth:`SimClockDriver.kill`)."""
        self.shared.kill(self._name(agent), at_ns)

    def quarantine(self, agent: str, at_ns: int) -> None:
        """``agent`` of this level is quarantined (see :meth:`SimClockDriver.quarantine`)."""
        self.shared.quarantine(self._name(agent), at_ns)

    def inject(self, agents) -> None:
        """``up`` sent one message to each of this level's ``agents``."""
        self.shared.inject([self._name(a) for a in agents])

    def cancel_restart(self, agent: str) -> None:
        """The planned restart of ``agent`` of this level will not happen."""
        self.shared.cancel_restart(self._name(agent))

    def start(self) -> None:
        """Begin granting (once, for every level)."""
        with self.shared.lock:
            if not self.shared._started:
                self.shared.start()

    def now_ns(self) -> int:
        """The run's frontier, ns (every level's)."""
        return self.shared.now_ns()

    def earliest_unprocessed_ns(self) -> int:
        """The earliest time no live agent of any level may have processed yet, ns."""
        return self.shared.earliest_unprocessed_ns()

    def stalled_s(self) -> float:
        """Wall seconds since the run's last grant (0 at a hold)."""
        return self.shared.stalled_s()

    @property
    def finished(self) -> bool:
        """The run (every level) is at its end."""
        return self.shared.finished

    @property
    def error(self):
        """Why the shared clock failed, or None."""
        return self.shared.error

    @property
    def grants_issued(self) -> int:
        """Grants of the whole run."""
        return self.shared.grants_issued

    @property
    def recent_ns(self) -> int:
        """The frontier at the last grants, ns (read without the lock)."""
        return self.shared.recent_ns
