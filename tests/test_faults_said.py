"""Every fault is said, and handled where it is said (issue 39): in-process runs of the small
runtime case (two WTs, tests/up_runs.py's table), the same nodes and clock as ``adnmesh up``.

- a DER that dies is taken at its schedule by the measurement, so the steps after its death are
  as good as with the DER gone by the scenario (it no longer leaves its last share of P_Y in
  P_IP for good);
- the CPFC notices a stale availability vector (the monitor dead) and follows the DERs'
  heartbeats instead;
- the summary lists the unplanned deaths as faults, every step of the scenario (and why one was
  not executed), and ``up`` refuses a table whose gains are unstable.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from adnmesh.config import Config, load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.control.measurement_point import Measurement
from adnmesh.results.summary import RunSeries, summarize
from adnmesh.sim.local import _LocalRunner
from adnmesh.tuning.table import SchedulingTable, TableEntry
from adnmesh.wire.keys import Keys
from adnmesh.wire.units import ns
from payloads import message

KP2, KI2 = 5e-8, 1.92e-7      # both WTs (tests/test_sim.py: stable, disk margin 1.51, 0 %)
KP1, KI1 = 1e-7, 3.84e-7      # SGen1 alone: the same loop


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    return load_config(configs_dir / "examples" / "runtime-step.yaml")


def schedule(config: Config) -> GainSchedule:
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), KP2, KI2, {"SGen1": 1.0, "SGen2": 1.0}))
    table.add(TableEntry(("SGen1",), KP1, KI1, {"SGen1": 1.0}))
    table.add(TableEntry(("SGen2",), KP1, KI1, {"SGen2": 1.0}))
    return GainSchedule(config, table, on_demand=False)


def with_scenario(config: Config, **changes) -> Config:
    return config.model_copy(update={"scenario": config.scenario.model_copy(update=changes)})


def run(config: Config, faults=()) -> list[dict]:
    """The in-process run with ``faults`` (kind, at s, for s or None, target): its messages
    as dicts, in delivery order."""
    runner = _LocalRunner(config, schedule(config), ns(config.scenario.duration_s))
    for kind, at, duration, target in faults:
        runner.plan.add(kind, ns(at), None if duration is None else ns(duration), **target)
    grants = runner.start()
    while grants:
        grants.extend(runner.step(grants.popleft()))
    bodies = [json.loads(p) for _, p in runner.run.messages]
    return sorted(bodies, key=lambda b: (b["t_deliver_ns"], b["src"], b["type"], b["seq"]))


def steps_of(config: Config, bodies: list[dict]) -> dict[float, object]:
    series = RunSeries()
    for body in bodies:
        series.add(body["type"], body)
    summary = summarize(series, end_ns=ns(config.scenario.duration_s),
                        band_pct=config.constraints.settling_band_pct)
    return {s.t_s: s for s in summary.steps}


# --- a dead DER goes to its schedule ----------------------------------------------------------


def test_a_silent_der_is_taken_at_its_schedule_and_back_when_it_reports(config: Config) -> None:
    """SGen2 (schedule 0.5 MW) reports 1.2 MW until 2 s, then nothing: from 2 s plus the
    watchdog timeout its infeed is its schedule, said once; its first state after that is
    taken as it is, said once."""
    meas, keys = Measurement(config), Keys(config.grid)
    timeout = ns(config.runtime.watchdog_timeout_s)
    events, p_ip = [], {}

    def state(t, der, p_w):
        meas.on_message(t, message(keys.of("der_state", der), t, {
            "p_w": p_w, "setpoint_w": p_w, "mode": "control", "held": 0}, src=f"der/{der}"))

    for t in range(0, ns(6), ns(0.01)):
        state(t, "SGen1", 1e5)
        if t <= ns(2) or t >= ns(5):
            state(t, "SGen2", 1.2e6 if t <= ns(2) else 7e5)
        for out in meas.on_timer(t):
            if out.key == keys.of("p_ip"):
                p_ip[t] = out.body["p_ip_w"]
            else:
                events.append((t, out.body["kind"], out.body["subject"]))
    rest = config.runtime.rest_of_grid_w
    assert p_ip[ns(2) + timeout - ns(0.01)] == rest + 1e5 + 1.2e6     # still its last infeed
    assert p_ip[ns(2) + timeout] == rest + 1e5 + 0.5e6                # its schedule
    assert p_ip[ns(5)] == rest + 1e5 + 7e5
    assert events == [(ns(2) + timeout, "der_silent", "der/SGen2"),
                      (ns(5), "der_reporting", "der/SGen2")]


def test_the_steps_after_a_ders_death_are_those_after_its_leaving(config: Config) -> None:
    """SGen2 (schedule 0.5 MW, carrying half of the +1 MW step of 1 s) dies at 5 s; -1 MW at
    10 s, +1 MW at 20 s. Before the fix its last infeed stayed in P_IP for good: the -1 MW step
    ended 489 kW short (SGen1 at its lower limit), not settled. Now every step after the death
    is within 0.05 s (settling) of the run in which SGen2 leaves by the scenario at 5 s."""
    scenario = {"duration_s": 30, "availability": (),
                "p_ref_steps": tuple(config.scenario.p_ref_steps[0].model_copy(
                    update={"t_s": t, "delta_w": d}) for t, d in ((1, 1e6), (10, -1e6),
                                                                    (20, 1e6)))}
    dead_config = with_scenario(config, **scenario)
    dead = steps_of(dead_config, run(dead_config, [("kill", 5, None, {"agent": "der/SGen2"})]))
    availability = (config.scenario.availability[0].model_copy(
        update={"t_s": 5.0, "ders": ("SGen2",)}),)
    gone_config = with_scenario(config, **{**scenario, "availability": availability})
    gone = steps_of(gone_config, run(gone_config))
    for t in (10.0, 20.0):
        d, g = dead[t], gone[t]
        assert abs(d.steady_error_w) < 0.01 * abs(d.step_w), (t, d)
        assert d.figures.settling_time_s == pytest.approx(g.figures.settling_time_s, abs=0.05)
        assert d.figures.overshoot_pct <= g.figures.overshoot_pct + 0.05


# --- a stale availability vector --------------------------------------------------------------


def test_the_cpfc_follows_the_heartbeats_when_si_stops(config: Config) -> None:
    """The availability monitor dies at 3 s; SGen2 leaves (scenario) at 8 s. Before, the CPFC
    kept the gains of both WTs to the end and said nothing. Now it says that SI is stale one SI
    timeout after the last SI, and switches to SGen1's entry when SGen2's heartbeat says it
    left (8.1 s, one PI period later), bumplessly."""
    bodies = run(config, [("kill", 3, None, {"agent": "availability"})])
    cpfc = [b for b in bodies if b["src"] == "cpfc"]
    stale = [b for b in cpfc if b["type"] == "event" and b["kind"] == "si_stale"]
    last_si = max(b["t_deliver_ns"] for b in bodies if b["type"] == "si")
    timeout = ns(config.runtime.heartbeat_timeout_s)
    assert len(stale) == 1 and last_si + timeout < stale[0]["t_send_ns"] <= \
        last_si + timeout + ns(config.runtime.pi_period_s)
    (switch,) = [b for b in cpfc if b["type"] == "p_y" and "switch" in b]
    assert ns(8.1) <= switch["t_send_ns"] <= ns(8.1) + ns(config.runtime.pi_period_s)
    assert sorted(switch["w"]) == ["SGen1"] and (switch["kp"], switch["ki"]) == (KP1, KI1)
    assert switch["p_y"] == switch["switch"]["p_y_before"] * switch["switch"]["scale"]


def test_si_rules_again_when_it_returns(config: Config) -> None:
    """An outage of the availability_to_cpfc link from 2 to 6 s: stale from 2 s + the timeout,
    back with the first SI after 6 s; the same gain switch (SI's) at 8.2 s as without it."""
    bodies = run(config, [("link_outage", 2, 4, {"link": "availability_to_cpfc"})])
    kinds = [(b["kind"], b["t_send_ns"]) for b in bodies
             if b["type"] == "event" and b["src"] == "cpfc"]
    assert [k for k, _ in kinds] == ["si_stale", "si_back"]
    assert ns(6) < kinds[1][1] < ns(7.2)
    (switch,) = [b for b in bodies if b["type"] == "p_y" and "switch" in b]
    assert switch["t_send_ns"] == ns(8.2)


def test_a_restarted_cpfc_without_si_starts_from_the_heartbeats(config: Config) -> None:
    """A CPFC restarted at 20 s while the monitor is dead: no SI comes; SGen1's heartbeats say
    it follows, SGen2's that it left. Before, the CPFC resumed after the heartbeat timeout with
    the gains of every DER (its state at t = 0); now with SGen1's, and says why."""
    from adnmesh.control.cpfc_controller import CPFC

    cpfc, keys = CPFC(config, schedule(config)), Keys(config.grid)
    start = ns(20)
    cpfc.resume(start)
    out = []
    while cpfc.next_timer_ns() < start + ns(3):
        t = cpfc.next_timer_ns()
        if (t - start) % ns(1) == ns(0.5):
            for der, available in (("SGen1", True), ("SGen2", False)):
                cpfc.on_message(t, message(keys.of("heartbeat", der), t - ns(0.1), {
                    "available": available, "mode": "control" if available else "schedule",
                    "p_y": 0.1, "entry": 0}, src=f"der/{der}"))
        cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": -2.5e6}, src="measurement"))
        out += [(t, o.body) for o in cpfc.on_timer(t)]
    p_y = [(t, b) for t, b in out if "p_y" in b]
    events = [b["kind"] for _, b in out if "kind" in b]
    assert p_y and p_y[0][0] == start + ns(config.runtime.heartbeat_timeout_s)
    assert sorted(p_y[0][1]["w"]) == ["SGen1"] and p_y[0][1]["kp"] == KP1
    assert events[:2] == ["si_stale", "resume"]


# --- the summary: unplanned deaths, every step of the scenario ---------------------------------


def _event(t_ns: int, src: str, kind: str, subject: str, seq: int) -> dict:
    return {"v": 1, "type": "event", "src": src, "seq": seq, "t_send_ns": t_ns,
            "t_deliver_ns": t_ns, "level": "WARNING", "kind": kind, "text": kind,
            "subject": subject}


def test_an_agent_up_lost_is_a_fault_of_the_summary_with_its_detection() -> None:
    """``up`` lost der/SGen2 at 5 s (its process died: an ``agent_lost`` event, no fault
    message); the measurement took it at its schedule at 6 s, the monitor marked it unavailable
    at 7.5 s. Before, the summary's fault list was empty; now the death is fault 2 (after the
    injected one), detected by the measurement 1 s after, open to the end; and it ends the
    window of the step before it."""
    series = RunSeries()
    series.add("fault", {"v": 1, "type": "fault", "src": "up", "seq": 0, "t_send_ns": 0,
                         "t_deliver_ns": ns(1), "fault_id": 1, "kind": "link_outage",
                         "link": "cpfc_to_der", "start_ns": ns(1), "end_ns": ns(2)})
    for t, w in ((0, 0.0), (ns(3), 1e6)):
        series.add("p_ref", {"src": "cpfc", "t_send_ns": t, "p_ref_w": w})
    for k in range(1000):
        series.add("p_ip", {"src": "measurement", "t_send_ns": k * ns(0.01),
                            "p_ip_w": 0.0 if k < 300 else 1e6})
    for seq, (t, src, kind, subject) in enumerate((
            (ns(5), "up", "agent_lost", "der/SGen2"),
            (ns(6), "measurement", "der_silent", "der/SGen2"),
            (ns(7.5), "availability", "unavailable", "der/SGen2"))):
        series.add("event", _event(t, src, kind, subject, seq))
    summary = summarize(series, end_ns=ns(10))
    lost = summary.faults[-1]
    assert (lost.fault_id, lost.kind, lost.target) == (2, "lost", "der/SGen2")
    assert (lost.start_s, lost.end_s) == (5.0, None)
    assert (lost.detected_by, lost.detection_delay_s) == ("measurement", 1.0)
    assert [s.window_s for s in summary.steps] == [2.0]           # 3 s to the death at 5 s
    assert summary.to_json()["faults"][-1]["kind"] == "lost"


def test_every_step_of_the_scenario_is_said_also_those_its_dead_source_never_sent(
        config: Config) -> None:
    """Steps at 1, 10 and 20 s. The CPFC (which sends P_ref) killed at 5 s without restart:
    before, the steps at 10 and 20 s vanished from the summary without a word; now each is
    listed as not executed, with why. Killed at 8 s and restarted at 12 s: the step at 10 s was
    executed late, at 12 s, when the restarted CPFC applied it."""
    scenario = {"duration_s": 25, "availability": (),
                "p_ref_steps": tuple(config.scenario.p_ref_steps[0].model_copy(
                    update={"t_s": t, "delta_w": d}) for t, d in ((1, 1e6), (10, -1e6),
                                                                    (20, 1e6)))}
    case = with_scenario(config, **scenario)
    planned = [(s.t_s, s.delta_w) for s in case.scenario.p_ref_steps]

    def summary_of(faults):
        series = RunSeries()
        for body in run(case, faults):
            series.add(body["type"], body)
        return summarize(series, end_ns=ns(25), planned_steps=planned,
                         sample_s=case.runtime.pi_period_s)

    dead = summary_of([("kill", 5, None, {"agent": "cpfc"})])
    assert [s.t_s for s in dead.steps] == [1.0]
    assert [(s.t_s, s.status) for s in dead.scenario_steps] == [
        (1, "executed"), (10, "not executed"), (20, "not executed")]
    assert dead.scenario_steps[1].reason == \
        "the CPFC, which sends P_ref, was killed at 5 s (fault 1)"
    from adnmesh.results.summary import format_summary
    lines = [x for x in format_summary(dead) if isinstance(x, str)]
    assert "  scenario step at 20 s (+1.000 MW): NOT EXECUTED: the CPFC, which sends P_ref, " \
        "was killed at 5 s (fault 1)" in lines
    late = summary_of([("kill", 8, 4, {"agent": "cpfc"})]).scenario_steps
    assert (late[1].status, late[1].executed_s) == ("late", 12.0)
    assert late[1].reason == \
        "the CPFC, which sends P_ref, was killed at 8 s (fault 1) and restarted at 12 s"
    assert late[2].status == "executed"
    ended = summarize(RunSeries(), end_ns=ns(15), planned_steps=planned,
                      extra={"ended": "SIGINT"}).scenario_steps
    assert ended[2].reason == "the run ended at 15 s (SIGINT)"


# --- a table with unstable gains ----------------------------------------------------------------


def test_the_unstable_loops_of_a_table_are_found(config: Config) -> None:
    """The test table is stable; with SGen1's entry at 30 times its gains it is not, nor is a
    static pair that large on any subset; NaN gains are not certifiable either."""
    import dataclasses

    from adnmesh.tuning.table_check import unstable_gains

    table = schedule(config).table
    subsets = [("SGen1", "SGen2"), ("SGen1",)]
    assert unstable_gains(config, table, subsets) == []
    entry = table.lookup(["SGen1"])
    table.add(dataclasses.replace(entry, kp=30 * entry.kp, ki=30 * entry.ki))
    table.static = dataclasses.replace(entry, ders=("SGen1", "SGen2"), kp=60 * KP2,
                                       ki=60 * KI2, w={"SGen1": 1.0, "SGen2": 1.0})
    found = unstable_gains(config, table, subsets)
    assert [(u.what, u.ders) for u in found] == [
        ("entry", ("SGen1",)), ("static", ("SGen1",)), ("static", ("SGen2",)),
        ("static", ("SGen1", "SGen2"))]
    assert all(u.poles > 0 for u in found)
    assert found[0].describe().startswith(
        f"entry SGen1 (K_P {30 * entry.kp:.4g} 1/W, K_I {30 * entry.ki:.4g} 1/(W s)): ")
    table.static = dataclasses.replace(table.static, kp=math.nan)
    assert "gains not finite and positive" in unstable_gains(config, table, [])[-1].describe()


def test_up_refuses_a_table_with_unstable_gains_before_starting_anything(
        tmp_path: Path) -> None:
    """Before, ``up`` ran a table whose gains were unstable without a word (the probe: 151.7 %
    overshoot). Now it says which loop in one line and exits 2; no agent, no recording."""
    import subprocess
    import sys

    from adnmesh.tuning.table import load_table, save_table
    from up_runs import up_argv, write_case

    config_path, table_path = write_case(tmp_path)
    table = load_table(table_path)
    entry = table.lookup(["SGen1", "SGen2"])
    table.add(entry.__class__(entry.ders, 30 * entry.kp, 30 * entry.ki, entry.w))
    save_table(table, table_path)
    out = tmp_path / "refused.mcap"
    result = subprocess.run(up_argv(config_path, table_path, out), cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "gains not certified stable, refusing to run them: entry SGen1, SGen2 " in line
    assert "closed-loop pole(s) in the right half-plane; retune with 'adnmesh tune " in line
    assert not out.exists() and "Traceback" not in result.stderr
