"""The gate: what a receiver accepts from the bus, and the count of what it rejects.

Every receiver of the run's messages (an agent's node, :mod:`adnmesh.sim.node`, and the
recorder's tap, :mod:`adnmesh.runtime.tap`) lets payloads in through a :class:`Gate`, so the
accept rules are one set, in this order:

1. the key is one this receiver accepts (its subscriptions; for the recorder, every key a party
   of the run sends) — else ``not_subscribed`` / ``unknown_key``;
2. the payload decodes and validates as the key's kind, from the key's one legitimate sender,
   delivered no earlier than sent (:func:`~adnmesh.wire.envelope.decode`: ``too_large``,
   ``malformed``, ``invalid``, ``wrong_sender``, ``time_order``);
3. it names no DER the run does not have (SI, the CPFC's weights, the grid guard's lists) —
   else ``unknown_der``;
4. its sender is not cut off: an agent ``up`` quarantined sends nothing genuine from the
   quarantine on (but the clock protocol of its process, which ends it) — else
   ``quarantined``;
5. it was sent within the clock's reach: the recorder knows how far the sim clock granted each
   agent, and no agent sends beyond its grant — else ``ahead_of_clock``;
6. what it says is physically possible: a DER's infeed and setpoint within ``[0, P_inst]`` of
   that DER — else ``implausible``;
7. its (send time, ``seq``) is new on the key — else ``replayed``: it repeats one already
   processed or held, or comes after one the receiver processed (a replay, a duplicate, or a
   message out of its sender's order);
8. it was sent no earlier than the receiver began (a restarted agent) — else ``before_start``.

Rule 7 compares with what the receiver has **processed**, not with everything it was sent: a
node holds a message until its delivery time (:meth:`Gate.consumed` then marks it processed),
so a forged message with a far-future send time or a huge ``seq`` sits in the inbox and cannot
shut out the genuine sender's next messages (it was accepted before they were sent, and they
come before it in time). An injected fault is taken at once and orders nothing
(:meth:`Gate.taken_unordered`): its receiver knows a fault by what it says.

Whatever fails is counted per key and reason, at most :data:`KEYS_TOLD_APART` keys told apart
(a flood of made-up keys cannot grow the counts), and never raised past the receiver. A sample
(:func:`~adnmesh.wire.envelope.split_frame`) counts **once per reason** however many of its
envelopes fail (:meth:`Gate.admit_sample`): the counts are of messages the bus carried, not of
fragments an attacker chose to cut a payload into.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from typing import NamedTuple

from msgspec import UNSET

from adnmesh.names import der_id_of
from adnmesh.wire.envelope import MessageError, decode, split_frame
from adnmesh.wire.keys import route
from adnmesh.wire.messages import Envelope

__all__ = ["HELD_MAX", "KEYS_TOLD_APART", "OTHER_KEYS", "SUSPICIOUS", "Gate", "SampleReject",
           "count_reject", "names_known_ders"]

KEYS_TOLD_APART = 256
"""Most distinct keys whose rejects are counted apart; the rest count under :data:`OTHER_KEYS`."""

OTHER_KEYS = "(other keys)"
"""Where rejects on keys beyond :data:`KEYS_TOLD_APART` are counted."""

SUSPICIOUS = frozenset({"ahead_of_clock", "implausible", "replayed", "held_full"})
"""Reasons that a genuine sender never gives (its messages are in time, possible and in order):
evidence that someone else sends with its identity (:mod:`adnmesh.runtime.tap` reports it)."""

_SLACK_W = 1.0
"""Rounding slack on a DER's power range, W."""

HELD_MAX = 4096
"""Most messages a receiver holds on one key at once (genuine traffic holds a few dozen: the
messages of one link delay); beyond, a flood is rejected (``held_full``)."""


def count_reject(rejected: dict[str, dict[str, int]], key: str, reason: str,
                 count: int = 1) -> None:
    """Count ``count`` rejected payloads on ``key`` in ``rejected`` (``key -> {reason ->
    count}``)."""
    if key not in rejected and len(rejected) >= KEYS_TOLD_APART:
        key = OTHER_KEYS
    per_key = rejected.setdefault(key, {})
    per_key[reason] = per_key.get(reason, 0) + count


def names_known_ders(message: Envelope, der_ids: frozenset[str]) -> bool:
    """False if ``message`` names a DER the run does not have (SI, the CPFC's weights, the
    grid guard's blocked DERs)."""
    if message.type == "si":
        return message.si.keys() <= der_ids
    if message.type in ("p_y", "q_y"):
        return ((message.w is UNSET or message.w.keys() <= der_ids)
                and (message.switch is UNSET or message.switch.keep is UNSET
                     or set(message.switch.keep) <= der_ids))
    if message.type == "grid_guard":
        return all(set(ders) <= der_ids for ders in (message.p_up, message.p_down,
                                                       message.q_up, message.q_down))
    return True


