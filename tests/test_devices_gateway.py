"""The DER's gateway to a plant device: its health bookkeeping (pure), its thread against a
fake link, and the DER controller with a device (bus-free)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from payloads import message

from adnmesh.config import Config, load_config
from adnmesh.control.der_controller import DERController
from adnmesh.control.plant_device import DeviceStatus
from adnmesh.devices.gateway import DeviceHealth, Gateway
from adnmesh.dermodels.limits import held_at
from adnmesh.devices.link import DeviceError, Reading
from adnmesh.wire.keys import Keys

MS = 1_000_000


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    """Two WTs (SGen2 with a 0.5 MW schedule), a step at 1 s, SGen2 unavailable from 8 s."""
    return load_config(configs_dir / "examples" / "runtime-step.yaml")


# --- health ---------------------------------------------------------------------------------------


def test_health_tells_each_fault_and_its_end() -> None:
    health = DeviceHealth(stale_after_s=2.0)
    assert health.status(0.0).reason == "unreachable"              # not connected yet
    health.connected(0.0)
    health.read(Reading(1e6, 0.0, True, stamp=10.0), 0.1)
    assert health.status(0.1) == DeviceStatus(True, None, "", 1e6, 0.0)
    health.failed(DeviceError("refused", "exception 4"), 0.2)
    assert (health.status(0.2).reason, health.status(0.2).p_w) == ("refused", 1e6)
    health.wrote(0.3)
    assert health.status(0.3).ok
    health.read(Reading(1e6, 0.0, True, stamp=10.0), 1.5)            # the stamp stays ...
    assert health.status(2.0).ok                                     # ... 1.9 s: not yet
    assert health.status(2.2).reason == "stale"                     # 2.1 s since it moved
    health.read(Reading(1e6, 0.0, True, stamp=11.0), 2.3)
    assert health.status(2.3).ok
    health.read(Reading(0.0, 0.0, False, stamp=12.0), 2.4)
    assert health.status(2.4).reason == "disconnected"
    health.failed(DeviceError("timeout", "no answer in 0.5 s"), 2.5)
    assert not health.link_up and health.status(2.5).reason == "timeout"
    health.connected(3.0)                                            # a restarted device:
    health.read(Reading(2e5, None, True, stamp=0.0), 3.1)            # its clock begins anew
    assert health.status(3.1).ok and health.status(3.1).q_var is None


def test_a_device_without_time_stamps_is_never_stale() -> None:
    health = DeviceHealth(stale_after_s=1.0)
    health.connected(0.0)
    health.read(Reading(5.0, None, True), 0.0)
    assert health.status(100.0).ok


# --- the thread against a fake link -----------------------------------------------------------------


class FakeLink:
    """A device in memory: fails as told, records what it was asked."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.fail: dict[str, DeviceError] = {}
        self.written: list[tuple[float, float | None]] = []
        self.connects = self.reads = self.closes = 0
        self.changed = threading.Condition(self.lock)
        self.stamp = 0.0

    def _call(self, what: str) -> None:
        with self.lock:
            error = self.fail.get(what)
            self.changed.notify_all()
        if error is not None:
            raise error

    def connect(self) -> None:
        self._call("connect")
        with self.lock:
            self.connects += 1

    def write(self, p_w: float, q_var: float | None) -> None:
        self._call("write")
        with self.lock:
            self.written.append((p_w, q_var))
            self.changed.notify_all()

    def read(self) -> Reading:
        self._call("read")
        with self.lock:
            self.reads += 1
            self.stamp += 1.0
            self.changed.notify_all()
            return Reading(7e5, 1e4, True, stamp=self.stamp)

    def close(self) -> None:
        with self.lock:
            self.closes += 1

    def wait_for(self, predicate, timeout: float = 5.0) -> bool:
        with self.changed:
            return self.changed.wait_for(predicate, timeout)


