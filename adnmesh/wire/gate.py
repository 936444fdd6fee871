"""The gate: what a receiver accepts from the bus, and the count of what it rejects.

Every receiver of the run's messages (an agent's node, :mod:`adnmesh.sim.node`, and the
recorder's tap, :mod:`adnmesh.runtime.tap`) lets payloads in through a :class:`Gate`, so the
accept rules are one set, in this order:

1. the key is one this receiver accepts (its subscriptions; for the recorder, every key a party
   of the run sends) — else ``not_subscribed`` / ``unknown_key``;
2. the payload decodes and validates as the key's kind, from the key's one legitimate sender,
   delivered no earlier than sent (:func:`~adnmesh.wire.envelope.decode`: ``too_large``,
   ``malformed``, ``invalid``, ``wrong_sender``, ``time_order``);
3. it names no DER the run does not have (SI, the CPFC's weights) — else ``unknown_der``;
4. its (send time, ``seq``) comes after the last one accepted on the key — else ``replayed``
   (a replay, a duplicate, or a message out of its sender's order);
5. it was sent no earlier than the receiver began (a restarted agent) — else ``before_start``.

Whatever fails is counted per key and reason, at most :data:`KEYS_TOLD_APART` keys told apart
(a flood of made-up keys cannot grow the counts), and never raised past the receiver.
"""

from __future__ import annotations

from collections.abc import Collection

from msgspec import UNSET

from adnmesh.wire.envelope import MessageError, decode
from adnmesh.wire.messages import Envelope

__all__ = ["KEYS_TOLD_APART", "OTHER_KEYS", "Gate", "count_reject", "names_known_ders"]

KEYS_TOLD_APART = 256
"""Most distinct keys whose rejects are counted apart; the rest count under :data:`OTHER_KEYS`."""

OTHER_KEYS = "(other keys)"
"""Where rejects on keys beyond :data:`KEYS_TOLD_APART` are counted."""


def count_reject(rejected: dict[str, dict[str, int]], key: str, reason: str) -> None:
    """Count one rejected payload on ``key`` in ``rejected`` (``key -> {reason -> count}``)."""
    if key not in rejected and len(rejected) >= KEYS_TOLD_APART:
        key = OTHER_KEYS
    per_key = rejected.setdefault(key, {})
    per_key[reason] = per_key.get(reason, 0) + 1


def names_known_ders(message: Envelope, der_ids: frozenset[str]) -> bool:
    """False if ``message`` names a DER the run does not have (SI, the CPFC's weights)."""
    if message.type == "si":
        return message.si.keys() <= der_ids
    if message.type == "p_y" and message.w is not UNSET:
        return message.w.keys() <= der_ids
    return True


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

    Attributes
    ----------
    rejected : dict
        ``key -> {reason -> count}`` of every payload rejected so far.
    """

    def __init__(self, accepts: Collection[str], der_ids: frozenset[str], *,
                 outside_reason: str, outside_detail: str = "not a key this receiver takes",
                 start_ns: int = 0) -> None:
        self.accepts = frozenset(accepts)
        self.der_ids = frozenset(der_ids)
        self.outside = (outside_reason, outside_detail)
        self.start_ns = int(start_ns)
        self.rejected: dict[str, dict[str, int]] = {}
        self._last: dict[str, tuple[int, int]] = {}   # key -> (t_send, seq) last accepted

    def admit(self, key: str, payload: bytes) -> Envelope:
        """The genuine message ``payload`` on ``key``, noted as the key's last one.

        Raises
        ------
        MessageError
            The payload is rejected (already counted in :attr:`rejected`).
        """
        try:
            if key not in self.accepts:
                raise MessageError(*self.outside)
            message = decode(key, payload)
            if not names_known_ders(message, self.der_ids):
                raise MessageError("unknown_der", "names a DER this run does not have")
            stamp = (message.t_send_ns, message.seq)
            last = self._last.get(key)
            if last is not None and stamp <= last:
                raise MessageError("replayed", f"(t_send_ns, seq) {stamp} already seen")
            if message.t_send_ns < self.start_ns:
                raise MessageError("before_start", "sent before this receiver began")
        except MessageError as exc:
            count_reject(self.rejected, key, exc.reason)
            raise
        self._last[key] = stamp
        return message

    def reject(self, key: str, reason: str) -> None:
        """Count a payload on ``key`` rejected after the gate (e.g. delivered in the past)."""
        count_reject(self.rejected, key, reason)

    @property
    def rejected_total(self) -> int:
        """Every payload rejected so far."""
        return sum(sum(r.values()) for r in self.rejected.values())
