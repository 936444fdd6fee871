"""Tests of adnmesh.control: the agents' state machines, driven without a bus or a clock."""

from __future__ import annotations

import json
import math
import random
from pathlib import Path

import pytest

from adnmesh.config import DER, Config, load_config
from adnmesh.control.registry import build_agent
from adnmesh.control.availability_monitor import AvailabilityMonitor
from adnmesh.names import der_id_of
from adnmesh.control.cpfc_controller import (CPFC, HANDOVER_BOUND, HANDOVER_RESPONSE_TIMES,
                                             GainSchedule, initial_p_ref_w, output_limits)
from adnmesh.control.der_controller import DERController
from adnmesh.dermodels.pt1 import PT1DelayParams, PT1DelayState, infeed_at, set_point
from adnmesh.control.measurement_point import Measurement
from adnmesh.control.pi import SampledPI
from adnmesh.sim.node import Node
from adnmesh.sim.topology import Topology
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Design, Switch
from msgspec import UNSET
from payloads import message, payload
from adnmesh.tuning.table import SchedulingTable, TableEntry

MS = 1_000_000  # ns


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    """Two WTs (SGen2 with a 0.5 MW schedule), a step at 1 s, SGen2 unavailable from 8 s."""
    return load_config(configs_dir / "examples" / "runtime-step.yaml")


@pytest.fixture(scope="module")
def table(config: Config) -> SchedulingTable:
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), 5e-8, 1.92e-7, {"SGen1": 1.0, "SGen2": 0.8}))
    table.add(TableEntry(("SGen1",), 1e-7, 3.84e-7, {"SGen1": 1.0}))
    return table


# --- DER dynamics -------------------------------------------------------------------------------


def test_pt1_with_delay_is_exact_for_piecewise_constant_setpoints() -> None:
    params = PT1DelayParams(p_inst_w=2e6, t_delay_ns=10 * MS, t_lag_s=0.25)
    state = PT1DelayState.steady(1e5)
    set_point(params, state, 100 * MS, 1.1e6)
    set_point(params, state, 400 * MS, 6e5)
    assert infeed_at(params, state, 110 * MS) == 1e5          # the dead time holds it
    for t_ms in (200, 410, 437, 1000):
        expected = 1e5
        t = t_ms / 1e3
        if t > 0.11:
            expected = 1.1e6 + (1e5 - 1.1e6) * math.exp(-(min(t, 0.41) - 0.11) / 0.25)
        if t > 0.41:
            expected = 6e5 + (expected - 6e5) * math.exp(-(t - 0.41) / 0.25)
        assert infeed_at(params, state, t_ms * MS) == pytest.approx(expected, rel=1e-13)


def test_pt1_reaches_the_rise_time_of_the_config(config: Config) -> None:
    der = config.ders[0]
    params = PT1DelayParams(der.p_inst_w, int(round(der.t_delay_s * 1e9)), config.t_lag_s(der))
    state = PT1DelayState.steady(0.0)
    set_point(params, state, 0, 1.0)
    t10 = params.t_delay_ns * 1e-9 - config.t_lag_s(der) * math.log(0.9)
    t90 = params.t_delay_ns * 1e-9 - config.t_lag_s(der) * math.log(0.1)
    assert infeed_at(params, state, round(t10 * 1e9)) == pytest.approx(0.1, abs=1e-8)
    assert infeed_at(params, state, round(t90 * 1e9)) == pytest.approx(0.9, abs=1e-8)
    assert t90 - t10 == pytest.approx(der.t_rise_s, rel=1e-12)


def test_pt1_refuses_to_go_back_in_time() -> None:
    params = PT1DelayParams(1.0, 0, 1.0)
    state = PT1DelayState.steady(0.0, t_ns=5)
    with pytest.raises(ValueError, match="back in time"):
        infeed_at(params, state, 4)


# --- PI -----------------------------------------------------------------------------------------


def test_pi_integrates_with_the_trapezoidal_rule() -> None:
    pi = SampledPI(kp=2.0, ki=3.0, period_s=0.5)
    assert pi.update(1.0) == pytest.approx(2.0 * 1.0 + 3.0 * 0.25)        # x = h/2 (0 + 1)
    assert pi.update(3.0) == pytest.approx(2.0 * 3.0 + 3.0 * (0.25 + 1.0))  # x += h/2 (1 + 3)


def test_pi_holds_its_integrator_while_saturated() -> None:
    pi = SampledPI(kp=1.0, ki=10.0, period_s=0.1, y_min=-1.0, y_max=1.0)
    for _ in range(50):
        assert pi.update(2.0) == 1.0
    assert pi.holding
    x_held = pi.x_i
    assert pi.update(-0.5) < 1.0             # leaves the limit at once: no wind-up to unwind
    assert pi.x_i == pytest.approx(x_held + 0.05 * (2.0 - 0.5))


@pytest.mark.parametrize("seed", range(20))
def test_pi_switch_keeps_the_output_continuous(seed: int) -> None:
    """P_Y stays continuous across a switch, to floating-point precision
    (docs/method.md#bumpless-switching)."""
    rng = random.Random(seed)
    pi = SampledPI(kp=rng.uniform(1e-9, 1e-6), ki=rng.uniform(1e-9, 1e-6), period_s=0.01)
    for _ in range(rng.randint(1, 200)):
        pi.update(rng.uniform(-2e6, 2e6))
    assert pi.x_i != 0.0
    record = pi.switch(rng.uniform(1e-9, 1e-6), rng.uniform(1e-9, 1e-6))
    scale = max(abs(record.p_y_before), abs(pi.kp * pi.e_prev))
    assert abs(record.p_y_after - record.p_y_before) <= 4 * math.ulp(scale)
    assert pi.kp * pi.e_prev + pi.ki * pi.x_i == pytest.approx(record.p_y_before, rel=1e-14)


