"""What a DER's local controller needs of a plant device (bus-free).

A DER whose plant is a device (the config's ``plant:``, docs/devices.md) does not run its model:
its controller hands each new set-point to a :class:`PlantDevice` and takes the infeed from the
device's latest :class:`DeviceStatus`. The gateway (:mod:`adnmesh.devices.gateway`) implements
it around a protocol link on a thread of its own; tests give a fake. A device that is not
healthy makes its DER unavailable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

__all__ = ["DeviceStatus", "PlantDevice"]


@dataclass(frozen=True, slots=True)
class DeviceStatus:
    """The device as the gateway last saw it.

    Attributes
    ----------
    ok : bool
        Healthy: reachable, answering, taking set-points, measuring, connected to the grid.
    reason : str or None
        Why not (``unreachable``, ``timeout``, ``refused``, ``stale``, ``malformed``,
        ``disconnected``), None when ok.
    detail : str
        One line on the reason ("" when ok).
    p_w : float or None
        The last measured active power, W (None: never read).
    q_var : float or None
        The last measured reactive power, var (None: never read or not read).
    held : int or None
        Whether the plant is held at a limit, as it says itself: +1 upwards, -1 downwards, 0
        not (None: it cannot say, as no device protocol here can; the DER's model tells).
    """

    ok: bool
    reason: str | None
    detail: str
    p_w: float | None
    q_var: float | None
    held: int | None = None


class PlantDevice(Protocol):
    """A DER's plant device, as its controller uses it (see the module docstring)."""

    def command(self, p_w: float, q_var: float | None) -> None:
        """New set-points, W and var (None: no reactive control); never blocks."""

    def status(self) -> DeviceStatus:
        """The latest status; never blocks."""

    def stats(self) -> dict[str, float]:
        """Counts and latencies for the agent's goodbye."""
