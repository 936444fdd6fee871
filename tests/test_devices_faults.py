"""Each gateway against its device simulator (real servers and clients on 127.0.0.1): the
set-point written, the measurement read, and every fault a field link has told apart by the
gateway's status — and gone when the device is well again."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from adnmesh.config import Config, load_config
from adnmesh.devices.faults import DeviceFaults
from adnmesh.devices.gateway import Gateway
from adnmesh.devices.realtime_plant import RealtimePlant

STALE_AFTER_S = {"sunspec": 1.5, "iec104": 0.5}   # SunSpec's Tms counts whole seconds


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    return load_config(configs_dir / "simbench.yaml")


def devices(protocol: str, plant, faults):
    if protocol == "sunspec":
        from adnmesh.devices.sunspec import SunSpecLink, SunSpecServer
        server = SunSpecServer(plant, faults=faults)
        return server, lambda: SunSpecLink("127.0.0.1", server.port, timeout_s=0.2)
    from adnmesh.devices.iec104 import IEC104Link, IEC104Server
    server = IEC104Server(plant, faults=faults)
    return server, lambda: IEC104Link("127.0.0.1", server.port, timeout_s=0.2)


def until(gateway: Gateway, wanted, timeout_s: float = 10.0):
    """The gateway's status once ``wanted(status)`` holds (polled, bounded)."""
    deadline = time.monotonic() + timeout_s
    while True:
        status = gateway.status()
        if wanted(status) or time.monotonic() > deadline:
            return status
        time.sleep(0.01)


@pytest.mark.parametrize("protocol", ["sunspec", "iec104"])
def test_the_gateway_tells_every_fault_of_its_device_and_its_end(config: Config,
                                                                 protocol: str) -> None:
    der = config.ders[0]                                   # SGen1, a 2 MW WT
    plant, faults = RealtimePlant(der, config), DeviceFaults()
    server, link = devices(protocol, plant, faults)
    server.start()
    gateway = Gateway(link(), poll_period_s=0.02, stale_after_s=STALE_AFTER_S[protocol],
                      retry_s=0.1)
    try:
        gateway.command(1.5e6, 2e4)
        gateway.start(first_within_s=5.0)
        healthy = until(gateway, lambda s: s.ok and plant.p_setpoint_w == 1.5e6)
        assert healthy.ok and plant.q_setpoint_var == 2e4
        p_w, q_var, _ = plant.read()
        status = until(gateway, lambda s: s.p_w is not None and abs(s.p_w - p_w) < 200)
        assert abs(status.p_w - p_w) < 200 and abs(status.q_var - q_var) < 200

        for switch, reason in (("refuse_writes", "refused"), ("silent", "timeout"),
                               ("disconnected", "disconnected"), ("frozen", "stale")):
            setattr(faults, switch, True)
            if switch == "refuse_writes":
                gateway.command(1.2e6, 0.0)                # a write to refuse
            lost = until(gateway, lambda s, r=reason: s.reason == r)
            assert lost.reason == reason and not lost.ok, (switch, lost)
            if switch == "refuse_writes":
                assert plant.p_setpoint_w == 1.5e6         # not taken
            setattr(faults, switch, False)
            back = until(gateway, lambda s: s.ok)
            assert back.ok, (switch, back)
        assert plant.p_setpoint_w == 1.2e6                 # written once it was taken again

        server.stop()                                      # the device restarts
        down = until(gateway, lambda s: s.reason == "unreachable")
        assert down.reason == "unreachable", down
        server.start()
        assert until(gateway, lambda s: s.ok).ok
    finally:
        gateway.stop()
        server.stop()
    stats = gateway.stats()
    assert stats["device_errors"] >= 3 and stats["device_reads"] > 10    # refused, silent, down