def test_pi_switch_with_equal_kp_keeps_the_integral_part() -> None:
    """The paper's invariant K_I' x_I' = K_I x_I holds when only K_I changes."""
    pi = SampledPI(kp=1e-7, ki=4e-7, period_s=0.01)
    for error in (1e6, 8e5, 6e5):
        pi.update(error)
    integral = pi.ki * pi.x_i
    pi.switch(1e-7, 1e-7)
    assert pi.ki * pi.x_i == pytest.approx(integral, rel=1e-14)


# --- DER local controller -----------------------------------------------------------------------


def command(der: DERController, t_ns: int, p_y: float, entry: int = 0, w: dict | None = None,
            seq: int = 0) -> None:
    body = {"p_y": p_y, "p_ref_w": 0.0, "kp": 1.0, "ki": 1.0, "entry": entry}
    if w is not None:
        body["w"] = w
    der.on_message(t_ns, message(Keys(der_grid(der)).of("p_y"), t_ns, body, seq=seq))


def der_grid(der: DERController) -> str:
    return der._state_key.split("/")[1]  # noqa: SLF001


def test_der_setpoint_follows_eq1(config: Config) -> None:
    der = DERController(config.ders[1], config)            # SGen2: P_inst 2 MW, P_sched 0.5 MW
    command(der, 100 * MS, 0.1, w={"SGen1": 1.0, "SGen2": 0.8})
    assert der.setpoint_w == pytest.approx(0.1 * 0.8 * 2e6 + 0.5e6)
    assert der.mode == "control"
    command(der, 110 * MS, 5.0, seq=1)                     # limited to P_inst
    assert der.setpoint_w == 2e6
    command(der, 120 * MS, -5.0, seq=2)                    # and to 0
    assert der.setpoint_w == 0.0


def test_der_ignores_p_y_of_an_entry_whose_weights_it_lacks(config: Config) -> None:
    der = DERController(config.ders[0], config)
    command(der, 100 * MS, 0.2, entry=0, w={"SGen1": 0.5})
    command(der, 110 * MS, 0.9, entry=1, seq=1)            # switch message lost: stale entry
    assert der.setpoint_w == pytest.approx(0.2 * 0.5 * 2e6)
    assert der.counts["stale_commands"] == 1
    command(der, 120 * MS, 0.9, entry=1, w={"SGen2": 1.0}, seq=2)  # entry without this DER
    assert der.setpoint_w == 0.0 and der.weight == 0.0


def test_der_falls_back_to_its_schedule_after_the_watchdog(config: Config) -> None:
    der = DERController(config.ders[1], config)
    command(der, 100 * MS, 0.25, w={"SGen2": 1.0})
    deadline = 100 * MS + int(config.runtime.watchdog_timeout_s * 1e9)
    assert der.next_timer_ns() <= deadline
    t = 0
    while t < deadline:
        t = der.next_timer_ns()
        der.on_timer(t)
    assert (der.mode, der.setpoint_w, der.counts["watchdog_trips"]) == ("watchdog", 0.5e6, 1)
    command(der, deadline + 5 * MS, 0.25, seq=1)           # contact is back
    assert der.mode == "control" and der.setpoint_w == pytest.approx(1e6)