class SampleReject(NamedTuple):
    """The envelopes of one sample rejected for one reason: the first one's detail and payload,
    and how many there were."""

    reason: str
    detail: str
    payload: bytes
    envelopes: int


class Gate:
    """The accept rules of one receiver (see the module docstring); not thread-safe.

    Parameters
    ----------
    accepts : collection of str
        The keys this receiver takes.
    der_ids : frozenset of str
        The run's DERs.
    outside_reason, outside_detail : str
        How a payload on any other key is rejected (``not_subscribed`` for an agent,
        ``unknown_key`` for the recorder) and what its record says.
    start_ns : int
        When the receiver began, ns of sim time (0, or later for a restarted agent).
    capacity_w : mapping, optional
        DER id -> its installed power P_inst, W: the range of its infeed and setpoint.
    clock_reach_ns : callable, optional
        Agent id -> how far the sim clock has granted it, ns (None: no bound); rule 5, for
        the messages an agent's node sends (not the clock protocol).
    decoder : callable, optional
        ``(key, payload) -> Envelope`` of rule 2 (default :func:`~adnmesh.wire.envelope.decode`;
        the receivers of one process may share one, :mod:`adnmesh.wire.shared_decode`).

    Attributes
    ----------
    rejected : dict
        ``key -> {reason -> count}`` of every payload rejected so far.
    """

    def __init__(self, accepts: Collection[str], der_ids: frozenset[str], *,
                 outside_reason: str, outside_detail: str = "not a key this receiver takes",
                 start_ns: int = 0, capacity_w: Mapping[str, float] | None = None,
                 clock_reach_ns: Callable[[str], int | None] | None = None,
                 decoder: Callable[[str, bytes], Envelope] = decode) -> None:
        self.accepts = frozenset(accepts)
        self.der_ids = frozenset(der_ids)
        self.outside = (outside_reason, outside_detail)
        self.start_ns = int(start_ns)
        self.capacity_w = dict(capacity_w or {})
        self.clock_reach_ns = clock_reach_ns
        self.decoder = decoder
        self.rejected: dict[str, dict[str, int]] = {}
        self._processed: dict[str, tuple[int, int]] = {}   # key -> latest (t_send, seq) done
        self._held: dict[str, set[tuple[int, int]]] = {}   # key -> stamps accepted, not done
        self._taken: dict[str, dict[tuple[int, int], None]] = {}   # key -> stamps taken at
        #                                                            once, oldest first
        self._cut_off: dict[str, int] = {}                 # agent -> quarantined from, ns

    def admit(self, key: str, payload: bytes, *, hold: bool = False) -> Envelope:
        """The genuine message ``payload`` on ``key``.

        ``hold``: the receiver processes it later and says so with :meth:`consumed` (a node);
        else it counts as processed now (the recorder).

        Raises
        ------
        MessageError
            The payload is rejected (already counted in :attr:`rejected`).
        """
        try:
            message = self._check(key, payload, hold)
        except MessageError as exc:
            count_reject(self.rejected, key, exc.reason)
            raise
        return message

    def admit_sample(self, key: str, sample: bytes, *, hold: bool = False
                     ) -> tuple[list[tuple[bytes, Envelope]], list[SampleReject]]:
        """The genuine messages of one sample, each with its payload, and the sample's
        rejects, one per reason (each counted once, see the module docstring)."""
        accepted: list[tuple[bytes, Envelope]] = []
        rejects: dict[str, SampleReject] = {}
        bounds = None                  # what the key's sender may send, once per sample
        for payload in split_frame(sample):
            try:
                if bounds is None:
                    bounds = self._bounds(key)
                accepted.append((payload, self._check_bounded(key, payload, hold, bounds)))
            except MessageError as exc:
                found = rejects.get(exc.reason)
                rejects[exc.reason] = SampleReject(exc.reason, exc.detail, payload, 1) \
                    if found is None else found._replace(envelopes=found.envelopes + 1)
        for reject in rejects.values():
            count_reject(self.rejected, key, reject.reason)
        return accepted, list(rejects.values())

    def consumed(self, key: str, message: Envelope) -> None:
        """A held message on ``key`` is processed (or dropped): later ones must come after it."""
        stamp = (message.t_send_ns, message.seq)
        held = self._held.get(key)
        if held is not None:
            held.discard(stamp)
        last = self._processed.get(key)
        if last is None or stamp > last:
            self._processed[key] = stamp

    def taken_unordered(self, key: str, message: Envelope) -> None:
        """A held message on ``key`` was taken at once and orders nothing after it (an
        injected fault: it carries its own window, and its receiver knows a fault it has
        applied by what it says). Unlike :meth:`consumed`, a later message with an earlier
        ``(t_send, seq)`` stays welcome: a forged fault with a huge ``seq`` cannot shut out
        ``up``'s own. The same stamp again is ``replayed`` (the last :data:`HELD_MAX` stamps
        are remembered; older ones are forgotten, so a flood cannot refuse a new one)."""
        stamp = (message.t_send_ns, message.seq)
        held = self._held.get(key)
        if held is not None:
            held.discard(stamp)
        taken = self._taken.setdefault(key, {})
        taken[stamp] = None
        if len(taken) > HELD_MAX:           # the oldest go: a flood cannot refuse a new one
            del taken[next(iter(taken))]

    def cut_off(self, agent: str, from_ns: int) -> None:
        """Accept nothing ``agent`` sends at or after ``from_ns`` (it is quarantined)."""
        self._cut_off[agent] = min(int(from_ns), self._cut_off.get(agent, int(from_ns)))

    def is_cut_off(self, message: Envelope) -> bool:
        """``message`` was sent by a quarantined agent after its quarantine (a receiver that
        held it from before the quarantine drops it unprocessed)."""
        cut = self._cut_off.get(message.src)
        return cut is not None and message.t_send_ns >= cut

    def reject(self, key: str, reason: str) -> None:
        """Count a payload on ``key`` rejected after the gate (e.g. delivered in the past)."""
        count_reject(self.rejected, key, reason)

    @property
    def rejected_total(self) -> int:
        """Every payload rejected so far."""
        return sum(sum(r.values()) for r in self.rejected.values())

    def _check(self, key: str, payload: bytes, hold: bool) -> Envelope:
        return self._check_bounded(key, payload, hold, self._bounds(key))

    def _bounds(self, key: str) -> _Bounds:
        """Rule 1 on ``key``, and what rules 4 to 6 allow its sender now (the same for every
        envelope of one sample)."""
        if key not in self.accepts:
            raise MessageError(*self.outside)
        found = route(key)
        if found is None:                      # rule 2 rejects every envelope (unknown key)
            return _Bounds(None, None, None, None)
        return self._bounds_of(found, found.sender)

    def _check_bounded(self, key: str, payload: bytes, hold: bool,
                       bounds: _Bounds) -> Envelope:
        message = self.decoder(key, payload)
        if not names_known_ders(message, self.der_ids):
            raise MessageError("unknown_der", "names a DER this run does not have")
        sender, t_send = message.src, message.t_send_ns
        if sender != bounds.sender:            # (a decoder that does not check the sender)
            bounds = self._bounds_of(route(key), sender)
        cut = bounds.cut_ns
        if cut is not None and t_send >= cut:
            raise MessageError("quarantined", f"{sender} is quarantined from {cut} ns")
        reach = bounds.reach_ns
        if reach is not None and t_send > reach:
            raise MessageError("ahead_of_clock", f"sent at {t_send} ns, but {sender} "
                               f"was granted only to {reach} ns")
        if message.type == "der_state" and not _possible(message, bounds.p_inst_w):
            raise MessageError("implausible", f"infeed {message.p_w:.6g} W or setpoint "
                               f"{message.setpoint_w:.6g} W beyond what {sender} can do")
        stamp = (t_send, message.seq)
        last = self._processed.get(key)
        held = None
        if hold:
            held = self._held.get(key)
            if held is None:
                held = self._held[key] = set()
        if (last is not None and stamp <= last) or (held is not None and stamp in held) \
                or stamp in self._taken.get(key, ()):
            raise MessageError("replayed", f"(t_send_ns, seq) {stamp} already seen")
        if held is not None and len(held) >= HELD_MAX:
            raise MessageError("held_full", f"{HELD_MAX} messages already held on the key")
        if t_send < self.start_ns:
            raise MessageError("before_start", "sent before this receiver began")
        if held is not None:
            held.add(stamp)
        else:
            self._processed[key] = stamp
        return message

    def _bounds_of(self, found, sender: str) -> _Bounds:
        """What rules 4 to 6 allow ``sender`` now on the key ``found`` routes."""
        p_inst = self.capacity_w.get(der_id_of(sender) or "")
        if found.kind.link is None:            # the clock protocol: rules 4 and 5 do not apply
            return _Bounds(sender, None, None, p_inst)
        reach = None if self.clock_reach_ns is None else self.clock_reach_ns(sender)
        return _Bounds(sender, self._cut_off.get(sender), reach, p_inst)


class _Bounds(NamedTuple):
    """What a gate lets one sender send on one key now: rules 4 to 6."""

    sender: str | None
    cut_ns: int | None          # quarantined from, ns (rule 4)
    reach_ns: int | None        # granted to, ns (rule 5)
    p_inst_w: float | None      # the sender DER's installed power, W (rule 6)


def _possible(message, p_inst_w: float | None) -> bool:
    """A DER's infeed and setpoint within [0, P_inst] (plus rounding)."""
    if p_inst_w is None:
        return True
    low, high = -_SLACK_W, p_inst_w * (1 + 1e-9) + _SLACK_W
    return low <= message.p_w <= high and low <= message.setpoint_w <= high
