"""The one place that makes an agent state machine from an agent id.

The sim layer, the agent processes and the tests build agents through :func:`build_agent`, so
which class runs as which agent is decided once. Each kind's module is imported when an agent
of that kind is built: a DER process loads neither the CPFC's gain tables nor the measurement's
grid solver.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from adnmesh.config import Config
from adnmesh.names import der_id_of

if TYPE_CHECKING:
    from adnmesh.control.base import Agent
    from adnmesh.control.cpfc_controller import GainSchedule

__all__ = ["build_agent"]

def build_agent(agent_id: str, config: Config, schedule: GainSchedule | None = None,
                p_avail_w: float | None = None, der_params=None,
                q_schedule: GainSchedule | None = None, device=None, model_watch=None) -> Agent:
    """The state machine of ``agent_id`` for ``config``; the CPFC needs its gain schedule (with
    reactive power control it runs a Q loop too, :mod:`adnmesh.control.cpfc_pair`, with
    ``q_schedule``, default the Q gains tuned on demand), a DER
    can be given its available power, W (default: :func:`adnmesh.control.operating_point.
    available_power_w`), and its model parameters (default: from the config,
    :func:`adnmesh.control.der_model.der_params`) and its plant device
    (:class:`~adnmesh.control.plant_device.PlantDevice`; default: its model runs in the agent).
    The CPFC's P loop takes ``model_watch`` (:class:`adnmesh.results.model_watch.ModelWatch`,
    for ``runtime.model_watch``; default none).

    Raises
    ------
    ValueError
        Unknown agent id, or the CPFC without a schedule.
    """
    if agent_id == "cpfc":
        if schedule is None:
            raise ValueError("the CPFC needs a gain schedule")
        from adnmesh.control.cpfc_controller import CPFC
        from adnmesh.control.operating_point import reachable_ranges
        ranges = reachable_ranges(config)
        found = not isinstance(ranges, str)
        note = "" if found or "could not" not in ranges else \
            f"references are not clipped: {ranges}"
        p_cpfc = CPFC(config, schedule, reachable=ranges[0] if found else None,
                      reachable_note=note, model_watch=model_watch)
        if config.reactive is None:
            return p_cpfc
        from adnmesh.control.cpfc_pair import CPFCPair, reactive_cpfc
        return CPFCPair(p_cpfc, reactive_cpfc(config, q_schedule,
                                              reachable=ranges[1] if found else None))
    if agent_id == "measurement":
        from adnmesh.control.measurement_point import Measurement
        return Measurement(config)
    if agent_id == "availability":
        from adnmesh.control.availability_monitor import AvailabilityMonitor
        return AvailabilityMonitor(config)
    der_id = der_id_of(agent_id)
    if der_id is not None and der_id in config.der_ids():
        from adnmesh.control.der_controller import DERController
        (der,) = config.ders_by_id([der_id])
        if p_avail_w is None:
            from adnmesh.control.operating_point import available_power_w
            p_avail_w = available_power_w(config)[der_id]
        return DERController(der, config, p_avail_w, der_params, device=device)
    raise ValueError(f"unknown agent id {agent_id!r}")
