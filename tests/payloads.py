"""Test helper: bus payloads of any message type from a key and a body."""

from __future__ import annotations

from adnmesh.wire.envelope import decode, encode
from adnmesh.wire.keys import route
from adnmesh.wire.messages import MESSAGE_TYPES, MESSAGE_VERSION


def payload(key: str, body: dict, *, src: str | None = None, seq: int = 0, t_send_ns: int = 0,
            t_deliver_ns: int | None = None) -> bytes:
    """The payload of a message on ``key`` (sender: the key's own unless given)."""
    found = route(key)
    cls = MESSAGE_TYPES[found.type]
    t_deliver = t_send_ns if t_deliver_ns is None else t_deliver_ns
    return encode(cls(MESSAGE_VERSION, found.type, src or found.sender, seq, t_send_ns,
                      t_deliver, **body))


def message(key: str, t_ns: int, body: dict, *, src: str | None = None, seq: int = 0):
    """A decoded message as the runtime would deliver it."""
    return decode(key, payload(key, body, src=src, seq=seq, t_send_ns=t_ns))