def test_der_availability_change_sends_a_heartbeat_and_runs_on_schedule(config: Config) -> None:
    der = DERController(config.ders[1], config)            # SGen2: unavailable from 8 s
    command(der, 100 * MS, 0.25, w={"SGen2": 1.0})
    sent = []
    t = 0
    while t < 8000 * MS:
        t = der.next_timer_ns()
        sent += [(t, o) for o in der.on_timer(t)]
        if t % (500 * MS) == 0 and t < 7500 * MS:          # keep the watchdog fed
            command(der, t, 0.25, seq=t // MS)
    beats = [(t, o.body["available"]) for t, o in sent if o.key.endswith("/heartbeat")]
    assert beats[0] == (0, True)
    assert beats[-1] == (8000 * MS, False)
    assert der.mode == "schedule" and der.setpoint_w == 0.5e6
    states = [o for _, o in sent if o.key.endswith("/state")]
    assert len(states) == 801                              # every 10 ms from 0 to 8 s


# --- measurement and availability ---------------------------------------------------------------


def test_measurement_sums_the_infeeds_and_the_rest_of_the_grid(config: Config) -> None:
    meas = Measurement(config)
    keys = Keys(config.grid)
    (out,) = meas.on_timer(0)
    assert out.body == {"p_ip_w": -3e6 + 0.5e6}            # rest + schedules at rest
    meas.on_message(10 * MS, message(keys.of("der_state", "SGen1"), 10 * MS,
                                     {"p_w": 1.5e5, "setpoint_w": 2e5, "mode": "control"},
                                     src="der/SGen1"))
    assert meas.next_timer_ns() == 10 * MS
    (out,) = meas.on_timer(10 * MS)
    assert out.key == keys.of("p_ip") and out.body["p_ip_w"] == -3e6 + 1.5e5 + 0.5e6


def test_a_restarted_availability_monitor_listens_before_it_speaks(config: Config) -> None:
    """Restarted at 240 s after SGen2 left: no SI until one heartbeat timeout has passed, then
    the SI the heartbeats say (never 'everyone available', the state at t = 0)."""
    monitor = AvailabilityMonitor(config)
    keys = Keys(config.grid)
    start = 240_000 * MS
    timeout = int(config.runtime.heartbeat_timeout_s * 1e9)
    monitor.resume(start)
    sent = []
    for k in range(3):                       # SGen1 beats every second, SGen2 says it left
        for der_id, available in (("SGen1", True), ("SGen2", False)):
            t = start + 100 * MS + k * 1000 * MS
            sent += monitor.on_message(t, message(keys.of("heartbeat", der_id), t, {
                "available": available, "mode": "schedule" if not available else "control"},
                src=f"der/{der_id}"))
            while monitor.next_timer_ns() <= t:
                sent += monitor.on_timer(monitor.next_timer_ns())
    assert [o for o in sent if o.key == keys.of("si") and o.body["si"]["SGen2"]] == []
    while monitor.next_timer_ns() <= start + timeout:
        sent += monitor.on_timer(monitor.next_timer_ns())
    first = [o.body["si"] for o in sent if o.key == keys.of("si")]
    assert first and first[0] == {"SGen1": True, "SGen2": False}


def test_availability_monitor_builds_si_from_heartbeats(config: Config) -> None:
    monitor = AvailabilityMonitor(config)
    keys = Keys(config.grid)

    def si_of(out):
        return [o.body["si"] for o in out if o.key == keys.of("si")]

    assert si_of(monitor.on_timer(monitor.next_timer_ns())) == [{"SGen1": True, "SGen2": True}]

    def beat(der_id: str, t_ns: int, available: bool, mode: str = "control"):
        """Deliver a heartbeat at ``t_ns``, then end the instant; return what was sent."""
        assert monitor.on_message(t_ns, message(keys.of("heartbeat", der_id), t_ns,
                                                {"available": available, "mode": mode},
                                                src=f"der/{der_id}")) == []
        return monitor.on_timer(t_ns) if monitor.next_timer_ns() == t_ns else []

    assert beat("SGen1", 100 * MS, True) == []                  # no change, nothing sent
    out = beat("SGen2", 150 * MS, False)
    assert si_of(out) == [{"SGen1": True, "SGen2": False}]
    assert [(o.body["kind"], o.body["subject"]) for o in out if o.key != keys.of("si")] == [
        ("unavailable", "der/SGen2")]
    assert si_of(monitor.on_timer(monitor.next_timer_ns())) == [      # repeated every second
        {"SGen1": True, "SGen2": False}]
    assert monitor.next_timer_ns() == 2000 * MS
    monitor.on_timer(2000 * MS)
    timeout = int(config.runtime.heartbeat_timeout_s * 1e9)
    assert monitor.next_timer_ns() == 100 * MS + timeout         # SGen1's heartbeat expires
    out = monitor.on_timer(100 * MS + timeout)
    assert si_of(out) == [{"SGen1": False, "SGen2": False}]
    assert "no heartbeat for 2.5 s" in out[1].body["text"]
    assert si_of(beat("SGen1", 100 * MS + timeout + 1, True))[0]["SGen1"] is True
    out = beat("SGen1", 100 * MS + timeout + 2, True, mode="watchdog")
    assert si_of(out)[0]["SGen1"] is False                       # a fallback: not available
    assert "in watchdog fallback" in out[1].body["text"]


def test_availability_monitor_sends_one_si_for_simultaneous_changes(configs_dir: Path) -> None:
    """The SimBench scenario: six WTs go unavailable at 170 s, so at 170.1 s eleven heartbeats
    arrive at once, six of them with ``available: false``; the monitor sends one SI with all six
    changes (not one SI per heartbeat)."""
    simbench = load_config(configs_dir / "simbench.yaml")
    keys = Keys(simbench.grid)
    (change,) = [c for c in simbench.scenario.availability if not c.available]
    assert (change.t_s, len(change.ders)) == (170, 6)
    node = Node(AvailabilityMonitor(simbench), Topology.from_config(simbench), seed=0)
    sent = []
    for second in range(171):   # every DER's heartbeat every second, 0.1 s on the link
        t_ns = second * 1000 * MS
        for der_id in simbench.der_ids():
            available = second < change.t_s or der_id not in change.ders
            node.receive(keys.of("heartbeat", der_id), payload(
                keys.of("heartbeat", der_id), {"available": available}, seq=second, t_send_ns=t_ns,
                t_deliver_ns=t_ns + 100 * MS))
        sent += [json.loads(payload) for key, payload in node.advance(t_ns + 500 * MS)
                 if key == keys.of("si")]
    changes = [m for i, m in enumerate(sent) if i == 0 or m["si"] != sent[i - 1]["si"]]
    assert [(m["t_send_ns"], m["si"]) for m in changes] == [
        (0, dict.fromkeys(simbench.der_ids(), True)),
        (170_100 * MS, {d: d not in change.ders for d in simbench.der_ids()})]


# --- CPFC ---------------------------------------------------------------------------------------


def run_cpfc(cpfc: CPFC, until_ns: int, p_meas=None, si_at=None):
    """Drive the CPFC's timer to ``until_ns``; return its messages by key."""
    keys = Keys(cpfc.config.grid)
    out = []
    while cpfc.next_timer_ns() < until_ns:
        t = cpfc.next_timer_ns()
        if si_at is not None and t == si_at[0]:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": si_at[1]}, src="availability"))
        if p_meas is not None:
            cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": p_meas(t)}, src="measurement"))
        out += [(t, o) for o in cpfc.on_timer(t)]
    return out


def test_cpfc_starts_at_the_operating_point_and_follows_the_scenario(config, table) -> None:
    cpfc = CPFC(config, GainSchedule(config, table))
    assert initial_p_ref_w(config) == -3e6 + 0.5e6
    out = run_cpfc(cpfc, 1010 * MS, p_meas=lambda t: -2.5e6)
    refs = [(t, o.body["p_ref_w"]) for t, o in out if o.key.endswith("/p_ref")]
    assert refs == [(0, -2.5e6), (1000 * MS, -1.5e6)]
    p_y = [o.body for t, o in out if o.key.endswith("/p_y")]
    assert all(b["p_y"] == 0.0 for b in p_y[:-1])              # at rest until the step
    assert p_y[-1]["p_y"] == pytest.approx(5e-8 * 1e6 + 1.92e-7 * 0.005 * 1e6)
    assert p_y[0]["w"] == {"SGen1": 1.0, "SGen2": 0.8} and "w" not in p_y[1]
    assert p_y[0]["entry"] == 0


def test_cpfc_switch_is_bumpless_with_a_nonzero_integrator(config, table) -> None:
    """Test 7c at the state-machine level: the switch leaves P_Y unchanged."""
    cpfc = CPFC(config, GainSchedule(config, table))
    out = run_cpfc(cpfc, 5000 * MS, p_meas=lambda t: -2.5e6 + 0.6e6 * min(1.0, t / 4e9),
                   si_at=(4500 * MS, {"SGen1": True, "SGen2": False}))
    (t_switch, switched), = [(t, o.body) for t, o in out if "switch" in o.body]
    assert t_switch == 4500 * MS
    assert cpfc.pi.x_i != 0.0
    assert switched["p_y"] - switched["switch"].p_y_before == 0.0
    assert (switched["kp"], switched["ki"]) == (1e-7, 3.84e-7)
    assert switched["w"] == {"SGen1": 1.0} and switched["entry"] == 1
    assert (switched["switch"].kp_before, switched["switch"].ki_before) == (5e-8, 1.92e-7)
    (event,) = cpfc.switches
    assert event.available == ("SGen1",) and event.source == "table"


def test_cpfc_repeats_the_weights_periodically(config, table) -> None:
    cpfc = CPFC(config, GainSchedule(config, table))
    out = run_cpfc(cpfc, 2500 * MS)
    with_w = [t for t, o in out if o.key.endswith("/p_y") and "w" in o.body]
    assert with_w == [0, 1000 * MS, 2000 * MS]


def test_output_limits_are_where_every_der_saturates(config: Config) -> None:
    low, high = output_limits(config, {"SGen1": 1.0, "SGen2": 0.5})
    # SGen1: 0 .. 2 MW at P_Y in [0, 1]; SGen2 (0.5 MW schedule): P_Y in [-0.5, 1.5]
    assert (low, high) == (-0.5, 1.5)
    assert all(math.isnan(x) for x in output_limits(config, {}))


def test_gain_schedule_falls_back_to_the_static_controller(config: Config) -> None:
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.static = TableEntry((), 2e-8, 1e-8, {})
    schedule = GainSchedule(config, table, on_demand=False)
    entry, source = schedule.lookup(frozenset({"SGen2"}))
    assert source == "static"
    assert (entry.ders, entry.kp, entry.ki, entry.w) == (("SGen2",), 2e-8, 1e-8, {"SGen2": 1.0})
    assert schedule.lookup(frozenset()) == (None, "none")


def test_gain_schedule_tunes_missing_subsets_on_demand(config: Config) -> None:
    calls = []

    def tune(cfg, ids):
        calls.append(ids)
        return TableEntry(tuple(ids), 3e-8, 2e-8, dict.fromkeys(ids, 1.0))

    schedule = GainSchedule(config, None, tune=tune)
    assert schedule.lookup(frozenset({"SGen2", "SGen1"}))[1] == "tuned"
    assert schedule.lookup(frozenset({"SGen1", "SGen2"}))[1] == "tuned"
    assert calls == [["SGen1", "SGen2"]]                     # once, in config order


def test_build_agent_knows_every_agent(config, table) -> None:
    schedule = GainSchedule(config, table)
    kinds = {a: type(build_agent(a, config, schedule)).__name__
             for a in ("cpfc", "measurement", "availability", "der/SGen2")}
    assert kinds == {"cpfc": "CPFC", "measurement": "Measurement",
                     "availability": "AvailabilityMonitor", "der/SGen2": "DERController"}
    with pytest.raises(ValueError, match="unknown agent"):
        build_agent("grid", config)
    with pytest.raises(ValueError, match="schedule"):
        build_agent("cpfc", config)


def test_der_defaults_follow_the_config_dataclass(config) -> None:
    der = DER(id="X", type="PV", p_inst_w=1e5, t_delay_s=0.0, t_rise_s=0.1, sgen="s")
    assert (der.p_sched_w, der.model) == (0.0, None)
    assert DERController(der, config).params.t_delay_ns == 0


def test_pi_switch_to_a_narrower_range_continues_from_its_limit() -> None:
    # P_Y slightly negative, the new actuators all saturate below 0: start from the limit
    pi = SampledPI(2e-8, 6e-8, 0.01, y_min=-0.5, y_max=0.5)
    for e in (-1e3, -2e3, -3e3):
        pi.update(e)
    assert pi.output < 0
    pi.set_limits(0.0, 1.0)
    record = pi.switch(5e-7, 7e-8)
    assert record.p_y_limited == 0.0 and record.p_y_after == pytest.approx(0.0, abs=1e-15)
    assert pi.kp * pi.e_prev + pi.ki * pi.x_i == pytest.approx(0.0, abs=1e-15)  # not wound up


# --- CPFC under faults: holds, undoing wind-up, power-continuous switches, restarts -------------


def heartbeat(cpfc: CPFC, der_id: str, t_ns: int, mode: str, p_y: float = 0.0,
              t_send_ns: int | None = None) -> None:
    keys = Keys(cpfc.config.grid)
    sent = t_ns - 100 * MS if t_send_ns is None else t_send_ns
    cpfc.on_message(t_ns, message(keys.of("heartbeat", der_id), sent,
                                  {"available": True, "mode": mode, "p_y": p_y, "entry": 0},
                                  src=f"der/{der_id}"))


def drive(cpfc: CPFC, until_ns: int, p_meas, on_sample=lambda t: None) -> list:
    """Run the CPFC's samples to ``until_ns`` with the measurement ``p_meas(t)`` (None: no
    measurement at that sample); return ``(t, body)`` of its P_Y messages. SI is repeated every
    second, as a live availability monitor does (the last SI the CPFC took: ``on_sample`` may
    deliver a new one)."""
    keys = Keys(cpfc.config.grid)
    out = []
    while cpfc.next_timer_ns() < until_ns:
        t = cpfc.next_timer_ns()
        if t % (1000 * MS) == 0:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {
                d: d in cpfc.si_available for d in cpfc.config.der_ids()}}))
        on_sample(t)
        value = p_meas(t)
        if value is not None:
            cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": value}, src="measurement"))
        out += [(t, o.body) for o in cpfc.on_timer(t) if o.key == keys.of("p_y")]
    return out


