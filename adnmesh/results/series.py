"""From recorded messages to named time series and events, by the rules of
:mod:`adnmesh.results.rules`.

``adnmesh replay``, ``adnmesh plot`` and ``adnmesh inspect`` all read a recording through
:func:`read_run` (one streaming pass) or :func:`extract` (a recording read whole), and the
live view of ``adnmesh up --view`` through :class:`LiveCollector`: the same series and events
from the same messages. Every value is placed at the message's send time, on the ``sim_time``
axis in seconds from ``t0``. Here is the machinery (a channel's messages a batch at a time,
as NumPy columns where the rules read known fields); what the messages mean is in the rules.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from adnmesh.recording.foxglove_log import FOXGLOVE_LOG
from adnmesh.recording.reader import ChannelInfo, Recording
from adnmesh.recording.stream import MessageBatch, ScannedRecording, Sink, decode_fields, scan
from adnmesh.results.rules import (AVAILABILITY_KEYS, COLORS, ENVELOPE_FIELDS, EVENTS,
                                   QUIET_KEYS, SERIES, Event, EventRule, Field,
                                   availability_change, available_ders, display_unit, match_key,
                                   message_body)

__all__ = [
    "LiveCollector",
    "RunData",
    "RunFile",
    "Series",
    "extract",
    "feed_recording",
    "grid_of_topic",
    "grids_of",
    "read_grid",
    "read_run",
    "read_runs",
    "recorded_grid_limits",
]

@dataclass
class Series:
    """One named time series.

    Attributes
    ----------
    name : str
        E.g. ``P_IP``, ``SGen1 infeed``.
    entity_path : str
        ``/<key>/<field>``: the Rerun entity path (before escaping).
    role, unit, step, color : str, str, bool, tuple or None
        See :class:`Field`.
    topic : str
        The key the values came from.
    t_ns : numpy.ndarray of int64
        Send times, ns (raw, not shifted by t0).
    log_time_ns : numpy.ndarray of int64
        Delivery times, ns.
    values : numpy.ndarray of float64
        In the SI unit ``unit`` (:meth:`shown` gives them in the unit viewers show).
    der : str or None
        The DER the series is of (its infeed, set-point, availability), else None.
    """

    name: str
    entity_path: str
    role: str
    unit: str
    step: bool
    color: tuple[int, int, int] | None
    topic: str
    t_ns: np.ndarray
    log_time_ns: np.ndarray
    values: np.ndarray
    der: str | None = None

    @property
    def display_unit(self) -> str:
        """The unit viewers show the values in (:func:`~adnmesh.results.rules.display_unit`:
        MW, Mvar, 1/MW, 1/(MW s); others as they are)."""
        return display_unit(self.unit)[0]

    def shown(self) -> np.ndarray:
        """The values in :attr:`display_unit` (the array itself where that is the SI unit)."""
        factor = display_unit(self.unit)[1]
        return self.values if factor == 1.0 else self.values * factor

    @property
    def label(self) -> str:
        """The name with the unit shown, e.g. ``P_IP [MW]``, ``K_I [1/(MW s)]`` (just the name
        for a dimensionless series)."""
        unit = self.display_unit
        return self.name if unit in ("1", "") else f"{self.name} [{unit}]"


@dataclass
class RunData:
    """Everything :func:`extract` takes from a recording.

    Attributes
    ----------
    series : dict of str to Series
        By entity path, in order of first appearance.
    events : list of Event
        In time order.
    der_ids : list of str
        DERs seen (on DER keys or in SI), sorted.
    t0_ns : int
        Origin of the ``sim_time`` axis, ns: the run metadata's ``t0_ns``, else 0 (message times
        count from the run's start in both clock modes).
    """

    series: dict[str, Series]
    events: list[Event]
    der_ids: list[str]
    t0_ns: int

    def by_role(self, role: str) -> list[Series]:
        """Return the series of ``role``, in order of first appearance."""
        return [s for s in self.series.values() if s.role == role]

    def one(self, role: str) -> Series | None:
        """Return the first series of ``role``, or None."""
        found = self.by_role(role)
        return found[0] if found else None

    def end_ns(self) -> int | None:
        """End of the run, ns: the ``end_ns`` of its start message, else the last P_IP
        sample; None without either."""
        start = next((e for e in self.events if e.kind == "run_start"), None)
        if start is not None:
            return int(start.data["end_ns"])
        p_ip = self.one("p_ip")
        return int(p_ip.t_ns.max()) if p_ip is not None and p_ip.t_ns.size else None

    def seconds(self, t_ns: np.ndarray | int) -> np.ndarray | float:
        """Convert send times in ns to seconds on the ``sim_time`` axis."""
        return (np.asarray(t_ns, dtype=np.int64) - self.t0_ns) / 1e9

    def availability_spans(self) -> list[tuple[int, int | None, frozenset[str]]]:
        """Return (start ns, end ns or None, available DER ids) for every availability state."""
        changes = [e for e in self.events if e.kind == "availability"]
        return [(e.t_ns, nxt.t_ns if nxt else None, frozenset(e.data["available"]))
                for e, nxt in zip(changes, changes[1:] + [None])]

    def fault_spans(self) -> list[tuple[int, int | None, str]]:
        """Return (start ns, end ns or None, description) per injected fault (a fault sent
        again to a restarted agent counts once; a kill without restart is an instant)."""
        spans: dict[int, tuple[int, int | None, str]] = {}
        for event in (e for e in self.events if e.kind == "fault"):
            data = event.data
            if data["fault_id"] not in spans:
                end = data.get("end_ns")
                if data.get("kind") == "kill" and end is None:
                    end = data["start_ns"]
                spans[data["fault_id"]] = (data["start_ns"], end, event.text)
        # by start, then end (a fault without one last), then text: ends may be None
        return sorted(spans.values(), key=lambda s: (s[0], s[1] is None, s[1] or 0, s[2]))


def _number(value: object) -> float | None:
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)) and np.isfinite(value):
        return float(value)
    return None


def _t0(recording: Recording) -> int:
    value = recording.run.get("t0_ns", "").strip()
    return int(value) if value.isdigit() else 0


class _Unordered(Exception):
    """A channel's messages are not in send-time order across chunks."""


