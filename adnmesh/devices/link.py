"""What the DER agent's gateway needs of a connection to its plant device.

A :class:`DeviceLink` is one device behind one protocol: it connects, writes the active (and
reactive) power set-point and reads the measured infeed back. Every call blocks for at most the
link's timeout and raises :class:`DeviceError` with a reason the gateway tells apart (all of
:data:`REASONS` but ``stale``, which the gateway finds from the readings' time stamps):

``unreachable``
    no connection (refused, reset, no route, closed by the device);
``timeout``
    connected, but the device did not answer within the timeout;
``refused``
    the device answered a write with an error (a Modbus exception, a negative 104
    confirmation);
``stale``
    (the gateway's) the device answers, but its measurement's time stamp stopped advancing
    (SunSpec model 122's ``Tms``, a 104 measurement's CP56Time2a);
``malformed``
    the device answered something that is not the expected model or point (a wrong SunSpec
    map, a value out of its type's range).

Links hold no adnmesh state; the gateway (:mod:`adnmesh.devices.gateway`) decides what an
error means for the DER.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

__all__ = ["DeviceError", "DeviceLink", "Reading", "REASONS"]

Reason = Literal["unreachable", "timeout", "refused", "stale", "malformed"]
REASONS: tuple[str, ...] = ("unreachable", "timeout", "refused", "stale", "malformed")


class DeviceError(Exception):
    """A device call failed; ``reason`` is one of :data:`REASONS`, ``detail`` one line."""

    def __init__(self, reason: Reason, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, slots=True)
class Reading:
    """What a device measured.

    Attributes
    ----------
    p_w : float
        Active power infeed, W (generator convention).
    q_var : float or None
        Reactive power, var (generator convention: > 0 injects), None if not read.
    connected : bool
        The device says it is connected to the grid and operating (SunSpec ``ConnSt``, a 104
        status point); False makes the DER unavailable.
    stamp : float or None
        The device's time stamp of the measurement, s in its own clock (for staleness: it
        must advance), None if the protocol gives none.
    """

    p_w: float
    q_var: float | None
    connected: bool
    stamp: float | None = None


class DeviceLink(Protocol):
    """One device behind one protocol (see the module docstring). Not thread-safe: one
    gateway thread uses it."""

    def connect(self) -> None:
        """Open the connection (again after an error). Raises :class:`DeviceError`."""

    def write(self, p_w: float, q_var: float | None) -> None:
        """Write the active power set-point, W, and, if not None, the reactive one, var.
        Raises :class:`DeviceError`."""

    def read(self) -> Reading:
        """Read the measured infeed. Raises :class:`DeviceError`."""

    def close(self) -> None:
        """Close the connection (never raises)."""