def test_cpfc_holds_without_measurements_and_resumes_without_a_jump(config, table) -> None:
    """Measurements stop at 2 s (the step came at 1 s): from the last one on the PI is taken
    back and held; when they return at 4 s the output continues from the held value."""
    cpfc = CPFC(config, GainSchedule(config, table))
    lost = (2000 * MS, 4000 * MS)
    out = drive(cpfc, 5000 * MS, lambda t: None if lost[0] <= t < lost[1] else -2.2e6)
    by_t = dict(out)
    last_fresh = by_t[lost[0] - 10 * MS]["p_y"]
    held = [b for t, b in out if lost[0] + 260 * MS <= t < lost[1]]
    assert held and all(b["hold"] == "measurement" and b["p_y"] == last_fresh for b in held)
    resumed = by_t[lost[1]]
    error = -1.5e6 - (-2.2e6)
    one_step = cpfc.pi.ki * config.runtime.pi_period_s * error
    assert "hold" not in resumed                # it continues from the held value with one
    assert resumed["p_y"] - last_fresh == pytest.approx(one_step, rel=1e-9)   # sample's integral
    assert cpfc.counts["rollbacks"] == 1


def test_cpfc_undoes_the_samples_a_fallback_disturbed(config, table) -> None:
    """Both DERs fall back at 3 s (their acknowledgements say so, 0.1 s later); P_IP drops. The
    CPFC takes its PI back to the sample at fallback + T_meas and holds: the outage leaves no
    trace in the integrator whatever its length."""
    cpfc = CPFC(config, GainSchedule(config, table))
    t_fall = 3000 * MS

    def p_meas(t):
        return -1.5e6 if t < t_fall + 100 * MS else -2.5e6      # the DERs' share is gone

    def acks(t):
        if t == t_fall + 100 * MS:
            for der in ("SGen1", "SGen2"):
                heartbeat(cpfc, der, t, "watchdog", 0.3, t_send_ns=t_fall)

    out = drive(cpfc, 9000 * MS, p_meas, acks)
    by_t = dict(out)
    before = by_t[t_fall + 100 * MS - 10 * MS]["p_y"]          # the sample it goes back to
    held = [b for t, b in out if t > t_fall + 100 * MS]
    assert all(b["hold"] == "actuators" and b["p_y"] == before for b in held)
    assert cpfc.counts["rollbacks"] == 1