@dataclass
class _Plan:
    """What :func:`extract` takes from the messages on one key."""

    specs: list[tuple[int, dict, Field]]            # (order, captures, field)
    is_si: bool
    rules: list[tuple[int, EventRule, dict]]        # (order, rule, captures)
    others: bool                                    # keep unmatched numbers too
    ders: set[str]

    @property
    def fields(self) -> tuple[str, ...] | None:
        """The payload fields to decode; None: the whole payload is needed."""
        if self.is_si or self.others or any(r.fields is None for _, r, _ in self.rules):
            return None
        names = [spec.field for _, _, spec in self.specs]
        names += [name for _, r, _ in self.rules for name in r.fields]
        return tuple(dict.fromkeys(names))

    @property
    def empty(self) -> bool:
        return not (self.specs or self.is_si or self.rules or self.others)


def _plan(topic: str, series_rules: Mapping[str, Iterable[Field]],
          event_rules: Mapping[str, EventRule]) -> _Plan:
    specs, ders = [], set()
    for pattern, fields in series_rules.items():
        captures = match_key(pattern, topic)
        if captures is not None:
            specs += [(0, captures, spec) for spec in fields]
            if "der" in captures:
                ders.add(captures["der"])
    specs = [(order, captures, spec) for order, (_, captures, spec) in enumerate(specs)]
    is_si = any(match_key(p, topic) is not None for p in AVAILABILITY_KEYS)
    rules = [(1 + order, rule, captures) for order, (p, rule) in enumerate(event_rules.items())
             if (captures := match_key(p, topic)) is not None]
    quiet = bool(specs or is_si or rules) or any(
        match_key(p, topic) is not None for p in QUIET_KEYS)
    return _Plan(specs, is_si, rules, not quiet, ders)


def _floats(values: list) -> np.ndarray:
    """Numbers as float64 (booleans 0/1), NaN for anything else."""
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        return np.asarray([np.nan if (v := _number(x)) is None else v for x in values],
                          dtype=np.float64)


