"""One decode of a sample for every receiver of a process that takes it.

The DERs a process hosts (``runtime.ders_per_process``, :mod:`adnmesh.runtime.host`) all take
the CPFC's ``P_Y``: the same payload, which each one's gate decoded again. With 1,000 DERs the
weights it carries about once a second name all of them (12 KB), and 50 decodes per sample cost
more than the DERs' own work. :class:`SharedDecode` stands in for
:func:`~adnmesh.wire.envelope.decode` in those gates: a payload on a key is decoded once, and
every gate gets that message (or its rejection). Everything after the decode — the accept rules
that depend on the receiver — stays each gate's own. Receivers read messages, never change them.
"""

from __future__ import annotations

import threading

from adnmesh.wire.envelope import MAX_ENVELOPE_BYTES, MessageError, decode
from adnmesh.wire.messages import Envelope

__all__ = ["SharedDecode"]


class SharedDecode:
    """``decode(key, payload)`` remembered for the last ``size`` distinct ``(key, payload)``
    (a sample fans out to its receivers one after the other, while other keys' samples arrive
    on Zenoh's other threads: thread-safe), holding at most ``max_bytes`` of payloads; a
    payload longer than an envelope may be is not kept (it is rejected unread anyway). A
    rejected payload raises a new :class:`~adnmesh.wire.envelope.MessageError` with the same
    reason and detail each time.

    Attributes
    ----------
    decoded, shared : int
        Payloads decoded, and decodes spared (a remembered one given again).
    """

    def __init__(self, size: int = 64, max_bytes: int = 4 * 1024 * 1024) -> None:
        if size < 1:
            raise ValueError(f"size must be at least 1, got {size}")
        self.size = size
        self.max_bytes = max_bytes
        self._bytes = 0
        self.decoded = 0
        self.shared = 0
        self._memo: dict[tuple[str, bytes], Envelope | MessageError] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> Envelope:
        if len(payload) > MAX_ENVELOPE_BYTES:
            return decode(key, payload)        # too_large, unread
        memo_key = (key, payload)
        with self._lock:
            found = self._memo.get(memo_key)
            if found is not None:
                self.shared += 1
        if found is None:
            try:
                found = decode(key, payload)
            except MessageError as exc:
                found = exc
            with self._lock:
                self.decoded += 1
                if memo_key not in self._memo:
                    self._memo[memo_key] = found
                    self._bytes += len(payload)
                while len(self._memo) > self.size or self._bytes > self.max_bytes:
                    self._bytes -= len(next(iter(self._memo))[1])
                    del self._memo[next(iter(self._memo))]
        if isinstance(found, MessageError):
            raise MessageError(found.reason, found.detail)
        return found
