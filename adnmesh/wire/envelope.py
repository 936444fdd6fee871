"""Encoding and decoding envelopes, and framing several envelopes into one sample.

:func:`decode` is the one way in: a payload received on a key becomes the typed message of the
key's kind (:mod:`adnmesh.wire.protocol`) or raises :class:`MessageError`, whose ``reason`` is a
short category (for per-reason counts) and whose text says what was wrong. Decoding validates in
one step (msgspec checks every field while it parses), then checks what a schema cannot state:
the sender is the key's legitimate sender, and a message is not delivered before it was sent.

:func:`encode` is the one way out; :func:`envelope_times` reads the two times of an envelope
without decoding its body (for a recorder that must place even a rejected payload in time).

**Framing.** A Zenoh sample on a key carries one or more envelopes of that key, one per line
(JSON Lines; compact JSON never contains a raw newline): in sim mode an agent sends everything
it has for a key in one clock window as one sample (:func:`frames`); receivers and the recorder
split samples back into envelopes (:func:`split_frame`) and count envelopes.
"""

from __future__ import annotations

import msgspec

from adnmesh.wire.keys import route
from adnmesh.wire.messages import Envelope
from adnmesh.wire.protocol import STRUCTS

__all__ = [
    "MAX_ENVELOPE_BYTES",
    "MAX_FRAME_BYTES",
    "MAX_SAMPLE_BYTES",
    "MessageError",
    "decode",
    "decode_as",
    "encode",
    "envelope_times",
    "frames",
    "split_frame",
]

MAX_ENVELOPE_BYTES = 256 * 1024
"""A longer envelope is rejected unread (the largest genuine one, a goodbye of a 1,000-DER run,
is well below)."""

MAX_FRAME_BYTES = 32 * 1024
"""A frame grows to at most this size (one envelope may exceed it alone), so that a sample fits
in one Zenoh transport batch (64 KiB) and is never fragmented."""

MAX_SAMPLE_BYTES = 4 * 1024 * 1024
"""A longer sample is rejected as a whole, unsplit."""


class MessageError(ValueError):
    """A payload is not a valid message.

    Parameters
    ----------
    reason : str
        Category for counting: ``unknown_key``, ``too_large``, ``malformed`` (not JSON),
        ``invalid`` (a field missing, unknown, of the wrong type or out of range),
        ``wrong_sender`` (``src`` is not the key's sender), ``time_order`` (delivered before
        it was sent).
    detail : str
        One line saying what is wrong, with the JSON path where there is one.
    """

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


_DECODERS = {name: msgspec.json.Decoder(cls) for name, cls in STRUCTS.items()}
_ENCODER = msgspec.json.Encoder()


class _Times(msgspec.Struct):
    t_send_ns: int | None = None
    t_deliver_ns: int | None = None


_TIMES = msgspec.json.Decoder(_Times)


def decode_as(type_name: str, payload: bytes) -> Envelope:
    """Parse and validate ``payload`` as a message of ``type_name`` (no sender check).

    Raises
    ------
    MessageError
        As :func:`decode`.
    """
    if len(payload) > MAX_ENVELOPE_BYTES:
        raise MessageError("too_large", f"{len(payload)} bytes (at most {MAX_ENVELOPE_BYTES})")
    try:
        message = _DECODERS[type_name].decode(payload)
    except msgspec.ValidationError as exc:
        raise MessageError("invalid", str(exc)) from None
    except msgspec.DecodeError as exc:
        raise MessageError("malformed", str(exc)) from None
    if message.t_deliver_ns < message.t_send_ns:
        raise MessageError("time_order", "t_deliver_ns is earlier than t_send_ns")
    return message


def decode(key: str, payload: bytes) -> Envelope:
    """The message received on ``key``: parsed, validated, from the key's legitimate sender.

    Raises
    ------
    MessageError
        Unknown key, too large, not JSON, a field missing, unknown, of the wrong type or out
        of range, the wrong sender, or delivered before it was sent.
    """
    found = route(key)
    if found is None:
        raise MessageError("unknown_key", f"not an adnmesh message key: {key[:120]!r}")
    message = decode_as(found.type, payload)
    if message.src != found.sender:
        raise MessageError("wrong_sender", f"src {message.src!r} may not send on this key "
                                           f"(only {found.sender!r})")
    return message


def encode(message: Envelope) -> bytes:
    """The payload of ``message``: compact UTF-8 JSON, envelope fields first."""
    return _ENCODER.encode(message)


def envelope_times(payload: bytes) -> tuple[int, int] | None:
    """``(t_send_ns, t_deliver_ns)`` of a payload without validating its body; None if the
    payload is not a JSON object with two integer times in [0, 2**63)."""
    if len(payload) > MAX_ENVELOPE_BYTES:
        return None
    try:
        times = _TIMES.decode(payload)
    except (msgspec.DecodeError, RecursionError):
        return None
    t_send, t_deliver = times.t_send_ns, times.t_deliver_ns
    if t_send is not None and t_deliver is not None and 0 <= t_send < 1 << 63 and 0 <= t_deliver < 1 << 63:
        return t_send, t_deliver
    return None


def frames(messages: list[tuple[str, bytes]],
           max_bytes: int = MAX_FRAME_BYTES) -> list[tuple[str, bytes]]:
    """Group ``(key, payload)`` envelopes into samples per key (JSON Lines) of at most
    ``max_bytes``, keeping the order of the envelopes of each key."""
    grouped: dict[str, list[list]] = {}
    for key, payload in messages:
        chunks = grouped.setdefault(key, [])
        if chunks and chunks[-1][0] + len(payload) + 1 <= max_bytes:
            chunks[-1][0] += len(payload) + 1
            chunks[-1][1].append(payload)
        else:
            chunks.append([len(payload), [payload]])
    return [(key, b"\n".join(payloads)) for key, chunks in grouped.items()
            for _, payloads in chunks]


def split_frame(frame: bytes) -> list[bytes]:
    """The envelopes of one sample (see the framing above); a sample longer than
    :data:`MAX_SAMPLE_BYTES` is returned whole (and then rejected as too large)."""
    if len(frame) > MAX_SAMPLE_BYTES:
        return [frame]
    return frame.split(b"\n") if b"\n" in frame else [frame]