def test_cpfc_hands_returning_ders_their_share_of_the_power(config, table) -> None:
    """SGen2 comes back while SGen1 carries P_Y alone: the switch scales P_Y so that the DERs'
    total commanded power P_Y Σ w P_inst stays the same (SGen2 does not add its share at once)."""
    cpfc = CPFC(config, GainSchedule(config, table))
    keys = Keys(config.grid)

    def si(t):
        if t == 2000 * MS:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {"SGen1": True, "SGen2": False}}))
        if t == 6000 * MS:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {"SGen1": True, "SGen2": True}}))

    out = drive(cpfc, 6100 * MS, lambda t: -2.2e6, si)
    by_t = dict(out)
    alone, together = by_t[2000 * MS], by_t[6000 * MS]
    assert alone["switch"].scale == 1.0 and alone["p_y"] == alone["switch"].p_y_before
    w = table.lookup(["SGen1", "SGen2"]).w
    share = 2e6 / (w["SGen1"] * 2e6 + w["SGen2"] * 2e6)
    assert together["switch"].scale == pytest.approx(share)
    before_w = together["switch"].p_y_before * 1.0 * 2e6
    after_w = together["p_y"] * (w["SGen1"] * 2e6 + w["SGen2"] * 2e6)
    assert after_w == pytest.approx(before_w, rel=1e-12)
    # leaving moves no DER's power: no handover; returning hands SGen2 its share in the
    # longer of 2 x its response (0.525 s) and 1 / (HANDOVER_BOUND K_I Σ w P_inst)
    assert alone["switch"].handover_s is UNSET
    ki_n = together["ki"] * (w["SGen1"] * 2e6 + w["SGen2"] * 2e6)
    assert together["switch"].handover_s == pytest.approx(
        max(HANDOVER_RESPONSE_TIMES * 0.525, 1 / (HANDOVER_BOUND * ki_n)))


