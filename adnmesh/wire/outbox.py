"""The outbox: how every sender turns what it has to say into envelopes.

An agent returns a message as its key and body fields (:class:`adnmesh.control.base.Outgoing`);
``up`` and the agent process send their own (grants, faults, clock reports, goodbyes). Each
sender has one :class:`Outbox`, which numbers its messages per key (``seq`` from 0, counted
also for a message the ICT link model then loses, so that receivers see the gap) and builds the
key's struct (:mod:`adnmesh.wire.protocol`) with the envelope fields once, here. The struct is
then encoded once (:func:`~adnmesh.wire.envelope.encode`) and never rebuilt on its way.
"""

from __future__ import annotations

from typing import Any

from adnmesh.wire.keys import route
from adnmesh.wire.messages import MESSAGE_VERSION, Envelope

__all__ = ["Outbox"]


class Outbox:
    """The envelopes of one sender (not thread-safe: a sender that sends from several threads
    holds a lock around it).

    Parameters
    ----------
    sender : str
        The sender's id (an agent id, ``up`` or ``operator``): ``src`` of every envelope.
    """

    __slots__ = ("sender", "_kinds", "_seq")

    def __init__(self, sender: str) -> None:
        self.sender = sender
        self._kinds: dict[str, tuple[type[Envelope], str]] = {}
        self._seq: dict[str, int] = {}

    def take_seq(self, key: str) -> int:
        """The next ``seq`` on ``key`` (from 0), used up."""
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        return seq

    def message(self, key: str, seq: int, t_send_ns: int, t_deliver_ns: int,
                body: dict[str, Any]) -> Envelope:
        """The message of ``body`` on ``key`` with its envelope (times in ns of sim time).

        Raises
        ------
        KeyError
            ``key`` is not a key of the protocol.
        """
        found = self._kinds.get(key)
        if found is None:
            kind = route(key)
            if kind is None:
                raise KeyError(f"not an adnmesh message key: {key!r}")
            found = self._kinds[key] = (kind.kind.struct, kind.type)
        struct, type_name = found
        return struct(MESSAGE_VERSION, type_name, self.sender, seq, t_send_ns, t_deliver_ns,
                      **body)

    def send(self, key: str, t_send_ns: int, body: dict[str, Any],
             t_deliver_ns: int | None = None) -> Envelope:
        """The next message on ``key``, sent at ``t_send_ns`` and delivered then (or at
        ``t_deliver_ns``)."""
        return self.message(key, self.take_seq(key), t_send_ns,
                            t_send_ns if t_deliver_ns is None else t_deliver_ns, body)

    def counts(self) -> dict[str, int]:
        """Messages numbered so far, per key."""
        return dict(self._seq)
