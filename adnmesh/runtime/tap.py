"""The recorder tap of ``adnmesh up``: every envelope on the bus into the MCAP recording.

The tap takes every sample the agents publish (one subscriber on ``adn/<grid>/**``) and every
message ``up`` sends itself, and writes one MCAP message per envelope. It decodes and validates
each envelope first, through the same gate every agent uses (:mod:`adnmesh.wire.gate`: a key
some party of the run sends, every field in range, the key's own sender, no unknown DER, no
(send time, seq) repeated on a key), so that only genuine
messages reach their channel, the summary's series and the caller (clock reports and goodbyes
go on to the clock and the shutdown). Anything else is **rejected**: counted per key and reason
and recorded apart on the channel ``adn/<grid>/rejected`` (type ``rejected``: the key, the
reason, what was wrong, the payload's size and sha256 and its first
:data:`REJECTED_PREFIX_BYTES` bytes in base64), so that nothing received is lost and nothing
invalid is taken for a message.

**Recording after the grants.** ``up``'s bus thread takes a batch of samples inside
:meth:`RecorderTap.writes_after`: each sample is checked and counted at once (the clock's
reports must be), but what it holds is written (and fed to the summary's series and the live
view) when the batch is done -- after its reports went to the sim clock and the grants that
follow were put on the bus. The agents then run their next window while ``up`` records: the
recording is off the clock's critical path. Grants ``up`` sends in the batch are recorded then
too. The recording is the same, message for message.
"""

from __future__ import annotations

import base64
import hashlib
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Annotated

import msgspec
from msgspec import Meta, Struct

from adnmesh.results.summary import RunSeries
from adnmesh.names import LAUNCHER, der_id_of
from adnmesh.sim.topology import Topology
from adnmesh.wire.envelope import encode, envelope_times
from adnmesh.wire.gate import SUSPICIOUS, Gate, SampleReject, count_reject
from adnmesh.wire.keys import route
from adnmesh.wire.messages import Envelope
from adnmesh.wire.schemas import SCHEMA_DIALECT, message_schemas

__all__ = ["REJECTED_PREFIX_BYTES", "REJECTED_RECORDS_KEPT", "REJECTED_TYPE", "RecorderTap",
           "Rejected", "recording_schemas"]

REJECTED_TYPE = "rejected"
"""Message type (schema name) of the rejected-payload records."""

REJECTED_PREFIX_BYTES = 4096
"""How much of a rejected payload is kept in its record."""

REJECTED_RECORDS_KEPT = 1000
"""Most rejected-payload records a run keeps (one per sample and reason; ~4 MiB at most); the
rest are counted only (:attr:`RecorderTap.rejected_unrecorded`), so no sender can grow the
recording without bound."""



class Rejected(Struct, forbid_unknown_fields=True):
    """A payload the recorder rejected: on which key, why, and what it held."""

    key: Annotated[str, Meta(max_length=512)]
    reason: str
    detail: Annotated[str, Meta(max_length=1000)]
    size_bytes: int
    sha256: str
    payload_prefix_b64: str


def recording_schemas() -> dict[str, dict]:
    """The JSON Schemas of a recording: every message type and the rejected records."""
    generated = msgspec.json.schema(Rejected)
    schema = generated["$defs"]["Rejected"]
    return {**message_schemas(),
            REJECTED_TYPE: {"$schema": SCHEMA_DIALECT, **schema, "title": REJECTED_TYPE}}