def test_cpfc_keeps_the_commanded_power_of_ders_at_a_limit(config, table) -> None:
    """SGen1 alone at P_Y 1.2 is held at its 2 MW (Eq. 1 asks 2.4 MW): when SGen2 returns, the
    new P_Y makes both command the 2 MW SGen1 delivered, not the 2.4 MW of Eq. 1 unlimited."""
    cpfc = CPFC(config, GainSchedule(config, table))
    cpfc.available = cpfc.in_use = frozenset({"SGen1"})
    cpfc.weights = {"SGen1": 1.0}
    cpfc.pi.set_limits(-10, 10)
    cpfc.pi.output = cpfc._p_y_sent = 1.2                    # noqa: SLF001
    record = cpfc._switch(0, frozenset({"SGen1", "SGen2"}))  # noqa: SLF001
    w = table.lookup(["SGen1", "SGen2"]).w
    commanded = min(record.p_y_after * w["SGen1"] * 2e6, 2e6) + \
        record.p_y_after * w["SGen2"] * 2e6
    assert commanded == pytest.approx(2e6, rel=1e-12)
    assert record.scale == pytest.approx(2e6 / (w["SGen1"] * 2e6 + w["SGen2"] * 2e6) / 1.2)


def test_der_takes_its_new_share_over_the_handover(config: Config) -> None:
    """docs/method.md#returning-ders-handover: on a switch with a handover time the DER keeps
    the setpoint it had, follows the change of P_Y of the switching sample with its new
    weight, and moves to Eq. 1 linearly over the handover; without one it takes Eq. 1 at
    once."""
    der = DERController(config.ders[0], config)            # SGen1: P_inst 2 MW, P_sched 0
    command(der, 100 * MS, 0.3, w={"SGen1": 1.0})
    assert der.setpoint_w == pytest.approx(0.6e6)
    keys = Keys(der_grid(der))
    body = {"p_y": 0.16, "p_ref_w": 0.0, "kp": 1.0, "ki": 1.0, "entry": 1,
            "w": {"SGen1": 1.0, "SGen2": 0.8},
            "switch": Switch(0.3, 0.15, 1.0, 1.0, 0.5, 10.0)}       # P_Y scaled by 0.5
    der.on_message(200 * MS, message(keys.of("p_y"), 200 * MS, body, seq=1))
    # from 0.6 MW, plus the sample's change (0.16 - 0.5 x 0.3) x 2 MW; Eq. 1 says 0.32 MW
    assert der.setpoint_w == pytest.approx(0.6e6 + 0.02e6)
    command(der, 5200 * MS, 0.15, entry=1, seq=2)          # half way: half the offset
    assert der.setpoint_w == pytest.approx(0.3e6 + 0.5 * 0.3e6)
    command(der, 10200 * MS, 0.15, entry=1, seq=3)         # over: Eq. 1
    assert der.setpoint_w == pytest.approx(0.3e6)
    body.update(entry=2, switch=Switch(0.15, 0.15, 1.0, 1.0))          # no handover time
    der.on_message(10300 * MS, message(keys.of("p_y"), 10300 * MS, {**body, "p_y": 0.2}, seq=4))
    assert der.setpoint_w == pytest.approx(0.4e6)


def test_cpfc_takes_the_entry_of_the_ders_that_can_move_one_sample_before_a_step(
        config, table) -> None:
    """docs/method.md#directional-availability: SGen1 (P_sched 0) cannot move down; one sample
    before a -0.5 MW step the CPFC switches to SGen2's entry, bumplessly and saying why; the
    switch does not end a step's window."""
    from adnmesh.config import PRefStep
    from adnmesh.results.rules import Event, StepWindowEnds, _gain_switch

    down = config.model_copy(update={"scenario": config.scenario.model_copy(
        update={"p_ref_steps": (PRefStep(t_s=1.0, delta_w=-0.5e6),)})})
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids(),
                            entries=dict(table.entries))
    table.add(TableEntry(("SGen2",), 1e-7, 3.84e-7, {"SGen2": 1.0}))
    cpfc = CPFC(down, GainSchedule(down, table))
    out = run_cpfc(cpfc, 1010 * MS, p_meas=lambda t: -2.5e6)
    (t_switch, switched), = [(t, o.body) for t, o in out if "switch" in o.body]
    assert t_switch == 990 * MS and switched["switch"].direction == "down"
    assert switched["w"] == {"SGen2": 1.0} and switched["p_y"] == 0.0
    after = [o.body for t, o in out if t == 1000 * MS and o.key.endswith("/p_y")][0]
    assert (after["kp"], after["ki"]) == (1e-7, 3.84e-7)        # the step meets SGen2's gains
    found = _gain_switch(json.loads(payload(Keys(down.grid).of("p_y"), switched)), None, {})
    ends = StepWindowEnds()
    ends.take(Event(t_switch, "gain_switch", *found[:2], "", found[2]))
    assert found[2]["direction"] == "down" and ends.instants == []


