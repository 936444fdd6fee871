"""Time on the bus: integer nanoseconds of sim time.

Every time in an envelope, in a clock message and in the sim layer is an integer number of
nanoseconds (sim time on the sim clock, scaled wall time since the run's start on the realtime
clock). Integers keep sim time exact and runs reproducible; the range is that of the recorder's
fields (unsigned 64 bit) cut to signed 64 bit, so that numpy's int64 holds every time too.
"""

from __future__ import annotations

__all__ = ["NS_MAX", "NS_PER_S", "ns", "seconds"]

NS_PER_S = 1_000_000_000
"""Nanoseconds per second."""

NS_MAX = (1 << 63) - 1
"""The largest time (and count) a message may carry, ns: about 292 years."""


def ns(seconds_: float) -> int:
    """Seconds to integer nanoseconds (rounded to the nearest ns)."""
    return int(round(seconds_ * 1e9))


def seconds(t_ns: int) -> float:
    """Integer nanoseconds to seconds."""
    return t_ns * 1e-9
