"""SunSpec over Modbus TCP (:mod:`adnmesh.devices.sunspec`): the device simulator's server and
the gateway's link against each other on 127.0.0.1, with the reference case's 2 MW WT run on a
clock the tests move (exact values) — set-points, measurement, status, faults, restarts, maps
that are not the expected one, TLS, and no thread left behind."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from contextlib import contextmanager

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from sunspec2.device import Model

from adnmesh.devices.link import DeviceError
from adnmesh.devices.realtime_plant import RealtimePlant
from adnmesh.devices.sunspec import BASE_ADDRESS, SunSpecLink, SunSpecPoints, SunSpecServer
from adnmesh.runtime.certificates import issue
from adnmesh.runtime.identity import cert_files

TIMEOUT_S = 0.3
"""The links' timeout, s."""


class FakeClock:
    """A wall clock that moves only when told, ns."""

    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns

    def advance(self, s: float) -> None:
        self.ns += round(s * 1e9)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def plant(simbench_config, clock) -> RealtimePlant:
    """SGen1, the 2 MW WT, on the fake clock."""
    return RealtimePlant(simbench_config.ders[0], simbench_config, clock_ns=clock)


@pytest.fixture
def server(plant):
    with SunSpecServer(plant) as server:
        yield server


@pytest.fixture
def link(server):
    link = SunSpecLink("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
    link.connect()
    yield link
    link.close()


def reason_of(call) -> str:
    """The reason of the DeviceError ``call()`` raises."""
    with pytest.raises(DeviceError) as raised:
        call()
    return raised.value.reason


def half_step(server: SunSpecServer, sf_point: str) -> float:
    """Half the resolution of a served scale factor, W or var."""
    return 10.0 ** server.scale_factors[sf_point] / 2


# --- set-points and measurement ----------------------------------------------------------------


def test_set_points_reach_the_plant(server, link, plant) -> None:
    link.write(1_234_567.891, -150_000.004)
    assert plant.p_setpoint_w == pytest.approx(1_234_567.891, abs=half_step(server, "704.WSet_SF"))
    assert plant.q_setpoint_var == pytest.approx(-150_000.004,
                                                 abs=half_step(server, "704.VarSet_SF"))
    link.write(800_000.0, None)                           # P only: Q stays
    assert plant.p_setpoint_w == 800_000.0 and plant.q_setpoint_var == -150_000.0
    with pytest.raises(DeviceError, match="malformed: 704.WSet: 1e.10 does not fit"):
        link.write(1e10, None)                            # beyond int32 at 10 mW steps


def test_the_measurement_is_the_plants_at_the_time_of_the_read(server, link, plant,
                                                               clock) -> None:
    link.write(1_500_000.0, 300_000.0)
    for dt_s in (0.05, 0.2, 0.4, 3.0):                    # along the step response
        clock.advance(dt_s)
        reading = link.read()
        p_w, q_var, t_s = plant.read()
        assert reading.p_w == pytest.approx(p_w, abs=half_step(server, "701.W_SF"))
        assert reading.q_var == pytest.approx(q_var, abs=half_step(server, "701.Var_SF"))
        assert reading.stamp == int(t_s) and reading.connected
    assert reading.p_w == 1_500_000.0 and reading.q_var == 300_000.0


def test_the_scale_factors_fit_the_ratings(server) -> None:
    # int16 W at 100 W steps holds 2 MW; int32 WSet at 10 mW steps
    assert server.scale_factors["701.W_SF"] == 2 and server.scale_factors["704.WSet_SF"] == -2


def test_a_disconnected_plant_says_so(server, link) -> None:
    assert link.read().connected
    server.faults.disconnected = True
    assert not link.read().connected
    server.faults.disconnected = False
    assert link.read().connected


def test_the_stamp_advances_and_stops_with_a_frozen_measurement(server, link, plant,
                                                                clock) -> None:
    clock.advance(2.5)
    assert link.read().stamp == 2
    link.write(500_000.0, None)
    clock.advance(0.1)
    before = link.read()
    server.faults.frozen = True
    clock.advance(5.0)
    frozen = link.read()
    assert frozen == before and frozen.stamp == 2
    assert plant.read()[2] > 7.5 and abs(plant.read()[0] - frozen.p_w) > 1e4
    server.faults.frozen = False
    assert link.read().stamp == 7


def test_a_link_without_a_stamp_point_reads_none(server) -> None:
    link = SunSpecLink("127.0.0.1", server.port, timeout_s=TIMEOUT_S,
                       points=SunSpecPoints(stamp=None))
    link.connect()
    assert link.read().stamp is None
    link.close()


# --- faults ------------------------------------------------------------------------------------


def test_refused_writes_take_nothing_and_keep_the_connection(server, link, plant) -> None:
    server.faults.refuse_writes = True
    assert reason_of(lambda: link.write(300_000.0, 100_000.0)) == "refused"
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (1_000_000.0, 0.0)
    assert link.read().connected
    server.faults.refuse_writes = False
    link.write(300_000.0, None)
    assert plant.p_setpoint_w == 300_000.0


@pytest.mark.parametrize("call", ["connect", "write", "read"])
def test_a_silent_device_times_out_within_the_timeout(server, link, call) -> None:
    server.faults.silent = True
    start = time.monotonic()
    assert reason_of({"connect": link.connect, "write": lambda: link.write(500_000.0, 0.0),
                      "read": link.read}[call]) == "timeout"
    assert 0.9 * TIMEOUT_S < time.monotonic() - start < TIMEOUT_S + 0.2
    server.faults.silent = False
    link.connect()
    assert link.read().connected


def test_a_stopped_device_is_unreachable_and_a_restarted_one_serves_again(server, link,
                                                                           plant) -> None:
    link.write(700_000.0, None)
    port = server.port
    server.stop()
    assert reason_of(link.read) == "unreachable"
    assert reason_of(link.connect) == "unreachable"
    server.start()
    assert server.port == port
    link.connect()
    assert link.read().connected
    link.write(600_000.0, 50_000.0)
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (600_000.0, 50_000.0)


def test_a_link_must_connect_first(server) -> None:
    assert reason_of(SunSpecLink("127.0.0.1", server.port).read) == "unreachable"


def test_a_server_on_a_busy_port_says_why(plant) -> None:
    with socket.create_server(("127.0.0.1", 0)) as busy:
        with pytest.raises(OSError, match="in use"):
            SunSpecServer(plant, port=busy.getsockname()[1]).start()


# --- the 704 semantics, by a plain Modbus client -----------------------------------------------


def test_disabling_a_function_releases_it_and_only_the_absolute_modes_are_taken(
        server, link, plant) -> None:
    controls = Model(704)

    def address(name: str) -> int:
        return link.model_addresses[704] + controls.points[name].offset

    link.write(400_000.0, 100_000.0)
    client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=TIMEOUT_S, retries=0)
    client.connect()
    try:
        assert not client.write_register(address("WSetEna"), 0).isError()
        assert not client.write_register(address("VarSetEna"), 0).isError()
        assert (plant.p_setpoint_w, plant.q_setpoint_var) == (plant.p_avail_w, 0.0)
        refused = client.write_register(address("WSetMod"), 0)           # W_MAX_PCT
        assert refused.isError() and refused.exception_code == ExcCodes.ILLEGAL_VALUE
        measured = link.model_addresses[701] + Model(701).points["W"].offset
        refused = client.write_register(measured, 0)
        assert refused.isError() and refused.exception_code == ExcCodes.ILLEGAL_ADDRESS
    finally:
        client.close()
    link.connect()                                       # enables again: WSet, VarSet count
    assert (plant.p_setpoint_w, plant.q_setpoint_var) == (400_000.0, 100_000.0)