def test_cpfc_says_what_each_entry_was_certified_for(config) -> None:
    """docs/method.md#said-when-over: the first P_Y of an entry with certified figures carries
    them (and the constraints' overshoot limit); an entry without them (the static
    controller's) carries none."""
    figures = {"rise_time_s": 2.5, "settling_time_s": 3.5, "overshoot_pct": 0.4}
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), 5e-8, 1.92e-7, {"SGen1": 1.0, "SGen2": 0.8},
                         figures=figures))
    table.static = TableEntry(("SGen1", "SGen2"), 4e-8, 1e-7, {})
    cpfc = CPFC(config, GainSchedule(config, table, on_demand=False))
    out = drive(cpfc, 2100 * MS, lambda t: -2.5e6,
                lambda t: t == 2000 * MS and cpfc.on_message(t, message(
                    Keys(config.grid).of("si"), t, {"si": {"SGen1": True, "SGen2": False}})))
    designs = [(t, b["entry"], b.get("design")) for t, b in out if "design" in b]
    assert designs == [(0, 0, Design(2.5, 3.5, 0.4, 1.0, 5.0))]
    (static,) = [b for t, b in out if "switch" in b]
    assert static["entry"] == 1 and "design" not in static


def test_a_restarted_cpfc_resumes_from_the_acknowledged_p_y(config, table) -> None:
    cpfc = CPFC(config, GainSchedule(config, table))
    keys = Keys(config.grid)
    cpfc.resume(5003 * MS)
    assert cpfc.next_timer_ns() == 5010 * MS and cpfc.hold == "resuming"

    def inputs(t):
        if t == 5100 * MS:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {"SGen1": True, "SGen2": True}}))
        if t == 5300 * MS:
            heartbeat(cpfc, "SGen1", t, "watchdog", 0.2125)
        if t == 5600 * MS:
            heartbeat(cpfc, "SGen2", t, "watchdog", 0.2125)

    out = drive(cpfc, 6000 * MS, lambda t: -2.1e6, inputs)
    first_t, first = out[0]
    assert first_t == 5600 * MS                      # SI and both acknowledgements in
    assert first["p_y"] == pytest.approx(0.2125, abs=1e-15)
    assert first["hold"] == "actuators"    # both in fallback: held until they follow again
    assert all(t >= 5600 * MS for t, _ in out)       # nothing sent while resuming


def test_a_restarted_cpfc_resumes_after_the_heartbeat_timeout_without_acks(config, table) -> None:
    cpfc = CPFC(config, GainSchedule(config, table))
    cpfc.resume(0)
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6)
    timeout = int(config.runtime.heartbeat_timeout_s * 1e9)
    one_step = cpfc.pi.ki * config.runtime.pi_period_s * 1e6     # P_ref -1.5 MW, P_IP -2.5
    assert out[0][0] == timeout and out[0][1]["p_y"] == pytest.approx(one_step, rel=1e-9)


def test_der_heartbeat_acknowledges_its_last_p_y_and_mode_changes_at_once(config) -> None:
    der = DERController(config.ders[0], config)
    sent = [(0, o.body) for o in der.on_timer(0) if o.key.endswith("/heartbeat")]
    command(der, 100 * MS, 0.25, w={"SGen1": 1.0})
    t = 0
    while t < 2500 * MS:
        t = der.next_timer_ns()
        sent += [(t, o.body) for o in der.on_timer(t) if o.key.endswith("/heartbeat")]
    assert sent[0] == (0, {"available": True, "mode": "control", "p_y": 0.0, "entry": None})
    assert (1000 * MS, "control", 0.25) in [(t, b["mode"], b["p_y"]) for t, b in sent]
    assert (1100 * MS, "watchdog", 0.25) in [(t, b["mode"], b["p_y"]) for t, b in sent]
    assert der.setpoint_w == 0.0 and der.counts["watchdog_trips"] == 1


def test_cpfc_announces_its_entry_as_an_actuator_of_the_level_above(config, table) -> None:
    """docs/hierarchy.md: with the first output of every entry the CPFC sends what the level
    above needs, the entry's exact closed loop; decoded, it is the loop of the entry."""
    import msgspec
    import numpy as np
    from adnmesh.cascade.lower_adn import announced
    from adnmesh.cascade.upper_table import lower_adn
    from adnmesh.wire.messages import AdnActuator

    cpfc = CPFC(config, GainSchedule(config, table))
    out = run_cpfc(cpfc, 5000 * MS, p_meas=lambda t: -2.5e6,
                   si_at=(4500 * MS, {"SGen1": True, "SGen2": False}))
    sent = [(t, o) for t, o in out if o.key == Keys(config.grid).of("adn_actuator")]
    assert [t for t, _ in sent] == [0, 4500 * MS]
    both, one = (o.body for _, o in sent)
    assert both["ders"] == ["SGen1", "SGen2"] and one["ders"] == ["SGen1"]
    assert (both["entry"], one["entry"]) == (0, 1)
    assert both["capacity_w"] == sum(d.p_inst_w for d in config.ders)
    assert both["range_down_w"] == 0.5e6                # SGen2's schedule
    assert both["range_up_w"] == both["capacity_w"] - 0.5e6
    assert (one["kp"], one["ki"]) == (1e-7, 3.84e-7)
    # through the wire format and back: the loop of the table entry, exactly
    wire = {"v": 1, "type": "adn_actuator", "src": "cpfc", "seq": 0, "t_send_ns": 0,
            "t_deliver_ns": 0, **both}
    decoded = msgspec.json.decode(msgspec.json.encode(wire), type=AdnActuator)
    entry = table.lookup(["SGen1", "SGen2"])
    omega = np.geomspace(1e-3, 1e2, 50)
    assert np.array_equal(announced("x", decoded).closed_loop(omega),
                          lower_adn(config, entry, "x").closed_loop(omega))


