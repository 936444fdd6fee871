"""The realtime clock of an agent process: sim time on the scaled wall clock.

``up`` announces the epoch (wall-clock ns of sim time 0), the speed and a tolerance; every
process then reads sim time as ``(wall - epoch) · speed`` from the monotonic clock (anchored to
the wall clock once, so that a wall-clock step cannot make time jump) and processes each event
at its time: it sleeps until the next event or message is due, processes what is due, and
measures every event's delivery error (:mod:`adnmesh.sim.latency`). When an error exceeds the
tolerance — the machine cannot keep up with the speed — it says so at once with an ``overrun``
event (at most one per second of sim time), so that ``up`` can warn, and stop with
``--strict``.
"""

from __future__ import annotations

import time

from adnmesh.names import ICT_LINKS
from adnmesh.sim.topology import Topology

__all__ = ["OVERRUN_EVERY_NS", "OverrunWatch", "ScaledClock", "tolerance_ns"]

OVERRUN_EVERY_NS = 1_000_000_000
"""At most one overrun event per this much sim time, ns."""

TOLERANCE_SHARE = 0.05
"""The default tolerance: this share of the shortest ICT link delay."""


def tolerance_ns(configured_s: float | None, topology: Topology) -> int:
    """The overrun tolerance of a run, ns of sim time: ``runtime.realtime_tolerance_s`` or
    :data:`TOLERANCE_SHARE` of the shortest positive ICT link delay (1 ms without one).

    A message that arrives later than its delivery time changes the run (it acts as a longer
    delay); below the shortest link delay every message is still there when it is due, so a
    small share of it keeps the realtime run equal to the sim run with margin to spare.
    """
    if configured_s is not None:
        return max(1, round(configured_s * 1e9))
    delays = [link.delay_ns for link in topology.links.values()
              if link.name in ICT_LINKS and link.delay_ns > 0]
    return round(TOLERANCE_SHARE * min(delays)) if delays else 1_000_000


class ScaledClock:
    """Sim time of a realtime run (see the module docstring).

    Parameters
    ----------
    epoch_ns : int
        Wall-clock time (ns since the Unix epoch) of sim time 0.
    speed : float
        Sim seconds per wall second.
    """

    def __init__(self, epoch_ns: int, speed: float) -> None:
        self.speed = float(speed)
        # monotonic ns at sim time 0, taken once from the wall clock
        self._zero = time.monotonic_ns() + (epoch_ns - time.time_ns())

    def now_ns(self) -> int:
        """Sim time now, ns (negative before the start)."""
        return int((time.monotonic_ns() - self._zero) * self.speed)

    def monotonic_ns(self, t_sim_ns: int) -> int:
        """The monotonic clock's reading (:func:`time.monotonic_ns`) at sim time ``t_sim_ns``."""
        return int(t_sim_ns / self.speed) + self._zero

    def wait_s(self, t_sim_ns: int) -> float:
        """Wall seconds until sim time ``t_sim_ns``."""
        return (t_sim_ns / self.speed + self._zero - time.monotonic_ns()) * 1e-9


class OverrunWatch:
    """Turns delivery errors beyond the tolerance into overrun event bodies, rate-limited."""

    def __init__(self, agent: str, tolerance_ns: int, speed: float) -> None:
        self.agent = agent
        self.tolerance_ns = tolerance_ns
        self.speed = speed
        self._next_ns = 0
        self.count = 0

    def check(self, now_ns: int, worst: tuple[int, str]) -> dict | None:
        """The body of an overrun event if ``worst`` (error ns, link) is beyond the tolerance
        and none was sent in the last second of sim time, else None."""
        error, link = worst
        if self.tolerance_ns <= 0 or error <= self.tolerance_ns:
            return None
        self.count += 1
        if now_ns < self._next_ns:
            return None
        self._next_ns = now_ns + OVERRUN_EVERY_NS
        return {"level": "WARNING", "kind": "overrun", "subject": self.agent,
                "text": f"{self.agent} is {error / 1e6:.1f} ms of sim time behind the scaled "
                        f"wall clock ({error / 1e6 / self.speed:.1f} ms wall, {link}) at speed "
                        f"{self.speed:g}: more than the tolerance of "
                        f"{self.tolerance_ns / 1e6:g} ms; the run is not real time"}