class _Collector:
    """The series, events and DERs of a recording, channel by channel (see :func:`extract`)."""

    def __init__(self, series_rules, event_rules) -> None:
        self.series_rules, self.event_rules = series_rules, event_rules
        self.columns: dict[str, tuple[Field | None, str, str, _Samples, str | None]] = {}
        self.first: dict[str, tuple] = {}
        self.events: list[tuple[tuple, Event]] = []
        # per grid (a recording of several has several; None: keys outside adn/<grid>/), the
        # DERs its keys and its SI name, and per SI key the set it last said available
        self.ders: dict[str | None, set[str]] = {}
        self.availability: list[tuple[int, int, str, frozenset[str]]] = []
        self.last_available: dict[str, frozenset[str]] = {}

    def sink_for(self, info) -> Sink | None:
        if info.schema_name == FOXGLOVE_LOG:   # the recorder's copy of the events
            return None
        plan = _plan(info.topic, self.series_rules, self.event_rules)
        if plan.empty:
            return None
        if plan.fields is None:
            return _WholeChannel(self, info.topic, plan)
        return _FieldChannel(self, info.topic, plan)

    def add(self, path: str, spec: Field | None, name: str, topic: str, t_ns, log_ns, values,
            first: tuple, der: str | None = None) -> None:
        """Append samples (arrays, in send-time order) to the series at ``path`` (of DER
        ``der``, if it is a DER's)."""
        if len(values) == 0:
            return
        entry = self.columns.get(path)
        if entry is None:
            entry = self.columns[path] = (spec, name, topic, _Samples(), der)
            self.first[path] = first
        entry[3].append(t_ns, log_ns, values)

    def event(self, key: tuple, t_ns: int, kind: str, found, topic: str) -> None:
        level, text, data = found
        self.events.append((key, Event(t_ns, kind, level, text, topic, data)))

    def si(self, t_ns: int, log_ns: int, order: int, topic: str, body: dict) -> None:
        """One SI message: the count of available DERs and, on a change, an event."""
        available, known = available_ders(body)
        self.ders.setdefault(grid_of_topic(topic), set()).update(known)
        self.availability.append((t_ns, log_ns, topic, frozenset(available)))
        self.add(f"/{topic}/available_count", _COUNT, _COUNT.name, topic, [t_ns], [log_ns],
                 [float(len(available))], (0, t_ns, order, 10_000))
        found = availability_change(available, self.last_available.get(topic))
        self.last_available[topic] = frozenset(available)
        if found is not None:
            self.event((t_ns, order, 0), t_ns, "availability", found, topic)

    def result(self, t0_ns: int) -> RunData:
        # one 0/1 step series per DER from SI, now that every DER id is known
        for number, (t_ns, log_ns, topic, available) in enumerate(self.availability):
            for der in sorted(self.ders[grid_of_topic(topic)]):
                self.add(f"/{topic}/available/{der}",
                         Field("available", f"{der} available", "availability", unit="1",
                               step=True),
                         f"{der} available", topic, [t_ns], [log_ns], [float(der in available)],
                         (1, number), der=der)
        series, times = {}, {}
        for path in sorted(self.columns, key=self.first.__getitem__):
            spec, name, topic, pieces, der = self.columns.pop(path)   # one series' copy at a time
            spec = spec or Field(path.rsplit("/", 1)[-1], name, "other", unit="")
            t_ns, log_ns, values = pieces.arrays()
            shared = times.get(topic)          # series of one key mostly share their times
            if shared is not None and np.array_equal(shared[0], t_ns) and \
                    np.array_equal(shared[1], log_ns):
                t_ns, log_ns = shared
            else:
                times[topic] = (t_ns, log_ns)
            series[path] = Series(name=name, entity_path=path, role=spec.role, unit=spec.unit,
                                  step=spec.step, color=spec.color, topic=topic, t_ns=t_ns,
                                  log_time_ns=log_ns, values=values, der=der)
        self.events.sort(key=lambda item: item[0])
        return RunData(series=series, events=[e for _, e in self.events],
                       der_ids=sorted(set().union(*self.ders.values())), t0_ns=t0_ns)