# --- maps that are not the expected one --------------------------------------------------------


def test_a_map_without_model_704_is_malformed(plant) -> None:
    with SunSpecServer(plant, models=(1, 701, 702, 122)) as server:
        link = SunSpecLink("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
        with pytest.raises(DeviceError, match="malformed: no SunSpec model 704"):
            link.connect()


@contextmanager
def modbus_device(address: int, registers: list[int]):
    """A plain Modbus TCP device (no SunSpec server) with ``registers`` from ``address``;
    yields its port."""
    listening, where = threading.Event(), {}

    async def serve() -> None:
        device = SimDevice(1, simdata=SimData(address, values=registers,
                                              datatype=DataType.REGISTERS))
        server = ModbusTcpServer(device, address=("127.0.0.1", 0))
        await server.serve_forever(background=True)
        where.update(port=server.transport.sockets[0].getsockname()[1],
                     loop=asyncio.get_running_loop(), stop=asyncio.Event())
        listening.set()
        await where["stop"].wait()
        await server.shutdown()

    thread = threading.Thread(target=asyncio.run, args=(serve(),))
    thread.start()
    assert listening.wait(5)
    try:
        yield where["port"]
    finally:
        where["loop"].call_soon_threadsafe(where["stop"].set)
        thread.join(5)


@pytest.mark.parametrize("address, registers, detail", [
    (BASE_ADDRESS, [0x1234, 0x5678, 1, 66], "no SunSpec marker"),
    (0, [0x5375, 0x6E53, 1, 66], "ExceptionResponse"),                # nothing at 40000
    (BASE_ADDRESS, [0x5375, 0x6E53, 1, 65000], "leaves the address space"),
])
def test_a_device_without_the_sunspec_map_is_malformed(address, registers, detail) -> None:
    with modbus_device(address, registers) as port:
        link = SunSpecLink("127.0.0.1", port, timeout_s=TIMEOUT_S)
        with pytest.raises(DeviceError, match="malformed") as raised:
            link.connect()
        assert detail in raised.value.detail


@pytest.mark.parametrize("field, text, problem", [
    ("p_set", "704.WSett", "model 704 has no point 'WSett'"),
    ("p_set", "WSet", "not 'model.point'"),
    ("q_set", "999.VarSet", "no SunSpec model 999"),
    ("p_set", "701.W", "not writable"),
    ("p_set", "704.VarSet", "not an integer point in W"),
    ("p_meas", "701.ConnSt", "not an integer point in W"),
    ("status", "701.W", "not an enum16 point with a CONNECTED value"),
    ("stamp", "701.W", "not an integer point in Secs"),
])
def test_bad_points_are_named(field, text, problem) -> None:
    with pytest.raises(ValueError, match=f"^SunSpecPoints.{field} '{text}': {problem}$"):
        SunSpecPoints(**{field: text})


# --- TLS ---------------------------------------------------------------------------------------


def test_tls_links_work_and_others_do_not(plant, tmp_path) -> None:
    issue(tmp_path / "certs", ["der/SGen1"], hosts=["127.0.0.1", "localhost"])
    issue(tmp_path / "other", ["der/SGen1"], hosts=["localhost"])
    ours, other = cert_files(tmp_path / "certs", "der/SGen1"), \
        cert_files(tmp_path / "other", "der/SGen1")

    def tls_link(server, host, ca):
        return SunSpecLink(host, server.port, timeout_s=TIMEOUT_S,
                           tls=None if ca is None else (str(ca), None, None))

    with SunSpecServer(plant, tls=(str(ours.cert), str(ours.key))) as server:
        link = tls_link(server, "127.0.0.1", ours.ca)
        link.connect()
        link.write(900_000.0, 20_000.0)
        assert (plant.p_setpoint_w, plant.q_setpoint_var) == (900_000.0, 20_000.0)
        assert link.read().p_w == 1_000_000.0
        for stranger in (tls_link(server, "127.0.0.1", None),        # no TLS
                         tls_link(server, "127.0.0.1", other.ca)):   # another CA
            assert reason_of(stranger.connect) == "unreachable"
        server.stop()
        assert reason_of(link.read) == "unreachable"
    with SunSpecServer(plant, tls=(str(other.cert), str(other.key))) as server:
        assert reason_of(tls_link(server, "127.0.0.1", other.ca).connect) == "unreachable"
        link = tls_link(server, "localhost", other.ca)         # the name the certificate has
        link.connect()
        link.close()


# --- threads -----------------------------------------------------------------------------------


def test_no_thread_is_left_after_stop(plant) -> None:
    before = threading.active_count()
    server = SunSpecServer(plant)
    for _ in range(2):                                   # a start, a restart
        server.start()
        link = SunSpecLink("127.0.0.1", server.port, timeout_s=TIMEOUT_S)
        link.connect()
        link.read()
        link.close()
        server.stop()
    deadline = time.monotonic() + 2.0
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert threading.active_count() == before