def test_the_gateway_writes_at_once_reads_at_its_period_and_comes_back() -> None:
    link = FakeLink()
    gateway = Gateway(link, poll_period_s=0.01, stale_after_s=5.0, retry_s=0.01)
    gateway.command(1e6, None)                       # before the start: written on connect
    gateway.start(first_within_s=5.0)
    try:
        assert link.wait_for(lambda: link.written == [(1e6, None)] and link.reads >= 1)
        assert gateway.status() == DeviceStatus(True, None, "", 7e5, 1e4)
        gateway.command(1.2e6, 3e4)
        assert link.wait_for(lambda: link.written[-1] == (1.2e6, 3e4))
        # the device refuses writes: unhealthy, tried again with the newest set-points
        link.fail["write"] = DeviceError("refused", "illegal data value")
        gateway.command(1.3e6, None)
        assert link.wait_for(lambda: gateway.status().reason == "refused")
        gateway.command(1.4e6, None)
        del link.fail["write"]
        assert link.wait_for(lambda: link.written[-1] == (1.4e6, None) and gateway.status().ok)
        # unreachable: closed, connected again, the last set-points written again
        connects = link.connects
        link.fail["read"] = DeviceError("unreachable", "connection reset")
        assert link.wait_for(lambda: gateway.status().reason == "unreachable")
        del link.fail["read"]
        assert link.wait_for(lambda: link.connects > connects and gateway.status().ok)
        assert link.closes >= 1 and link.written[-1] == (1.4e6, None)
    finally:
        gateway.stop()
    stats = gateway.stats()
    assert stats["device_errors"] >= 2 and stats["device_writes"] >= 3
    assert 0 <= stats["device_read_p50_ms"] <= stats["device_read_p99_ms"]


def test_a_gateway_that_cannot_connect_says_why_and_stops_promptly() -> None:
    link = FakeLink()
    link.fail["connect"] = DeviceError("unreachable", "connection refused")
    gateway = Gateway(link, poll_period_s=0.01, stale_after_s=5.0, retry_s=60.0)
    gateway.start(first_within_s=0.3)                # tried again and again within it
    status = gateway.status()
    gateway.stop()                                   # not after the 60 s retry
    assert (status.ok, status.reason, status.p_w) == (False, "unreachable", None)
    assert link.connects == 0


@pytest.mark.parametrize("call", ["connect", "read"])
def test_a_device_slow_at_the_start_is_tried_again_at_once(call: str) -> None:
    """A device that fails its first connection or read while a run starts (every process
    busy) is connected before the DER's first timer, not a retry_s later."""
    link = FakeLink()
    link.fail[call] = DeviceError("timeout", "no answer within 0.5 s")
    tries = []
    original = getattr(link, call)

    def once(*args):
        tries.append(1)
        if len(tries) == 2:
            del link.fail[call]
        return original(*args)

    setattr(link, call, once)
    gateway = Gateway(link, poll_period_s=0.01, stale_after_s=5.0, retry_s=60.0)
    gateway.start(first_within_s=30.0)
    try:
        assert gateway.status().ok and link.connects == (2 if call == "read" else 1)
    finally:
        gateway.stop()