class _Samples:
    """The samples of one series as they come, in few large blocks (small pieces are merged
    once there are enough of them, so that their memory is reused, not left fragmented)."""

    _MERGE = 1 << 16

    def __init__(self) -> None:
        self.blocks: list[tuple[np.ndarray, ...]] = []
        self.pieces: list[tuple[np.ndarray, ...]] = []
        self.size = 0

    def append(self, t_ns, log_ns, values) -> None:
        self.pieces.append((np.asarray(t_ns, dtype=np.int64), np.asarray(log_ns, dtype=np.int64),
                            np.asarray(values, dtype=np.float64)))
        self.size += self.pieces[-1][0].size
        if self.size >= self._MERGE:
            self.blocks.append(self._merge(self.pieces))
            self.pieces, self.size = [], 0

    @staticmethod
    def _merge(parts) -> tuple[np.ndarray, ...]:
        return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """Send times, delivery times (ns) and values, all of them; the blocks are let go."""
        parts, self.blocks, self.pieces = self.blocks + self.pieces, [], []
        return self._merge(parts)


class _Channel:
    """The messages on one key, a batch at a time, in send-time order."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        self.collector, self.topic, self.plan = collector, topic, plan
        self.last_t_ns: int | None = None
        self.seen = False

    def __call__(self, batch: MessageBatch) -> None:
        order = np.argsort(batch.publish_time_ns, kind="stable")
        if np.any(order[1:] < order[:-1]):
            batch = batch.select(order)
        t_ns = batch.publish_time_ns
        if self.last_t_ns is not None and t_ns.size and t_ns[0] < self.last_t_ns:
            raise _Unordered(self.topic)
        if t_ns.size:
            self.last_t_ns = int(t_ns[-1])
            self.take(batch)

    def found_bodies(self) -> None:
        if not self.seen:
            self.seen = True
            self.collector.ders.setdefault(grid_of_topic(self.topic), set()).update(
                self.plan.ders)


class _FieldChannel(_Channel):
    """A key whose rules read known fields: columns decoded by msgspec, rules asked only where
    a watched field changes."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        super().__init__(collector, topic, plan)
        self.names = self.fields = plan.fields
        self.previous: dict | None = None

    def take(self, batch: MessageBatch) -> None:
        t_ns, log_ns, ordinal = batch.publish_time_ns, batch.log_time_ns, batch.ordinal
        decoded = batch.columns or decode_fields(batch, self.names)
        columns, valid = decoded.columns, decoded.valid
        if not valid.all():
            keep = np.flatnonzero(valid)
            t_ns, log_ns, ordinal = t_ns[keep], log_ns[keep], ordinal[keep]
            columns = {k: [v[i] for i in keep.tolist()] for k, v in columns.items()}
        if not t_ns.size:
            return
        self.found_bodies()
        for order, captures, spec in self.plan.specs:
            values = _floats(columns[spec.field])
            ok = np.isfinite(values)
            if ok.any():
                first = int(np.argmax(ok))
                self.collector.add(f"/{self.topic}/{spec.field}", spec,
                                   spec.name.format(**captures), self.topic, t_ns[ok],
                                   log_ns[ok], values[ok],
                                   (0, int(t_ns[first]), int(ordinal[first]), order),
                                   der=captures.get("der"))
        for order, rule, captures in self.plan.rules:
            self.apply(rule, order, captures, columns, t_ns, ordinal)
        self.previous = self.body(columns, t_ns.size - 1)

    def body(self, columns: dict[str, list], i: int) -> dict:
        return {k: v[i] for k, v in columns.items() if v[i] is not msgspec.UNSET}

    def apply(self, rule: EventRule, order: int, captures: dict, columns, t_ns, ordinal) -> None:
        """Ask ``rule`` about the messages of this batch where it may find an event."""
        n = t_ns.size
        if rule.watch or rule.present:
            asked = np.zeros(n, dtype=bool)
            asked[0] = True
            for name in rule.watch:
                values = np.fromiter(columns[name], dtype=object, count=n)
                asked[1:] |= (values[1:] != values[:-1]).astype(bool)
            for name in rule.present:
                asked |= np.fromiter((v is not msgspec.UNSET and v is not None
                                      for v in columns[name]), dtype=bool, count=n)
            rows = np.flatnonzero(asked).tolist()
        else:
            rows = range(n)
        for i in rows:
            previous = self.previous if i == 0 else self.body(columns, i - 1)
            found = rule.rule(self.body(columns, i), previous, captures)
            if found is not None:
                self.collector.event((int(t_ns[i]), int(ordinal[i]), order), int(t_ns[i]),
                                     rule.kind, found, self.topic)


