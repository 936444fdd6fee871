"""How late events are processed on the realtime clock: a histogram per link.

On the realtime clock an event (a delivered message, a timer) is due at its time on the scaled
wall clock; the **delivery error** is the time it was actually processed minus that, in ns of
sim time (0 on the sim clock, where time waits for the agents). :class:`Latency` counts the
errors of one agent per link (the link a message came over, ``timer`` for the agent's own
timers) in logarithmic bins — 8 per decade from 1 µs to 100 s — and keeps the exact largest;
histograms of several agents add up (:func:`merge`), and :func:`percentile` reads the upper
edge of the bin that holds it (so within 33 % above, never below, the true value).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["BINS", "Latency", "LinkLatency", "bin_of", "merge", "percentile", "upper_edge_ns"]

_PER_DECADE = 8
_LOW_NS = 1_000              # 1 µs: smaller errors go into bin 0
BINS = _PER_DECADE * 8 + 1   # up to 1e11 ns = 100 s, and one bin for everything beyond


def bin_of(error_ns: int) -> int:
    """The bin of a delivery error, ns."""
    if error_ns <= _LOW_NS:
        return 0
    return min(BINS - 1, 1 + int(math.log10(error_ns / _LOW_NS) * _PER_DECADE))


def upper_edge_ns(index: int) -> float:
    """The largest error bin ``index`` holds, ns."""
    return _LOW_NS * 10 ** (index / _PER_DECADE)


@dataclass
class LinkLatency:
    """The delivery errors of one link: bin counts and the largest, ns."""

    counts: list[int] = field(default_factory=lambda: [0] * BINS)
    max_ns: int = 0

    def add(self, error_ns: int) -> None:
        self.counts[bin_of(error_ns)] += 1
        if error_ns > self.max_ns:
            self.max_ns = error_ns


@dataclass
class Latency:
    """Delivery errors of one agent, per link (see the module docstring)."""

    links: dict[str, LinkLatency] = field(default_factory=dict)

    def add(self, link: str, error_ns: int) -> None:
        entry = self.links.get(link)
        if entry is None:
            entry = self.links[link] = LinkLatency()
        entry.add(max(0, int(error_ns)))

    def to_wire(self) -> dict[str, list[int]]:
        """``link -> [max_ns, count of bin 0, count of bin 1, ...]`` (the goodbye's form)."""
        return {link: [e.max_ns, *e.counts] for link, e in self.links.items()}


def merge(histograms) -> dict[str, LinkLatency]:
    """Add up ``link -> [max_ns, *counts]`` histograms of several agents."""
    merged: dict[str, LinkLatency] = {}
    for histogram in histograms:
        for link, values in histogram.items():
            if not values:                 # a malformed goodbye adds nothing
                continue
            max_ns, *counts = values
            entry = merged.setdefault(link, LinkLatency())
            entry.counts = [a + b for a, b in zip(entry.counts, counts)]
            entry.max_ns = max(entry.max_ns, max_ns)
    return merged


def percentile(entry: LinkLatency, q: float) -> float:
    """The ``q``-quantile (0 < q <= 1) of a link's errors, ns (the bin's upper edge; the
    largest error if that is smaller); NaN without events."""
    total = sum(entry.counts)
    if total == 0:
        return math.nan
    rank, seen = q * total, 0
    for index, count in enumerate(entry.counts):
        seen += count
        if seen >= rank:
            return min(upper_edge_ns(index), float(entry.max_ns))
    return float(entry.max_ns)