class FakeClock:
    """Monotonic seconds the test moves."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_set_points_within_the_deadband_are_not_written() -> None:
    link = FakeLink()
    gateway = Gateway(link, poll_period_s=0.01, stale_after_s=5.0, retry_s=0.01,
                      deadband=(1e3, 2e3))
    gateway.start(first_within_s=5.0)
    try:
        gateway.command(1e6, 0.0)
        assert link.wait_for(lambda: link.written == [(1e6, 0.0)])
        gateway.command(1e6 + 900.0, 1.9e3)            # within both bands: not written
        gateway.command(1e6 - 900.0, -1.9e3)
        gateway.command(1e6, 2.5e3)                    # Q beyond its band: written
        assert link.wait_for(lambda: link.written[-1] == (1e6, 2.5e3))
        gateway.command(1e6 + 1.1e3, 2.5e3)            # P beyond its band: written
        assert link.wait_for(lambda: link.written[-1] == (1e6 + 1.1e3, 2.5e3))
        assert gateway.stats()["device_within_deadband"] == 2
        assert link.written == [(1e6, 0.0), (1e6, 2.5e3), (1e6 + 1.1e3, 2.5e3)]
    finally:
        gateway.stop()


def test_writes_keep_their_interval_and_the_newest_set_point_wins() -> None:
    link, clock = FakeLink(), FakeClock()
    gateway = Gateway(link, poll_period_s=1.0, stale_after_s=50.0, retry_s=0.01,
                      write_interval_s=10.0, clock=clock)
    gateway.command(1e6, None)
    gateway.start(first_within_s=5.0)
    try:
        assert link.wait_for(lambda: link.written == [(1e6, None)] and link.reads == 1)
        gateway.command(1.1e6, None)                   # 0 s after the write: held
        gateway.command(1.2e6, None)
        clock.now = 5.0                                # a read is due, the write is not
        assert link.wait_for(lambda: link.reads >= 2)
        assert link.written == [(1e6, None)]
        clock.now = 10.0                               # the interval has passed
        assert link.wait_for(lambda: len(link.written) == 2)
        assert link.written[-1] == (1.2e6, None)       # only the newest, never 1.1 MW
    finally:
        gateway.stop()


# --- the DER controller with a device -----------------------------------------------------------


class FakeDevice:
    """A plant device as the controller sees it."""

    def __init__(self) -> None:
        self.commands: list[tuple[float, float | None]] = []
        self.now = DeviceStatus(True, None, "", 5e5, None)

    def command(self, p_w: float, q_var: float | None) -> None:
        self.commands.append((p_w, q_var))

    def status(self) -> DeviceStatus:
        return self.now

    def stats(self) -> dict[str, float]:
        return {"device_reads": 3.0}


def command(der: DERController, t_ns: int, p_y: float, w: dict | None = None,
            seq: int = 0) -> None:
    body = {"p_y": p_y, "p_ref_w": 0.0, "kp": 1.0, "ki": 1.0, "entry": 0}
    if w is not None:
        body["w"] = w
    der.on_message(t_ns, message(Keys(der._state_key.split("/")[1]).of("p_y"),  # noqa: SLF001
                                 t_ns, body, seq=seq))


def test_a_der_with_a_device_commands_it_reports_its_measurement_and_leaves_while_it_is_down(
        config: Config) -> None:
    device = FakeDevice()
    der = DERController(config.ders[1], config, device=device)   # SGen2: 2 MW, schedule 0.5 MW
    assert device.commands == [(5e5, None)]                       # its schedule at the start
    command(der, 0, 0.1, w={"SGen2": 1.0})
    assert device.commands[-1] == (pytest.approx(0.1 * 2e6 + 5e5), None)
    t = der.next_timer_ns()
    out = der.on_timer(t)
    state = next(o.body for o in out if o.key.endswith("/state"))
    assert state["p_w"] == 5e5                                     # the device's, not a model's
    assert state["held"] == held_at(der.params, der.state, t)     # by the model: no protocol
    assert der.state.t_ns == t                                     # says it; kept running
    # the device goes silent: at the next timer the DER is unavailable, on its schedule
    device.now = DeviceStatus(False, "timeout", "no answer in 0.5 s", 6e5, None)
    out = der.on_timer(der.next_timer_ns())
    kinds = {o.body.get("kind") for o in out if "/event/" in o.key}
    beat = next(o.body for o in out if o.key.endswith("/heartbeat"))
    assert kinds == {"device_lost"} and beat["available"] is False
    assert der.mode == "schedule" and device.commands[-1] == (5e5, None)
    command(der, der.next_timer_ns(), 0.2, seq=1)                 # commands change nothing now
    assert device.commands[-1] == (5e5, None)
    device.now = DeviceStatus(True, None, "", 6e5, None)
    out = der.on_timer(der.next_timer_ns())
    assert {o.body.get("kind") for o in out if "/event/" in o.key} == {"device_back"}
    assert next(o.body for o in out if o.key.endswith("/heartbeat"))["available"] is True
    assert der.counts["device_lost"] == der.counts["device_back"] == 1
    assert der.stats()["device_reads"] == 3.0


def test_a_device_down_at_the_start_is_said_at_the_first_timer(config: Config) -> None:
    device = FakeDevice()
    device.now = DeviceStatus(False, "unreachable", "connection refused", None, None)
    der = DERController(config.ders[1], config, device=device)
    out = der.on_timer(der.next_timer_ns())
    state = next(o.body for o in out if o.key.endswith("/state"))
    assert state["p_w"] == 5e5 and state["mode"] == "schedule"    # its schedule, never read
    assert [o.body["kind"] for o in out if "/event/" in o.key] == ["device_lost"]


def test_a_device_ders_model_keeps_up_with_its_set_points(config: Config) -> None:
    """The model behind a device's hold flag consumes its set-point changes as it runs: they
    do not pile up over a long run (they did: every sample's hold flag went through all)."""
    der = DERController(config.ders[1], config, device=FakeDevice())
    for i in range(400):
        t = der.next_timer_ns()
        command(der, t, 0.1 + 1e-4 * i, w={"SGen2": 1.0}, seq=i)
        der.on_timer(der.next_timer_ns())
    assert len(der.state.queue) <= 2
