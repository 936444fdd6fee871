"""The DER agent's gateway to its plant device: a protocol link driven from a thread of its own.

:class:`Gateway` is the DER controller's :class:`~adnmesh.control.plant_device.PlantDevice`:
the controller hands it set-points and takes its status without ever waiting for the network.
Its thread connects, writes each new set-point pair, reads the measurement every
``poll_period_s`` and keeps the device's health. A new pair is written at once, unless

- it differs from the pair last written by no more than the dead band in P and in Q: it is not
  written (the device already runs within the dead band of it), or
- the last write was less than ``write_interval_s`` ago: the newest pair is written when the
  interval has passed (pairs in between are never written).

Its health:

- an error of the link (:class:`~adnmesh.devices.link.DeviceError`) makes the device unhealthy
  with its reason; after ``unreachable``, ``timeout`` or ``malformed`` the link is closed and
  opened again every ``retry_s``; a ``refused`` write is tried again every ``retry_s`` (with the
  newest set-points) while reads go on;
- a reading whose time stamp has not advanced for ``stale_after_s`` is ``stale``; one that says
  the plant is not connected is ``disconnected``;
- the device is healthy again when it is reachable, its last write was taken, its time stamp
  advances and it is connected.

:class:`DeviceHealth` is that bookkeeping as a pure state machine (times in s, given by the
caller); the thread only calls the link and feeds it. Each write's and read's duration is kept
(the last :data:`LATENCIES_KEPT`) for the agent's goodbye: p50 and p99 in ms.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

from adnmesh.control.plant_device import DeviceStatus
from adnmesh.devices.link import DeviceError, DeviceLink, Reading

__all__ = ["DeviceHealth", "Gateway", "LATENCIES_KEPT"]

LATENCIES_KEPT = 20_000
"""How many write and read durations a gateway keeps for its statistics."""

_START_RETRY_S = 0.05
"""While a gateway starts (within ``first_within_s``), a device that failed is tried again this
soon, s."""

_RECONNECT = frozenset({"unreachable", "timeout", "malformed"})


class DeviceHealth:
    """Health of one device from what its link did (see the module docstring; times in s)."""

    def __init__(self, stale_after_s: float) -> None:
        self.stale_after_s = stale_after_s
        self.reading: Reading | None = None
        self._link_error: DeviceError | None = DeviceError("unreachable", "not connected yet")
        self._refused: DeviceError | None = None
        self._stamp: tuple[float, float] | None = None   # (stamp, when it last advanced)
        self._now = 0.0

    @property
    def link_up(self) -> bool:
        """The link is connected and answered its last call."""
        return self._link_error is None

    def failed(self, error: DeviceError, now: float) -> None:
        """A call of the link failed."""
        self._now = now
        if error.reason == "refused":
            self._refused = error
        else:
            self._link_error = error

    def connected(self, now: float) -> None:
        """The link (re)connected."""
        self._now = now
        self._link_error = None
        self._stamp = None                   # a restarted device's clock may begin anew

    def wrote(self, now: float) -> None:
        """A write was taken."""
        self._now = now
        self._refused = None

    def read(self, reading: Reading, now: float) -> None:
        """A reading came."""
        self._now = now
        self._link_error = None
        self.reading = reading
        if reading.stamp is not None and (self._stamp is None
                                          or reading.stamp != self._stamp[0]):
            self._stamp = (reading.stamp, now)

    def status(self, now: float | None = None) -> DeviceStatus:
        """The device's status (at ``now``, default the last event's time)."""
        now = self._now if now is None else now
        reading = self.reading
        p, q = (None, None) if reading is None else (reading.p_w, reading.q_var)
        for error in (self._link_error, self._refused):
            if error is not None:
                return DeviceStatus(False, error.reason, error.detail, p, q)
        if self._stamp is not None and now - self._stamp[1] > self.stale_after_s:
            return DeviceStatus(False, "stale", f"its measurement's time stamp stayed at "
                                f"{self._stamp[0]:g} s for {now - self._stamp[1]:.3g} s", p, q)
        if reading is not None and not reading.connected:
            return DeviceStatus(False, "disconnected", "the plant says it is not connected "
                                "to the grid", p, q)
        return DeviceStatus(True, None, "", p, q)


class Gateway:
    """A DER's plant device behind ``link`` (see the module docstring; thread-safe).

    Parameters
    ----------
    link : DeviceLink
    poll_period_s : float
        How often the measurement is read, s.
    stale_after_s : float
        See :class:`DeviceHealth`, s.
    retry_s : float
        How often a failed connection or refused write is tried again, s.
    write_interval_s : float
        Shortest time between two writes, s (0: each new pair at once).
    deadband : (float, float)
        A pair within ``(W, var)`` of the pair last written is not written.
    clock : callable
        Monotonic seconds (tests give their own).
    """

    def __init__(self, link: DeviceLink, poll_period_s: float, stale_after_s: float,
                 retry_s: float, write_interval_s: float = 0.0,
                 deadband: tuple[float, float] = (0.0, 0.0),
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.link = link
        self.poll_period_s = poll_period_s
        self.retry_s = retry_s
        self.write_interval_s = write_interval_s
        self.deadband = deadband
        self._clock = clock
        self._health = DeviceHealth(stale_after_s)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._pending: tuple[float, float | None] | None = None
        self._latest: tuple[float, float | None] | None = None
        self._written: tuple[float, float | None] | None = None
        self._stop = False
        self._first = threading.Event()
        self._starting_until = 0.0
        self._thread: threading.Thread | None = None
        self.counts = {"device_writes": 0, "device_reads": 0, "device_errors": 0,
                       "device_within_deadband": 0}
        self._write_s: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self._read_s: deque[float] = deque(maxlen=LATENCIES_KEPT)

    # -- PlantDevice ---------------------------------------------------------------------------

    def command(self, p_w: float, q_var: float | None) -> None:
        with self._lock:
            self._latest = (p_w, q_var)
            if self._within_deadband(p_w, q_var):
                self._pending = None
                self.counts["device_within_deadband"] += 1
                return
            self._pending = self._latest
            self._wake.notify()

    def _within_deadband(self, p_w: float, q_var: float | None) -> bool:
        """The pair differs from the one last written by no more than the dead band."""
        if self._written is None:
            return False
        p_last, q_last = self._written
        if abs(p_w - p_last) > self.deadband[0]:
            return False
        if q_var is None or q_last is None:
            return q_var is None and q_last is None
        return abs(q_var - q_last) <= self.deadband[1]

    def status(self) -> DeviceStatus:
        with self._lock:
            return self._health.status(self._clock())

    def stats(self) -> dict[str, float]:
        with self._lock:
            out = {k: float(v) for k, v in self.counts.items()}
            for name, values in (("write", self._write_s), ("read", self._read_s)):
                if values:
                    ordered = sorted(values)
                    for q in (50, 99):
                        at = min(len(ordered) - 1, int(q / 100 * len(ordered)))
                        out[f"device_{name}_p{q}_ms"] = ordered[at] * 1e3
            return out

    # -- the thread ----------------------------------------------------------------------------

    def start(self, first_within_s: float | None = None) -> None:
        """Start the thread; with ``first_within_s``, return once the first connection and
        read were done, or that long has passed (a device slow to answer while a whole run
        starts is tried again at once within it, not after ``retry_s``)."""
        if first_within_s is not None:
            self._starting_until = self._clock() + first_within_s
        self._thread = threading.Thread(target=self._run, name="adnmesh-gateway", daemon=True)
        self._thread.start()
        if first_within_s is not None:
            self._first.wait(first_within_s)

    def stop(self) -> None:
        """End the thread (after at most one call of the link) and close the link."""
        with self._lock:
            self._stop = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join()
        self.link.close()

    def _run(self) -> None:
        up, retry_at, next_read, next_write = False, 0.0, 0.0, 0.0
        while True:
            with self._lock:
                if self._stop:
                    return
                now = self._clock()
                write_at = max(retry_at, next_write)
                if not up:
                    wake = retry_at
                elif self._pending is not None:
                    wake = min(next_read, write_at)
                else:
                    wake = next_read
                if wake > now:
                    self._wake.wait(wake - now)
                    continue
                write = self._pending if up and now >= write_at else None
                if write is not None:
                    self._pending = None
            if not up:
                up = self._attempt(self.link.connect, None) is not None
                with self._lock:
                    if up:
                        self._health.connected(self._clock())
                        self._pending, retry_at, next_read = self._latest, 0.0, 0.0
                        self._written = None    # a restarted device has lost its set-points
                    else:
                        retry_at = self._retry_at()
                continue
            if write is not None:
                done = self._attempt(self.link.write, self._write_s, *write)
                with self._lock:
                    if done is None:
                        self._pending = self._pending or self._latest
                        retry_at = self._retry_at()
                    else:
                        self.counts["device_writes"] += 1
                        self._written = write
                        next_write = self._clock() + self.write_interval_s
                        self._health.wrote(self._clock())
            if self._clock() >= next_read and self._health.link_up:
                reading = self._attempt(self.link.read, self._read_s)
                with self._lock:
                    if reading is not None:
                        self.counts["device_reads"] += 1
                        self._health.read(reading[0], self._clock())
                        self._first.set()
                    next_read = max(next_read + self.poll_period_s, self._clock())
            with self._lock:
                up = self._health.link_up
                if not up:
                    retry_at = self._retry_at()

    def _retry_at(self) -> float:
        """When to try the device again after a failure (lock held), s: at once while the
        gateway starts, else ``retry_s`` from now."""
        now = self._clock()
        if not self._first.is_set() and now + _START_RETRY_S < self._starting_until:
            return now + _START_RETRY_S
        self._first.set()
        return now + self.retry_s

    def _attempt(self, call, durations: deque | None, *args) -> tuple | None:
        """``(result,)`` of a call of the link, or None if it failed (the health told)."""
        began = self._clock()
        try:
            result = call(*args)
        except DeviceError as exc:
            with self._lock:
                self.counts["device_errors"] += 1
                self._health.failed(exc, self._clock())
            if exc.reason in _RECONNECT:
                self.link.close()
            return None
        if durations is not None:
            took = self._clock() - began
            with self._lock:
                durations.append(took)
        return (result,)