class _WholeChannel(_Channel):
    """A key whose messages are needed whole (SI, faults, agents' events, unmatched keys):
    message by message, as decoded JSON."""

    def __init__(self, collector: _Collector, topic: str, plan: _Plan) -> None:
        super().__init__(collector, topic, plan)
        self.previous: dict | None = None

    def take(self, batch: MessageBatch) -> None:
        series: dict[str, tuple[Field | None, str, list, tuple]] = {}
        for t, log, number, payload in zip(batch.publish_time_ns.tolist(),
                                           batch.log_time_ns.tolist(), batch.ordinal.tolist(),
                                           batch.payloads):
            body = message_body(_json(payload))
            if body:
                self.found_bodies()
                self.message(t, log, number, body, series)
        der = next(iter(self.plan.ders)) if len(self.plan.ders) == 1 else None
        for path, (spec, name, samples, first) in series.items():
            t, log, values = zip(*samples)
            self.collector.add(path, spec, name, self.topic, t, log, values, first, der=der)

    def message(self, t: int, log: int, number: int, body: dict, series: dict) -> None:
        def add(path, spec, name, value, order):
            entry = series.setdefault(path, (spec, name, [], (0, t, number, order)))
            entry[2].append((t, log, value))

        for order, captures, spec in self.plan.specs:
            value = _number(body.get(spec.field))
            if value is not None:
                add(f"/{self.topic}/{spec.field}", spec, spec.name.format(**captures), value,
                    order)
        if self.plan.is_si:
            self.collector.si(t, log, number, self.topic, body)
        for order, rule, captures in self.plan.rules:
            found = rule.rule(body, self.previous, captures)
            if found is not None:
                self.collector.event((t, number, order), t, rule.kind, found, self.topic)
        if self.plan.rules:
            self.previous = body
        if self.plan.others:
            for k, (name, raw) in enumerate(body.items()):
                value = None if name in ENVELOPE_FIELDS or isinstance(raw, bool) else \
                    _number(raw)
                if value is not None:
                    add(f"/{self.topic}/{name}", None, f"{self.topic}/{name}", value,
                        20_000 + k)


def _json(payload: bytes) -> object:
    try:
        return msgspec.json.decode(payload)
    except msgspec.DecodeError:
        pass
    try:
        return json.loads(payload)
    except ValueError:
        return None


def extract(recording: Recording, *, series_rules: Mapping[str, Iterable[Field]] = SERIES,
            event_rules: Mapping[str, EventRule] = EVENTS) -> RunData:
    """Turn a recording's messages into named series and events, using the tables above.

    Messages whose payload is not a JSON object are skipped. :func:`read_run` gives the same
    result for a file, reading it in one streaming pass.
    """
    collector = _Collector(series_rules, event_rules)
    feed_recording(recording, collector.sink_for)
    return collector.result(_t0(recording))


def feed_recording(recording: Recording, sink_for: Callable[[ChannelInfo], Sink | None]) -> None:
    """Give the messages of ``recording`` (read whole) to sinks, as :func:`scan` gives a file's:
    one batch per channel, in send-time order."""
    by_topic: dict[str, list[int]] = {}
    for number, m in enumerate(recording.messages):
        by_topic.setdefault(m.topic, []).append(number)
    for topic, info in recording.channels.items():
        sink = sink_for(info)
        numbers = by_topic.get(topic, [])
        if sink is None or not numbers:
            continue
        messages = [recording.messages[i] for i in numbers]
        sink(MessageBatch(np.asarray([m.publish_time_ns for m in messages], dtype=np.int64),
                          np.asarray([m.log_time_ns for m in messages], dtype=np.int64),
                          np.asarray(numbers, dtype=np.int64), [m.data for m in messages]))