class RecorderTap:
    """Validates and records envelopes (thread-safe; see the module docstring).

    Parameters
    ----------
    recorder : adnmesh.recording.Recorder
        Where the messages go.
    topology : Topology
        The run's keys and who sends them.
    series : RunSeries
        Fed with what the summary needs.
    now_ns : callable
        The run's current time, ns, for rejected payloads that carry no usable times.
    view : adnmesh.results.live.LiveView, optional
        Also gets every message recorded (``up --view``: queued, sent to Rerun elsewhere).
    weigh_reports : bool
        Reject a clock report that claims messages this tap never saw (``implausible``: the
        clock's protection, default). A site's recorder (:mod:`adnmesh.runtime.site_recorder`)
        only witnesses, and may have missed a first message of a session the clock's tap saw.
    """

    def __init__(self, recorder, topology: Topology, series: RunSeries,
                 now_ns: Callable[[], int], view=None,
                 clock_reach_ns: Callable[[str], int | None] | None = None,
                 on_suspect: Callable[[str, str, str], None] | None = None,
                 weigh_reports: bool = True) -> None:
        self.recorder = recorder
        self.view = view
        self.series = series
        self._now_ns = now_ns
        self._on_suspect = on_suspect
        self._weigh_reports = weigh_reports
        self.rejected_key = f"{topology.keys.root}/rejected"
        self._agents = frozenset(topology.agents)
        self._report_keys = {a: topology.keys.of("clock_report", a) for a in topology.agents}
        # every key a party of the run sends, but up's own (recorded as it sends them)
        self._gate = Gate({r.key for r in topology.routes if r.sender != LAUNCHER},
                          topology.der_ids, outside_reason="unknown_key",
                          outside_detail="not a key of this run's agents",
                          capacity_w=topology.capacity_w, clock_reach_ns=clock_reach_ns)
        self.rejected = self._gate.rejected
        self.suspects: dict[str, str] = {}      # DER agent -> why it is suspected
        self._unreported: dict[str, dict[str, int]] = {}   # agent -> key -> since its report
        self.rejected_unrecorded = 0            # beyond REJECTED_RECORDS_KEPT
        self._records_kept = 0
        self._lock = threading.Lock()
        self._after: list | None = None   # within writes_after: (key, type, records, messages)
        self._writing = threading.Lock()  # held while records are written (after the tap's)
        self.record_errors = 0
        self.problems: list[str] = []

    def take(self, key: str, sample: bytes) -> list[Envelope]:
        """Record the envelopes of one sample from an agent; return the genuine messages."""
        # the clock's time before the lock: the clock driver records its grants (the tap's
        # lock) while it holds its own, so asking it under the tap's lock deadlocked ``up``
        # (a junk payload without times arriving while grants went out)
        now_ns = self._now_ns()
        with self._lock:
            accepted, rejects = self._gate.admit_sample(key, sample)
            accepted, rejects = self._tally(key, accepted, rejects)
            if accepted:
                self._record(key, accepted[0][1].type,
                             [(payload, m.t_deliver_ns, m.t_send_ns) for payload, m in accepted],
                             [message for _, message in accepted])
            suspects = self._note_rejects(key, rejects, now_ns)
        if self._on_suspect is not None:
            for agent, why in suspects:
                self._on_suspect(agent, why)
        return [message for _, message in accepted]

    def take_attached(self, key: str, attachment: bytes) -> list[Envelope]:
        """Take the clock report an agent attached to its window's last sample on ``key``
        (:meth:`adnmesh.runtime.process.AgentProcess._run_window`): checked, recorded and
        returned exactly as if it had come on the report key of the key's sender, which is
        the only party the gate lets send it. An attachment on a key no agent of the run
        sends is rejected on that key (``unknown_key``)."""
        found = route(key)
        if found is None or found.sender not in self._agents:
            with self._lock:
                count_reject(self._gate.rejected, key, "unknown_key")
            return []
        return self.take(self._report_keys[found.sender], attachment)

    def record_own(self, key: str, message: Envelope, payload: bytes) -> None:
        """Record a message ``up`` sent itself."""
        with self._lock:
            self._record(key, message.type,
                         [(payload, message.t_deliver_ns, message.t_send_ns)], [message])

    @contextmanager
    def writes_after(self) -> Iterator[None]:
        """Within the block, what :meth:`take` and :meth:`record_own` accept is recorded, fed
        to the series and shown when the block ends, in the order it came (see the module
        docstring); what they check and count, and return, is as without it."""
        with self._lock:
            self._after = []
        try:
            yield
        finally:
            self._write_after()

    def _write_after(self) -> None:
        """Write what :meth:`writes_after` held, outside the tap's lock (a thread that holds
        the clock's lock and records a message of ``up``'s own waits for the tap's lock, not
        for a batch's writing: it adds to what is held meanwhile, written next, in order);
        every record is written even if one raises, and the first error is raised after."""
        error = None
        while True:
            with self._lock:
                after = self._after
                self._after = [] if after else None
            if not after:
                break
            with self._writing:
                for key, type_name, records, messages in after:
                    try:
                        self._write_and_feed(key, type_name, records, messages)
                    except Exception as exc:   # a bug in the series or the view: said after
                        error = error or exc
        if error is not None:
            raise error

    def count_rejected(self, key: str, reason: str) -> None:
        """Count a payload rejected elsewhere in ``up`` (e.g. a malformed fault request)."""
        with self._lock:
            self._gate.reject(key, reason)

    def rejected_total(self) -> int:
        """Every rejected payload so far."""
        with self._lock:
            return self._gate.rejected_total

    # -- internals (with the lock held) ----------------------------------------------------------

    def _tally(self, key: str, accepted: list, rejects: list) -> tuple[list, list]:
        """Count each agent's messages per key since its last clock report, and take a report
        only if it claims no more than that (a report that claims messages nobody sent would
        make their receivers wait for them for ever): else it is ``implausible``.

        A quarantined agent's messages count too, though they are not recorded as genuine:
        an agent sends on until its kill reaches it, its receivers count what they drop as
        quarantined (:meth:`adnmesh.sim.node.Node.receive`), and its report of them must
        reach the clock (else its process waits for its end for ever)."""
        found = route(key)
        for reject in rejects:
            if reject.reason == "quarantined" and found is not None:
                tally = self._unreported.setdefault(found.sender, {})
                tally[key] = tally.get(key, 0) + reject.envelopes
        kept = []
        for payload, message in accepted:
            sender = message.src
            if message.type != "clock_report":
                if sender != LAUNCHER:
                    tally = self._unreported.setdefault(sender, {})
                    tally[key] = tally.get(key, 0) + 1
                kept.append((payload, message))
                continue
            tally = self._unreported.setdefault(sender, {})
            over = [k for k, (count, _) in message.sent.items() if count > tally.get(k, 0)]
            if over and self._weigh_reports:
                count_reject(self._gate.rejected, key, "implausible")
                rejects.append(SampleReject("implausible", f"reports messages on {over[0]} "
                                            "that the recorder never saw", payload, 1))
                continue
            for k, (count, _) in message.sent.items():
                tally[k] = tally.get(k, 0) - count
            kept.append((payload, message))
        return kept, rejects

    def _note_rejects(self, key: str, rejects, now_ns: int) -> list[tuple[str, str]]:
        """Record the rejects of one sample (one record per reason, at most
        :data:`REJECTED_RECORDS_KEPT` in a run) and return the DER agents newly suspected of
        having a second sender (a reason of :data:`~adnmesh.wire.gate.SUSPICIOUS` on a key of
        theirs)."""
        records, suspects = [], []
        for reject in rejects:
            if self._records_kept < REJECTED_RECORDS_KEPT:
                self._records_kept += 1
                records.append(self._rejected_record(key, reject, now_ns))
            else:
                self.rejected_unrecorded += 1
            found = route(key)
            if reject.reason in SUSPICIOUS and found is not None:
                agent = found.sender
                if der_id_of(agent) is not None and agent not in self.suspects:
                    self.suspects[agent] = f"{reject.reason} on {key}: {reject.detail}"
                    suspects.append((agent, self.suspects[agent]))
        if records:
            self._record(self.rejected_key, REJECTED_TYPE, records, [])
        return suspects

    def cut_off(self, agent: str, from_ns: int) -> None:
        """Accept nothing more from ``agent`` sent at or after ``from_ns`` (quarantined)."""
        with self._lock:
            self._gate.cut_off(agent, from_ns)

    def _rejected_record(self, key: str, reject: SampleReject, now_ns: int):
        payload = reject.payload
        detail = reject.detail if reject.envelopes == 1 else \
            f"{reject.detail} (and {reject.envelopes - 1} more envelopes of the sample)"
        record = Rejected(key=key[:512], reason=reject.reason, detail=detail[:1000],
                          size_bytes=len(payload),
                          sha256=hashlib.sha256(payload).hexdigest(),
                          payload_prefix_b64=base64.b64encode(
                              payload[:REJECTED_PREFIX_BYTES]).decode())
        times = envelope_times(payload)
        t_send, t_deliver = times if times is not None else (now_ns,) * 2
        return encode(record), max(t_send, t_deliver), t_send

    def _record(self, key: str, type_name: str, records: list, messages: list) -> None:
        if self._after is not None:
            self._after.append((key, type_name, records, messages))
        else:
            with self._writing:
                self._write_and_feed(key, type_name, records, messages)

    def _write_and_feed(self, key: str, type_name: str, records: list, messages: list) -> None:
        if self._write(key, type_name, records):
            for message in messages:
                self.series.take(message)

    def _write(self, key: str, type_name: str, records: list) -> bool:
        try:
            self.recorder.write_many(key, type_name, records)
        except (ValueError, RuntimeError) as exc:   # reported at the end of the run
            if not self.record_errors and getattr(self.recorder, "failure", None) is None:
                self.problems.append(f"recording failed: {exc}")   # (a failed file: by up)
            self.record_errors += len(records)
            return False
        if self.view is not None:
            self.view.take(key, type_name, records)
        return True
