"""A run's series and events to Rerun while it goes (``adnmesh up --view``).

:class:`LiveView` takes the messages the recorder writes (:meth:`LiveView.take`, cheap: it
only queues them) and, on a background thread every ``period_s`` wall seconds, turns them into
series and events by the rules ``replay`` uses (:class:`~adnmesh.results.series.LiveCollector`)
and sends them to a Rerun recording stream in columns, with the styles and the blueprint of
:mod:`~adnmesh.results.rerun_export`. Step series (P_ref, availability, the gains) are held
up to :data:`HOLD_BEHIND_NS` before the newest sim time seen (to it when the view closes), as
``replay`` holds them to the run's end: the agents of one clock window send in any order, so a sample of a step series can
come after another agent's later one, and a held value at its time would show the old value
there. The recorder's thread is never blocked by Rerun: a slow viewer only delays the view.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable

import numpy as np

from adnmesh.results.rerun_export import (HOLD_PERIOD_NS, blueprint, held, limit_series,
                                          log_style, send_events, send_series)
from adnmesh.results.rules import Event
from adnmesh.results.series import LiveCollector, RunData, Series

__all__ = ["LiveView", "RecordQueue", "VIEW_PERIOD_S"]

VIEW_PERIOD_S = 0.5
"""How often the view is sent what came, wall s."""


class RecordQueue:
    """Recorded messages queued for another thread: what a view is given by the recorder tap
    (:meth:`take`, cheap and thread-safe, so that the recorder is never held up) and hands on
    from another thread (:meth:`taken`)."""

    def __init__(self) -> None:
        self._pending: list[tuple[str, str, list]] = []
        self._lock = threading.Lock()

    def take(self, topic: str, schema_name: str, records: list[tuple[bytes, int, int]]) -> None:
        """Queue recorded messages: ``(payload, log_time_ns, publish_time_ns)`` each."""
        with self._lock:
            self._pending.append((topic, schema_name, records))

    def taken(self) -> list[tuple[str, str, list]]:
        """What was queued since the last call, ``(topic, schema_name, records)`` in order."""
        with self._lock:
            pending, self._pending = self._pending, []
        return pending


@dataclasses.dataclass(frozen=True)
class _Last:
    """The last real sample of a step series and how far it was sent (held), ns."""

    t_ns: int
    log_time_ns: int
    value: float
    sent_ns: int


class LiveView(RecordQueue):
    """Streams the series and events of a running run to the Rerun stream ``rec``.

    Parameters
    ----------
    rec : rerun.RecordingStream or None
        Where to send (saved to a file or connected to a viewer); None: events only (for
        ``on_events``).
    t0_ns : int
        Origin of the timelines, ns (the run's ``t0_ns``).
    period_s : float
        How often what came is sent, wall s.
    on_events : callable, optional
        Gets the list of new :class:`~adnmesh.results.rules.Event` (in time order) at each
        send, on the view's thread.
    viewer_pid : int, optional
        The viewer process the stream is connected to (it outlives the run).
    limits : adnmesh.config.GridLimits, optional
        The run's grid band, drawn beside the grid's extremes once they come
        (:func:`~adnmesh.results.rerun_export.limit_series`, as ``replay`` draws it).
    """

    def __init__(self, rec, *, t0_ns: int = 0, period_s: float = VIEW_PERIOD_S,
                 on_events: Callable[[list[Event]], None] | None = None,
                 viewer_pid: int | None = None, limits=None) -> None:
        super().__init__()
        self.rec, self.t0_ns, self.period_s, self.on_events = rec, t0_ns, period_s, on_events
        self.viewer_pid, self.limits = viewer_pid, limits
        self._der_ids: list[str] = []            # the DERs seen: their colours
        self.collector = LiveCollector()
        self.now_ns = 0                          # newest send time seen, ns
        self._behind_ns = HOLD_BEHIND_NS         # step series held up to now_ns - this
        self.sends = 0                           # how many times something was sent
        self.error: str | None = None            # why the view stopped, if it failed
        self._stop = threading.Event()
        self._known: dict[str, Series] = {}      # every series seen (samples not kept)
        self._last: dict[str, _Last] = {}        # step series: last sample, sent up to
        self._event_topics: dict[str, Event] = {}
        self._thread = threading.Thread(target=self._loop, name="adnmesh-live-view",
                                        daemon=True)

    def start(self) -> LiveView:
        """Start the background thread; return self."""
        self._thread.start()
        return self

    def close(self) -> None:
        """Send what is left, flush and disconnect the stream."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._behind_ns = 0                      # everything has come: held to the newest
        self.send_pending()
        if self.rec is not None:
            self.rec.flush()
            self.rec.disconnect()

    # -- the view's thread --------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self.send_pending()

    def send_pending(self) -> None:
        """Turn what was queued into series and events and send them (the view's thread does
        this every ``period_s``; callable directly when it is not started)."""
        pending = self.taken()
        if self.error is not None:
            return
        try:
            by_topic: dict[str, tuple[str, list]] = {}
            for topic, schema_name, records in pending:     # one batch per topic
                by_topic.setdefault(topic, (schema_name, []))[1].extend(records)
            for topic, (schema_name, records) in by_topic.items():
                self.now_ns = max(self.now_ns, max(r[2] for r in records))
                self.collector.feed(topic, schema_name, records)
            run = self.collector.drain(self.t0_ns)
            if self.rec is not None:
                self._send(run)
            if run.events and self.on_events is not None:
                self.on_events(run.events)
        except Exception as exc:      # noqa: BLE001 - the run goes on without its view
            self.error = f"live view stopped: {type(exc).__name__}: {exc}"

    def _send(self, run: RunData) -> None:
        if self.limits is not None and not any(s.role == "grid_limit"
                                               for s in self._known.values()):
            for series in limit_series(run, self.limits):   # once the grid reports
                run.series[series.entity_path] = series
        new_paths = [p for p in run.series if p not in self._known]
        new_topics = [e for e in run.events if e.topic not in self._event_topics]
        restyle = run.der_ids != self._der_ids     # a new DER: the DERs' colours move
        self._der_ids = list(run.der_ids)
        for path in new_paths:
            self._known[path] = dataclasses.replace(run.series[path], t_ns=_EMPTY_I,
                                                    log_time_ns=_EMPTY_I, values=_EMPTY_F)
            log_style(self.rec, run.series[path], self._der_ids)
        if restyle:
            for path, known in self._known.items():
                if known.der is not None and path not in new_paths:
                    log_style(self.rec, known, self._der_ids)
        for event in new_topics:
            self._event_topics.setdefault(event.topic, event)
        if new_paths or new_topics:
            layout = RunData(dict(self._known), list(self._event_topics.values()),
                             run.der_ids, self.t0_ns)
            self.rec.send_blueprint(blueprint(layout))
        for path, known in self._known.items():
            series = run.series.get(path)
            if known.step:
                series = self._held(path, series if series is not None else known)
            if series is not None and series.t_ns.size:
                send_series(self.rec, series, self.t0_ns)
        send_events(self.rec, run.events, self.t0_ns)
        self.rec.flush()
        self.sends += 1

    def _held(self, path: str, series: Series) -> Series:
        """The new samples of a step series with its value held up to :data:`HOLD_BEHIND_NS`
        before :attr:`now_ns` (up to it once the view closes)."""
        last = self._last.get(path)
        if last is not None:
            series = dataclasses.replace(
                series, t_ns=np.insert(series.t_ns, 0, last.t_ns),
                log_time_ns=np.insert(series.log_time_ns, 0, last.log_time_ns),
                values=np.insert(series.values, 0, last.value))
        if not series.t_ns.size:
            return series
        end = series.t_ns[-1], series.log_time_ns[-1], series.values[-1]
        out = held(series, self.now_ns - self._behind_ns)
        keep = out.t_ns > (last.sent_ns if last is not None else -1)
        self._last[path] = _Last(int(end[0]), int(end[1]), float(end[2]),
                                 int(out.t_ns[-1]))
        return dataclasses.replace(out, t_ns=out.t_ns[keep], log_time_ns=out.log_time_ns[keep],
                                   values=out.values[keep])


HOLD_BEHIND_NS = HOLD_PERIOD_NS
"""How far behind the newest sim time seen a step series is held, ns: longer than the clock
windows of the shipped configs (300 ms for the reference case), so every real sample before it
has come. A run whose windows are longer than this could still show a held value early."""

_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)