@dataclass(frozen=True)
class RunFile:
    """A recording read by :func:`read_run`: the file's description and its series."""

    recording: ScannedRecording
    run: RunData


def grid_of_topic(topic: str) -> str | None:
    """The grid of an adnmesh topic (``adn/<grid>/...``), None for another topic."""
    parts = topic.split("/", 2)
    return parts[1] if len(parts) == 3 and parts[0] == "adn" else None


def grids_of(topics: Iterable[str]) -> list[str]:
    """The grids of ``topics`` (:func:`grid_of_topic`), in order of first appearance."""
    return list(dict.fromkeys(g for g in map(grid_of_topic, topics) if g is not None))


def read_run(path: str | Path, *, also: Callable[[], object] | None = None,
             series_rules: Mapping[str, Iterable[Field]] = SERIES,
             event_rules: Mapping[str, EventRule] = EVENTS,
             grid: str | None = None) -> tuple[RunFile, object]:
    """Read the recording ``path`` in one streaming pass: its series and events, as
    :func:`extract` finds them, without holding its messages.

    Parameters
    ----------
    path : str or Path
        An MCAP file, complete or truncated.
    also : callable, optional
        Makes another consumer of the same pass: an object with a ``sink_for(info)`` method
        (see :func:`~adnmesh.recording.stream.scan`); it is returned beside the result.
    grid : str, optional
        Only the messages of this grid (topics ``adn/<grid>/...``; a recording of several,
        such as a hierarchy's).

    Returns
    -------
    (RunFile, object)
        The file and its run data, and the object ``also`` made (None without it).

    Raises
    ------
    RecordingError
        As :func:`~adnmesh.recording.stream.scan`.
    """
    only = (lambda topic: grid_of_topic(topic) == grid) if grid is not None else None
    scanned, parts = _read(path, also, series_rules, event_rules,
                           lambda topic: None if only is None or only(topic) else False)
    run, other = parts.get(None, (None, None))
    if run is None:                                # nothing of the grid: empty series
        run = _Collector(series_rules, event_rules).result(_t0(scanned))
        other = also() if also is not None else None
    return RunFile(scanned, run), other


def read_runs(path: str | Path, *, also: Callable[[], object] | None = None
              ) -> tuple[ScannedRecording, dict[str | None, tuple[RunData, object]]]:
    """Read a recording of several grids (a hierarchy's) in one streaming pass, each grid's
    series and events apart (:func:`read_run` of each grid, at the cost of one).

    Returns
    -------
    (ScannedRecording, dict)
        The file, and grid -> (its run data, the object ``also`` made for it), in order of the
        grids' first channels; the topics of no grid (not ``adn/<grid>/...``) under None.
    """
    return _read(path, also, SERIES, EVENTS, grid_of_topic)


def read_grid(path: str | Path, grid: str | None = None, *,
              also: Callable[[], object] | None = None
              ) -> tuple[RunFile, object, list[str], str | None]:
    """Read one grid of a recording in one pass: ``grid``'s, else, in a recording of several
    (a hierarchy's), its own (its run metadata's ``grid``: the upper level's) or the first.

    Returns
    -------
    (RunFile, object, list, str or None)
        The file with that grid's run data, the object ``also`` made for it, every grid of
        the recording (:func:`grids_of`), and the grid read (None: a recording of no grid).

    Raises
    ------
    UsageError
        ``grid`` is not a grid of the recording (one line).
    RecordingError
        As :func:`~adnmesh.recording.stream.scan`.
    """
    from adnmesh.errors import UsageError

    if grid is not None:
        found, other = read_run(path, also=also, grid=grid)
        grids = grids_of(found.recording.channels)
        if grid not in grids:
            raise UsageError(f"--grid {grid}: not a grid of {path} (it has: "
                             f"{', '.join(grids) or 'none'})")
        return found, other, grids, grid
    scanned, parts = read_runs(path, also=also)
    grids = grids_of(scanned.channels)
    own = scanned.run.get("grid")
    chosen = own if own in grids else next(iter(grids), None)
    if chosen not in parts:          # no channel at all: empty series
        found, other = read_run(path, also=also)
        return found, other, grids, chosen
    run, other = parts[chosen]
    return RunFile(scanned, run), other, grids, chosen


