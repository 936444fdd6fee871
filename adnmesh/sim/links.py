"""The ICT channel model: per-link delay, jitter, loss and outages, decided on the sender's side.

Every logical link (CPFC → DERs, measurement → CPFC, DER → availability monitor, availability
monitor → CPFC) is configured in the config's ``runtime.links`` (:class:`adnmesh.config.Links`).
The sender passes every message through its :class:`Link`, which returns the delivery time (or
``None``: lost) from the link's settings and a seeded random stream. The stream depends only on the
run's seed, the link's name and the sender, and every message draws the same numbers whatever
happens to it, so a run is reproducible message by message. The receiver holds a message until its
delivery time (the clock does that). Times are integer nanoseconds; sim time is exact.

Fate of a message sent at ``t`` (in this order):

1. lost if ``t`` falls in an outage window ``[t_s, t_s + duration_s)``,
2. lost with probability ``loss``,
3. otherwise delivered at ``t + delay + floor(U * jitter)`` (``U`` uniform in [0, 1)), and with
   ``fifo`` (the default) never before the previous message delivered on the link.

Injected faults (:class:`Impairment`, added at run time) act after that, while ``t`` is in their
window: an outage loses the message, a loss probability loses it with that probability (drawn
from a stream of its own, so that the link's own stream is the same as in a run without the
fault), a delay spike delays it further (FIFO still holds).
"""

from __future__ import annotations

import hashlib
import random
from dataclasses import dataclass

from adnmesh.config import LinkSettings
from adnmesh.wire.units import ns

__all__ = ["Impairment", "Link", "LinkParams", "stream_seed"]


def stream_seed(seed: int, *names: str) -> int:
    """A 64-bit seed for the random stream named ``names`` of a run with ``seed``."""
    text = "/".join((str(seed), *names)).encode()
    return int.from_bytes(hashlib.sha256(text).digest()[:8], "big")


@dataclass(frozen=True)
class LinkParams:
    """A link's settings in integer nanoseconds.

    Parameters
    ----------
    name : str
        Link name, e.g. ``cpfc_to_der``; ``physical`` and ``local`` are the lossless zero-delay
        paths (DER infeed to the measurement; records nobody receives).
    delay_ns, jitter_ns : int
        Fixed delay and jitter span, ns.
    loss : float
        Loss probability in [0, 1).
    fifo : bool
        Keep the send order.
    outages_ns : tuple of (int, int)
        ``[start, end)`` windows, ns.
    """

    name: str
    delay_ns: int
    jitter_ns: int = 0
    loss: float = 0.0
    fifo: bool = True
    outages_ns: tuple[tuple[int, int], ...] = ()

    @classmethod
    def from_settings(cls, name: str, settings: LinkSettings,
                      delay_s: float | None = None) -> LinkParams:
        """Build from the config; ``delay_s`` is used when the settings carry none."""
        delay = settings.delay_s if settings.delay_s is not None else delay_s
        if delay is None:
            raise ValueError(f"link {name}: no delay")
        return cls(name, ns(delay), ns(settings.jitter_s), float(settings.loss),
                   bool(settings.fifo),
                   tuple((ns(o.t_s), ns(o.t_s + o.duration_s)) for o in settings.outages))

    @property
    def min_delay_ns(self) -> int:
        """The lookahead the link gives the clock: no message arrives sooner than this."""
        return self.delay_ns


@dataclass(frozen=True)
class Impairment:
    """An injected fault on a link: ``kind`` ``outage``, ``loss`` (``value`` the probability) or
    ``delay`` (``value`` the extra delay, ns) for messages sent in ``[start_ns, end_ns)``
    (``end_ns`` None: to the end of the run)."""

    fault_id: int
    kind: str
    start_ns: int
    end_ns: int | None
    value: float = 0.0

    def covers(self, t_ns: int) -> bool:
        return self.start_ns <= t_ns and (self.end_ns is None or t_ns < self.end_ns)


class Link:
    """Sender side of one link for one sender: decides each message's fate.

    Parameters
    ----------
    params : LinkParams
    seed : int
        The run's seed.
    sender : str
        The sending agent's id (each sender has its own stream).
    """

    def __init__(self, params: LinkParams, seed: int, sender: str) -> None:
        self.params = params
        self._random = random.Random(stream_seed(seed, params.name, sender))
        self._last_deliver_ns = -1
        self._draws = params.loss > 0 or params.jitter_ns > 0
        self._ideal = not (self._draws or params.outages_ns)
        self._seed, self._sender = seed, sender
        self._impairments: list[tuple[Impairment, random.Random]] = []
        self.lost = 0

    @property
    def impairments(self) -> list[Impairment]:
        """The injected faults on this link, in the order they came."""
        return [impairment for impairment, _ in self._impairments]

    def impair(self, impairment: Impairment) -> None:
        """Add an injected fault (see the module docstring)."""
        stream = random.Random(stream_seed(self._seed, self.params.name, self._sender,
                                           f"fault{impairment.fault_id}"))
        self._impairments.append((impairment, stream))
        self._ideal = False

    def transmit(self, t_send_ns: int) -> int | None:
        """Return the delivery time (ns) of a message sent at ``t_send_ns``, or None if lost."""
        p = self.params
        if self._ideal:  # fixed delay: FIFO by construction (sends come in time order)
            return t_send_ns + p.delay_ns
        u_loss = u_jitter = 0.0
        if self._draws:
            u_loss = self._random.random()
            u_jitter = self._random.random()
        for start, end in p.outages_ns:
            if start <= t_send_ns < end:
                self.lost += 1
                return None
        if p.loss > 0 and u_loss < p.loss:
            self.lost += 1
            return None
        t_deliver = t_send_ns + p.delay_ns + int(u_jitter * p.jitter_ns)
        for impairment, stream in self._impairments:
            if not impairment.covers(t_send_ns):
                continue
            if impairment.kind == "outage" or (impairment.kind == "loss"
                                               and stream.random() < impairment.value):
                self.lost += 1
                return None
            if impairment.kind == "delay":
                t_deliver += int(impairment.value)
        if p.fifo and t_deliver < self._last_deliver_ns:
            t_deliver = self._last_deliver_ns
        self._last_deliver_ns = t_deliver
        return t_deliver
