"""The faults a device simulator can play (``adnmesh device --fault``, tests): what field links
do to a gateway. Set from any thread; the protocol servers read them at each request."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DeviceFaults", "FAULT_KINDS"]

FAULT_KINDS = ("refuse_writes", "frozen", "silent", "disconnected", "down")
"""What :class:`DeviceFaults` can switch on (``down``: the server is stopped, unreachable)."""


@dataclass
class DeviceFaults:
    """Switches of a simulated device's faults (all off: a healthy device).

    Attributes
    ----------
    refuse_writes : bool
        Answer every set-point write with an error (a Modbus exception, a negative 104
        confirmation); the set-point is not taken.
    frozen : bool
        The measurement and its time stamp stop moving (a stale measurement).
    silent : bool
        Take requests and answer none (the gateway's calls time out).
    disconnected : bool
        The plant says it is not connected to the grid (SunSpec ``ConnSt`` 0, the 104 status
        point off).
    """

    refuse_writes: bool = False
    frozen: bool = False
    silent: bool = False
    disconnected: bool = False
