"""The agents' logic as bus-free state machines (see :mod:`adnmesh.control.base`).

- :class:`~adnmesh.control.cpfc.CPFC`: gain-scheduled PI control of ``P_IP``;
- :class:`~adnmesh.control.der.DERController`: a DER's local controller and dynamics;
- :class:`~adnmesh.control.measurement.Measurement`: ``P_IP`` at the interconnection point;
- :class:`~adnmesh.control.availability.AvailabilityMonitor`: heartbeats to SI.

:func:`build_agent` makes the state machine of an agent id.
"""

from __future__ import annotations

from adnmesh.config import Config

__all__ = ["build_agent"]


def build_agent(agent_id: str, config: Config, schedule=None):
    """The state machine of ``agent_id`` (``cpfc``, ``measurement``, ``availability``,
    ``der/<id>``) for ``config``; the CPFC needs a
    :class:`~adnmesh.control.cpfc.GainSchedule`.

    Raises
    ------
    ValueError
        Unknown agent id, or the CPFC without a schedule.
    """
    if agent_id == "cpfc":
        from adnmesh.control.cpfc import CPFC
        if schedule is None:
            raise ValueError("the CPFC needs a gain schedule")
        return CPFC(config, schedule)
    if agent_id == "measurement":
        from adnmesh.control.measurement import Measurement
        return Measurement(config)
    if agent_id == "availability":
        from adnmesh.control.availability import AvailabilityMonitor
        return AvailabilityMonitor(config)
    if agent_id.startswith("der/"):
        from adnmesh.control.der import DERController
        (der,) = config.ders_by_id([agent_id[4:]])
        return DERController(der, config)
    raise ValueError(f"unknown agent id {agent_id!r}")