def test_cpfc_announces_the_ders_it_keeps_when_no_entry_has_gains_for_them(config) -> None:
    """No entry and no static pair for the DERs left: the CPFC keeps its gains on them, and
    the level above hears of the smaller ADN (the same entry number, fewer DERs)."""
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), 5e-8, 1.92e-7, {"SGen1": 1.0, "SGen2": 0.8}))
    cpfc = CPFC(config, GainSchedule(config, table, on_demand=False))
    out = run_cpfc(cpfc, 5000 * MS, p_meas=lambda t: -2.5e6,
                   si_at=(4500 * MS, {"SGen1": True, "SGen2": False}))
    sent = [(t, o.body) for t, o in out if o.key == Keys(config.grid).of("adn_actuator")]
    assert [(t, b["entry"], b["ders"]) for t, b in sent] == [
        (0, 0, ["SGen1", "SGen2"]), (4500 * MS, 0, ["SGen1"])]
    assert sent[1][1]["capacity_w"] == config.ders_by_id(["SGen1"])[0].p_inst_w


class _MonitorByScans(AvailabilityMonitor):
    """The monitor as it was before SI and the deadlines were kept up to date DER by DER: SI
    rebuilt and every deadline scanned at each call (the reference)."""

    def si(self):
        return {d: self.flag[d] and d not in self.expired for d in self.der_ids}

    def next_timer_ns(self):
        times = [t for d, t in self.deadline_ns.items() if d not in self.expired]
        times.append(self._next_repeat_ns)
        if self._send_ns is not None:
            times.append(self._send_ns)
        return min(times)

    def on_message(self, t_ns, message):
        send_ns = self._send_ns                 # flags, reasons and deadlines as the monitor
        out = AvailabilityMonitor.on_message(self, t_ns, message)   # sets them; when SI goes
        self._send_ns = send_ns                 # out, by comparing it whole
        if (der_id_of(message.src) in self.flag and self.si() != self._sent
                and t_ns >= self._quiet_until_ns):
            self._send_ns = t_ns
        return out

    def on_timer(self, t_ns):
        self._send_ns = None
        for der_id, deadline in self.deadline_ns.items():
            if deadline <= t_ns and der_id not in self.expired:
                self.expired.add(der_id)
                self.reason[der_id] = f"no heartbeat for {self.timeout_ns / 1e9:g} s"
        repeat = t_ns >= self._next_repeat_ns
        if repeat:
            self._next_repeat_ns = t_ns + self.period_ns
        return self._publish(t_ns, repeat)


@pytest.mark.parametrize("seed", range(4))
def test_the_availability_monitor_keeps_si_as_rebuilding_it_at_every_heartbeat_would(
        seed: int, config) -> None:
    """SI, its changes and the monitor's timers, kept DER by DER and in a heap, equal those of
    the monitor that rebuilt SI and scanned every deadline at each heartbeat, over random
    heartbeats (late, missing, unavailable, in watchdog fallback, repeated at one instant) and
    a restart (resume)."""
    from adnmesh.wire.messages import MESSAGE_VERSION, Heartbeat

    rng = random.Random(seed)
    kept, scanned = AvailabilityMonitor(config), _MonitorByScans(config)
    ders = list(config.der_ids())
    t, seen, timed_out = 0, 0, 0
    for step in range(3000):
        if step == 1500:
            kept.resume(t), scanned.resume(t)
        due = scanned.next_timer_ns()
        assert kept.next_timer_ns() == due
        if due is not None and due <= t:
            assert kept.on_timer(due) == scanned.on_timer(due)
            assert kept.si() == scanned.si()
            timed_out += bool(scanned.expired)
            continue
        der = rng.choice(ders[: rng.choice([2, len(ders)])])   # some DERs fall silent
        mode = rng.choices(["control", "schedule", "watchdog"], [8, 1, 1])[0]
        beat = Heartbeat(MESSAGE_VERSION, "heartbeat", f"der/{der}", step, t, t,
                         available=rng.random() > 0.15, mode=mode)
        assert kept.on_message(t, beat) == scanned.on_message(t, beat)
        assert kept.si() == scanned.si() and kept.expired == scanned.expired
        seen += 1
        t += rng.choice([0, 0, 1, 10_000_000, 400_000_000, 3_000_000_000])
    assert seen > 1000 and timed_out > 10      # heartbeats timed out too


@pytest.mark.parametrize("seed", range(3))
def test_the_cpfcs_available_set_after_each_heartbeat_is_the_one_a_pass_over_all_acks_gives(
        seed: int, config, table) -> None:
    """The CPFC keeps the DERs in watchdog fallback as a set, not by a pass over every
    acknowledgement at each heartbeat: after every heartbeat (random modes and flags, SI now
    and then, SI going stale) the pending set is the one the pass gives."""
    rng = random.Random(seed)
    cpfc = CPFC(config, GainSchedule(config, table))
    keys, ders = Keys(config.grid), list(config.der_ids())
    t, checked = 0, 0
    for _ in range(400):
        t += rng.choice([10 * MS, 100 * MS, 2000 * MS])
        while cpfc.next_timer_ns() <= t:
            cpfc.on_timer(cpfc.next_timer_ns())
        if rng.random() < 0.1:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {d: rng.random() > 0.3
                                                               for d in ders}},
                                       src="availability"))
            continue
        der = rng.choice(ders)
        mode = rng.choices(["control", "schedule", "watchdog"], [5, 1, 2])[0]
        cpfc.on_message(t, message(keys.of("heartbeat", der), t, {
            "available": rng.random() > 0.2, "mode": mode, "p_y": 0.0}, src=f"der/{der}"))
        base = cpfc._heard(t) if cpfc.si_stale else cpfc.si_available
        by_pass = frozenset(d for d in base if cpfc.acks.get(d, (0, "control"))[1] != "watchdog")
        assert cpfc._pending == (None if by_pass == cpfc.available else by_pass)
        checked += 1
    assert checked > 300
