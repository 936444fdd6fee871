"""From a DER's ``plant:`` section to its link, its gateway and its simulator's server.

The config says which protocol, address, points and TLS files (paths relative to the config
file); this module builds the objects of :mod:`~adnmesh.devices.sunspec` and
:mod:`~adnmesh.devices.iec104` from it and turns what they refuse (a point the SunSpec models do
not have, a TLS file that is not there) into a one-line :class:`~adnmesh.errors.ConfigError`
naming the DER.
"""

from __future__ import annotations

import logging
from pathlib import Path

from adnmesh.config import DER, Config
from adnmesh.devices.gateway import Gateway
from adnmesh.errors import ConfigError

__all__ = ["gateway_for", "link_for", "server_for"]


def _quiet() -> None:
    """pymodbus logs every failed request with a frame dump on stderr: the gateway reports
    each fault itself (an event, one line), so only pymodbus's own breakdowns are left."""
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def _where(config: Config, der: DER) -> str:
    return f"{config.path}: ders[{config.der_ids().index(der.id)}].plant"


def _file(config: Config, der: DER, name: str | None, what: str) -> str | None:
    if name is None:
        return None
    path = Path(config.path).parent / name
    if not path.is_file():
        raise ConfigError(f"{_where(config, der)}.tls.{what}: no file {path}")
    return str(path)


def _points(config: Config, der: DER):
    plant = der.plant
    try:
        if plant.protocol == "sunspec":
            from adnmesh.devices.sunspec import SunSpecPoints
            return SunSpecPoints(**plant.points.model_dump())
        from adnmesh.devices.iec104 import IEC104Points
        return IEC104Points(common_address=plant.common_address, **plant.addresses.model_dump())
    except ValueError as exc:
        raise ConfigError(f"{_where(config, der)}: {exc}") from None


def link_for(der: DER, config: Config):
    """The protocol link to the device of ``der`` (not connected yet).

    Raises
    ------
    ConfigError
        A point or TLS file of the DER's ``plant:`` that cannot be used.
    """
    _quiet()
    plant, points = der.plant, _points(config, der)
    tls = None
    if plant.tls is not None:
        tls = (_file(config, der, plant.tls.ca, "ca"), _file(config, der, plant.tls.cert, "cert"),
               _file(config, der, plant.tls.key, "key"))
    try:
        if plant.protocol == "sunspec":
            from adnmesh.devices.sunspec import SunSpecLink
            return SunSpecLink(plant.host, plant.port, plant.unit_id, plant.timeout_s, points,
                               tls=tls)
        from adnmesh.devices.iec104 import IEC104Link
        return IEC104Link(plant.host, plant.port, points, plant.timeout_s, tls=tls)
    except ValueError as exc:
        raise ConfigError(f"{_where(config, der)}: {exc}") from None


def gateway_for(der: DER, config: Config) -> Gateway:
    """The gateway of ``der`` to its device (not started). Raises like :func:`link_for`."""
    plant = der.plant
    period = plant.poll_period_s or config.runtime.measurement_period_s
    band = plant.write_deadband_pct / 100 * der.p_inst_w
    return Gateway(link_for(der, config), period, plant.stale_after_s, plant.retry_s,
                   write_interval_s=plant.write_interval_s, deadband=(band, band))


def server_for(protocol: str, der: DER, config: Config, plant_model, host: str, port: int,
               faults):
    """The device simulator's server for ``der`` on ``host:port`` (not started): its points and
    TLS as the DER's ``plant:`` says if it speaks ``protocol``, else the defaults.

    Raises
    ------
    ConfigError
        As :func:`link_for`.
    """
    _quiet()
    plant = der.plant if der.plant is not None and der.plant.protocol == protocol else None
    tls = None
    if plant is not None and plant.tls is not None and plant.tls.server_cert is not None:
        tls = (_file(config, der, plant.tls.server_cert, "server_cert"),
               _file(config, der, plant.tls.server_key, "server_key"))
    try:
        if protocol == "sunspec":
            from adnmesh.devices.sunspec import SunSpecServer
            return SunSpecServer(plant_model, host, port, plant.unit_id if plant else 1,
                                 tls=tls, faults=faults)
        from adnmesh.devices.iec104 import IEC104Points, IEC104Server
        points = _points(config, der) if plant is not None else IEC104Points()
        return IEC104Server(plant_model, host, port, points, tls=tls, faults=faults)
    except ValueError as exc:
        raise ConfigError(f"{_where(config, der)}: {exc}") from None
