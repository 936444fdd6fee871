"""IEC 104 device simulator and link (adnmesh.devices.iec104): a real c104 server and client on
127.0.0.1, the reference case's 2 MW WT behind them."""

from __future__ import annotations

import os
import socket
import time

import numpy as np
import pytest

from adnmesh.devices.faults import DeviceFaults
from adnmesh.devices.iec104 import IEC104Link, IEC104Points, IEC104Server
from adnmesh.devices.link import DeviceError
from adnmesh.devices.realtime_plant import RealtimePlant

TIMEOUT_S = 0.5


def _native_threads() -> int:
    """Threads of this process, c104's native ones included."""
    return len(os.listdir("/proc/self/task"))


def _f32(value: float) -> float:
    """``value`` as a short float (IEC 104's R32) carries it."""
    return float(np.float32(value))


@pytest.fixture
def plant(simbench_config):
    return RealtimePlant(simbench_config.ders[0], simbench_config)


@pytest.fixture
def faults():
    return DeviceFaults()


@pytest.fixture
def server(plant, faults):
    with IEC104Server(plant, faults=faults) as server:
        yield server


@pytest.fixture
def link(server):
    link = IEC104Link("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
    link.connect()
    yield link
    link.close()


def _reason(call, *args) -> str:
    with pytest.raises(DeviceError) as caught:
        call(*args)
    return caught.value.reason


@pytest.mark.parametrize("kwargs, words", [
    ({"common_address": 0}, "common address 0"),
    ({"common_address": 65535}, "common address 65535"),
    ({"p_set": 0}, "p_set address 0"),
    ({"status": 16_777_216}, "status address 16777216"),
    ({"q_meas": 200}, "not distinct"),
])
def test_bad_points_are_refused_in_one_line(kwargs, words):
    with pytest.raises(ValueError, match=words) as caught:
        IEC104Points(**kwargs)
    assert "\n" not in str(caught.value)


def test_tls_is_refused(plant):
    with pytest.raises(ValueError, match="TLS"):
        IEC104Link("127.0.0.1", 2404, tls=("ca.pem", "der.pem", "der.key"))
    with pytest.raises(ValueError, match="TLS"):
        IEC104Server(plant, tls=("rtu.pem", "rtu.key"))


def test_set_points_reach_the_plant(link, plant):
    link.write(1.5e6, 2e5)
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (1.5e6, 2e5)
    link.write(1.25e6, None)
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (1.25e6, 2e5)


def test_reading_is_the_model_at_its_time(simbench_config):
    now_ns = [0]
    plant = RealtimePlant(simbench_config.ders[0], simbench_config, clock_ns=lambda: now_ns[0])
    with IEC104Server(plant) as server:
        link = IEC104Link("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
        link.connect()
        try:
            link.write(1.5e6, 1e5)
            now_ns[0] = 50_000_000                 # 50 ms into the WT's and Q's transients
            reading = link.read()
            p_w, q_var, _ = plant.read()
        finally:
            link.close()
    assert 1e6 < p_w < 1.5e6 and 0 < q_var < 1e5
    assert (reading.p_w, reading.q_var) == (_f32(p_w), _f32(q_var))
    assert reading.connected
    assert abs(reading.stamp - time.time()) < 1.0   # the RTU's wall clock, s since the epoch


def test_status_says_disconnected(link, faults):
    assert link.read().connected
    faults.disconnected = True
    assert not link.read().connected
    faults.disconnected = False
    assert link.read().connected


def test_refused_write_leaves_the_set_point(link, plant, faults):
    faults.refuse_writes = True
    assert _reason(link.write, 1.5e6, 2e5) == "refused"
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (1e6, 0.0)
    faults.refuse_writes = False
    link.write(1.5e6, None)                    # a refusal keeps the connection
    assert plant.p_setpoint_w == 1.5e6


def test_non_finite_set_point_is_refused(link, plant):
    assert _reason(link.write, float("nan"), None) == "refused"
    assert plant.p_setpoint_w == 1e6


def _times_out(call, *args) -> None:
    started = time.monotonic()
    assert _reason(call, *args) == "timeout"
    assert TIMEOUT_S <= time.monotonic() - started < TIMEOUT_S + 0.5


def test_silent_device_times_out(link, plant, faults):
    faults.silent = True
    _times_out(link.write, 1.5e6, None)
    assert plant.p_setpoint_w == 1e6              # a silent device takes nothing
    _times_out(link.connect)                      # connected, but the interrogation times out
    faults.silent = False
    link.connect()
    faults.silent = True
    _times_out(link.read)
    faults.silent = False
    link.connect()
    assert link.read().connected


def test_stopped_server_is_unreachable_and_its_port_closed(link, server):
    server.stop()
    assert _reason(link.read) == "unreachable"
    assert _reason(link.connect) == "unreachable"
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", server.port), timeout=TIMEOUT_S).close()


def test_link_reconnects_after_a_device_restart(link, server, plant):
    port = server.port
    server.stop()
    assert _reason(link.write, 1.5e6, None) == "unreachable"
    server.start()
    assert server.port == port
    link.connect()
    link.write(1.5e6, None)
    assert plant.p_setpoint_w == 1.5e6
    assert link.read().connected


def test_frozen_measurement_keeps_its_stamp(link, faults):
    first = link.read()
    deadline = time.monotonic() + 2.0
    while (advanced := link.read()).stamp == first.stamp:   # the time tag resolves 1 ms
        assert time.monotonic() < deadline, "the time tag does not advance"
    faults.frozen = True
    frozen = link.read()
    until = frozen.stamp + 0.02
    while time.time() < until:
        assert link.read() == frozen
    assert frozen.stamp == advanced.stamp
    faults.frozen = False
    deadline = time.monotonic() + 2.0
    while link.read().stamp == frozen.stamp:
        assert time.monotonic() < deadline, "the time tag does not advance after thawing"


def test_wrong_common_address_is_malformed(server):
    link = IEC104Link("127.0.0.1", server.port, IEC104Points(common_address=2), TIMEOUT_S)
    try:
        assert _reason(link.connect) == "malformed"
    finally:
        link.close()


def test_point_of_another_type_is_malformed(server):
    link = IEC104Link("127.0.0.1", server.port, IEC104Points(q_meas=300, status=201),
                      TIMEOUT_S)
    try:
        assert _reason(link.connect) == "malformed"
    finally:
        link.close()


def test_nothing_listening_is_unreachable():
    with socket.create_server(("127.0.0.1", 0)) as probe:
        port = probe.getsockname()[1]
    link = IEC104Link("127.0.0.1", port, timeout_s=TIMEOUT_S)
    started = time.monotonic()
    assert _reason(link.connect) == "unreachable"
    assert time.monotonic() - started < TIMEOUT_S + 0.5
    assert _reason(link.read) == "unreachable"
    link.close()
    link.close()


def test_unknown_host_is_unreachable():
    link = IEC104Link("no-such-host.invalid", 2404, timeout_s=TIMEOUT_S)
    assert _reason(link.connect) == "unreachable"


def test_busy_port_is_an_os_error(plant):
    with socket.create_server(("127.0.0.1", 0)) as busy:
        server = IEC104Server(plant, port=busy.getsockname()[1])
        with pytest.raises(OSError, match="cannot listen"):
            server.start()


def test_no_threads_left_after_stop(plant, faults):
    before = _native_threads()
    server = IEC104Server(plant, faults=faults)
    server.start()
    link = IEC104Link("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
    link.connect()
    link.read()
    faults.silent = True
    assert _reason(link.read) == "timeout"     # the server holds that request until stop
    link.close()
    server.stop()
    assert _native_threads() == before