def _read(path, also, series_rules, event_rules, part_of):
    """One pass over ``path``: ``(scanned, {part: (run data, also's object)})``, each channel
    to the collector of ``part_of(topic)`` (False: to none)."""
    parts: dict = {}

    def sink_for(info: ChannelInfo) -> Sink | None:
        part = part_of(info.topic)
        if part is False:
            return None
        if part not in parts:
            parts[part] = (_Collector(series_rules, event_rules),
                           also() if also is not None else None)
        collector, other = parts[part]
        sinks = [s for s in (collector.sink_for(info),
                             other.sink_for(info) if other is not None else None) if s]
        if len(sinks) < 2:
            return sinks[0] if sinks else None
        return lambda batch: [sink(batch) for sink in sinks]

    try:
        scanned = scan(path, sink_for)
    except _Unordered:   # messages of a key out of send-time order: read it whole
        from adnmesh.recording.reader import read_recording

        recording = read_recording(path)
        parts.clear()
        feed_recording(recording, sink_for)
        scanned = scan(path, lambda info: None)
    t0 = _t0(scanned)
    return scanned, {part: (collector.result(t0), other)
                     for part, (collector, other) in parts.items()}


def recorded_grid_limits(metadata: Mapping[str, str]):
    """The band of the recorded run's grid model (its config's ``grid_model.limits``, the
    defaults where it gives none: :class:`adnmesh.config.GridLimits`), as ``up`` checked every
    grid sample against; None if the config has no grid model or cannot be read.

    ``metadata`` is the recording's run metadata (``Recording.run``: the config's text in
    ``config``)."""
    import yaml
    from pydantic import ValidationError

    from adnmesh.config import GridLimits

    try:
        document = yaml.safe_load(metadata.get("config", "")) or {}
        grid_model = document.get("grid_model")
        if not isinstance(grid_model, Mapping):
            return None
        return GridLimits(**(grid_model.get("limits") or {}))
    except (yaml.YAMLError, AttributeError, TypeError, ValidationError):
        return None


class LiveCollector(_Collector):
    """The series and events of messages as they come (``adnmesh up --view``), by the rules of
    :func:`extract`, handed out in pieces: :meth:`drain` returns what came since the last call.

    Not thread-safe: one thread feeds and drains.
    """

    def __init__(self, series_rules: Mapping[str, Iterable[Field]] = SERIES,
                 event_rules: Mapping[str, EventRule] = EVENTS) -> None:
        super().__init__(series_rules, event_rules)
        self._sinks: dict[str, Sink | None] = {}
        self._ordinal = 0

    def feed(self, topic: str, schema_name: str, records: list[tuple[bytes, int, int]]) -> None:
        """Take messages of one topic: ``(payload, log_time_ns, publish_time_ns)`` each, as
        the recorder writes them. Messages older than the topic's last are dropped."""
        if topic not in self._sinks:
            self._sinks[topic] = self.sink_for(ChannelInfo(topic, "json", schema_name))
        sink = self._sinks[topic]
        if sink is None or not records:
            return
        payloads, log_ns, publish_ns = zip(*records)
        publish = np.asarray(publish_ns, dtype=np.int64)
        ordinal = np.arange(self._ordinal, self._ordinal + publish.size, dtype=np.int64)
        self._ordinal += publish.size
        batch = MessageBatch(publish, np.asarray(log_ns, dtype=np.int64), ordinal, payloads)
        if sink.last_t_ns is not None:
            keep = np.flatnonzero(publish >= sink.last_t_ns)
            if keep.size < publish.size:
                batch = batch.select(keep)
        if len(batch):
            sink(batch)

    def drain(self, t0_ns: int = 0) -> RunData:
        """The series samples and events found since the last call (series: only those with
        new samples; events: in time order)."""
        run = self.result(t0_ns)
        self.events, self.availability, self.first = [], [], {}
        return run


_COUNT = Field("available_count", "DERs available", "available_count", unit="1", step=True,
               color=COLORS["available_count"])
