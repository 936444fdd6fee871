"""Who takes part in a run of ``adnmesh up``: alive, ready, said goodbye, gone.

The roster is filled by the router session's callbacks (liveliness tokens ``alive/<agent>``,
first clock reports, goodbyes) and read by the launcher's phases; every change sets
:attr:`Roster.changed` so that the main thread waits on one event, never polls blindly.
"""

from __future__ import annotations

import threading

import zenoh

from adnmesh.names import LAUNCHER

__all__ = ["Roster"]


class Roster:
    """The agents of a run and what is known of each (thread-safe).

    Parameters
    ----------
    agents : iterable of str
        Every agent id of the run.
    changed : threading.Event, optional
        The event to set on a change (default: its own; the levels of a hierarchy's run share
        one).
    """

    def __init__(self, agents, changed: threading.Event | None = None) -> None:
        self.agents = frozenset(agents)
        self.lock = threading.Lock()
        self.changed = threading.Event() if changed is None else changed
        self.alive: set[str] = set()
        self.reported: set[str] = set()
        self.unheard: dict[str, int] = {}      # reports an agent sent before up heard its first
        self.byes: dict[str, object] = {}     # agent -> its agent_bye message
        self.gone: list[str] = []             # sessions that ended without a goodbye
        self._changes: list[tuple[str, bool]] = []   # (agent, session up) after a loss

    def on_alive(self, sample: zenoh.Sample) -> None:
        """Liveliness callback: an agent's session appeared or ended."""
        agent = str(sample.key_expr).split("/alive/", 1)[1]
        if agent == LAUNCHER or agent not in self.agents:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(agent)
                if agent in self.gone:
                    self.gone.remove(agent)
                    self._changes.append((agent, True))
            else:
                self.alive.discard(agent)
                if agent not in self.byes:
                    self.gone.append(agent)
                    self._changes.append((agent, False))
        self.changed.set()

    def note_report(self, agent: str, seq: int = 0) -> None:
        """An agent's clock report arrived (the first one makes it ready). ``seq`` of the
        first one heard: the reports before it were sent before a route to ``up`` existed (an
        agent behind a site router can see ``up``'s token before its reports are routed)."""
        with self.lock:
            if agent in self.reported:
                return
            self.reported.add(agent)
            self.unheard[agent] = seq
        self.changed.set()

    def note_bye(self, message) -> None:
        """An agent's goodbye arrived."""
        with self.lock:
            self.byes[message.src] = message
        self.changed.set()

    def not_ready(self) -> list[str]:
        """Agents without a liveliness token or a first report, sorted."""
        with self.lock:
            return sorted(self.agents - (self.alive & self.reported))

    def alive_now(self) -> set[str]:
        """Agents whose session is up."""
        with self.lock:
            return set(self.alive)

    def session_changes(self) -> list[tuple[str, bool]]:
        """``(agent, back)`` of every session lost without a goodbye (``back`` False) or back
        after such a loss (True) since the last call."""
        with self.lock:
            changes, self._changes = self._changes, []
        return changes

    def without_bye(self) -> set[str]:
        """Agents that have not said goodbye."""
        with self.lock:
            return set(self.agents - set(self.byes))

    def published(self, own: dict[str, int]) -> dict[str, int]:
        """What the agents say they published per key, plus ``own`` (``up``'s messages)."""
        total = dict(own)
        with self.lock:
            for bye in self.byes.values():
                for key, count in bye.published.items():
                    total[key] = total.get(key, 0) + count
        return total

    def wait(self, timeout_s: float) -> None:
        """Wait until something changes (at most ``timeout_s``), then clear the flag."""
        self.changed.wait(timeout_s)
        self.changed.clear()
