"""A site's own recording: what the agents behind a site router publish, recorded at the site
(``adnmesh router --record FILE``, started so by ``adnmesh up`` of a hierarchy;
docs/hierarchy.md#adnmesh-up-sites-on-the-bus).

``up`` records every level of a run at the top. A site router with ``--record`` also records
what its own clients publish -- its ADN's agents and the upper level's site agent of it --
checked and written by a :class:`~adnmesh.runtime.tap.RecorderTap` per level (on that level's
topology; a witness: it does not weigh clock reports, and knows nothing of the clock's grants
or of quarantines, which ``up``'s taps do), into a recording of the same run (its ``run_id``):
every message is recorded at its site too, and ``adnmesh merge`` takes each message once.
``up``'s own messages (grants, the start) are ``up``'s to record. A router killed (a planned
restart) leaves its file unfinished, which :func:`~adnmesh.recording.read_recording` recovers;
the router started again records to a file of its own.

The router's forwarding never waits for the recording: a sample the recording thread has no
room for (:data:`_QUEUE` behind) is dropped from the site's file and counted, as is one it
fails on; :meth:`SiteRecorder.close` says how many.
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path

import zenoh

from adnmesh import __version__
from adnmesh.names import der_agent_id
from adnmesh.recording import Recorder
from adnmesh.sim.hierarchy_topology import HIERARCHY
from adnmesh.sim.topology import Topology

__all__ = ["SiteRecorder"]


class _NoSeries:
    """The site keeps no summary series (``up``'s taps feed the summary)."""

    def take(self, message) -> None:
        """Nothing."""


_QUEUE = 65536      # samples queued for the recording thread (beyond: dropped, counted)
_JOIN_S = 4.0       # longest wait for the recording thread at the close (up stops in 5 s)
FLUSH_S = 0.25
"""How often the site's recording is put on disk, wall s: what a site router killed loses."""


class SiteRecorder:
    """The recording of site ``adn`` of a hierarchy's run (see the module docstring).

    Parameters
    ----------
    path : Path
        The MCAP file to write.
    levels : adnmesh.sim.hierarchy_levels.Levels
        The hierarchy.
    adn : str
        The site's ADN id.
    run_id : str
        The run's id (``adnmesh merge`` joins only one run's recordings).
    """

    def __init__(self, path: Path, levels, adn: str, run_id: str) -> None:
        from adnmesh.runtime.tap import RecorderTap, recording_schemas

        upper = levels.upper.grid
        run = {"run_id": run_id, "grid": adn, "site": f"router/{adn}", "clock": "sim",
               "adnmesh_version": __version__}
        self.recorder = Recorder(path, schemas=recording_schemas(), metadata=run,
                                 flush_interval_s=FLUSH_S)
        own = {adn: Topology.from_config(levels.adns[adn], HIERARCHY),
               upper: Topology.from_config(levels.upper, HIERARCHY)}
        members = {adn: own[adn].agents, upper: (der_agent_id(adn),)}
        self.keys = frozenset(k for grid, agents in members.items() for a in agents
                              for k in own[grid].sends(a))
        # one subscriber per level, not one per key: each has a Zenoh delivery thread of its
        # own, and an agent's clock report rides the last sample of its window on any of its
        # keys, so per-key subscribers let a later report overtake an earlier one (which the
        # witness then rejected as replayed)
        self.patterns = (f"{own[adn].keys.root}/**",
                         f"{own[upper].keys.root}/**/{der_agent_id(adn)}/**")
        self.taps = {grid: RecorderTap(self.recorder, t, _NoSeries(), lambda: 0,
                                       weigh_reports=False)   # a witness, not the clock's
                     for grid, t in own.items()}
        self.dropped = 0                 # samples not recorded: no room, or failed on
        self._handles: list = []
        self._queue: queue.Queue = queue.Queue(_QUEUE)
        self._thread: threading.Thread | None = None

    def declare(self, session: zenoh.Session) -> None:
        """Subscribe to the keys the site's agents publish, one subscriber per level
        (:attr:`patterns`, of which only those keys are taken); record on a thread of its own,
        in the order the samples came (one queue for both)."""
        keys = self.keys

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if key not in keys:          # up's grants to the site's agents, say
                return
            attachment = sample.attachment
            try:
                self._queue.put_nowait((key, sample.payload.to_bytes(),
                                        None if attachment is None else attachment.to_bytes()))
            except queue.Full:
                self.dropped += 1

        for pattern in self.patterns:
            self._handles.append(session.declare_subscriber(pattern, on_sample))
        self._thread = threading.Thread(target=self._record, daemon=True,
                                        name="adnmesh-site-recorder")
        self._thread.start()

    def _record(self) -> None:
        while (item := self._queue.get()) is not None:
            key, payload, attachment = item
            try:
                tap = self.taps[key.split("/")[1]]
                tap.take(key, payload)
                if attachment is not None:
                    tap.take_attached(key, attachment)
            except Exception:            # a failed write (a full disk): the file keeps the rest
                self.dropped += 1

    def close(self) -> str | None:
        """Stop recording and finish the file; return what went wrong, in one line, or
        None."""
        for handle in self._handles:
            handle.undeclare()
        self._handles = []
        if self._thread is not None:
            self._queue.put(None)            # after the undeclares: nothing else comes
            self._thread.join(_JOIN_S)
        problems = [p for tap in self.taps.values() for p in tap.problems]
        try:
            self.recorder.close()
        except RuntimeError as exc:
            problems.append(f"recording failed while finishing the file: {exc}")
        if self.dropped:
            problems.append(f"{self.dropped} sample(s) not recorded at the site")
        return "; ".join(problems) or None
