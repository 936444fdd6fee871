"""The grid guard, the tap changer and the CPFC's answer to them, as state machines
(docs/method.md#grid-guard, docs/models.md#tap-changer): the direction logic with its
hysteresis in value and time, block mode, violation episodes, the tap changer's delay, band and
range, and the CPFC leaving blocked DERs out bumplessly or holding."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from adnmesh.config import Config, GridLimits, Guard, load_config
from adnmesh.control.cpfc_controller import CPFC, GainSchedule
from adnmesh.control.grid_guard import GridGuard, GuardValues
from adnmesh.control.tap_changer import TapChangerControl
from adnmesh.grid.sensitivity import LimitSensitivities
from adnmesh.tuning.table import SchedulingTable, TableEntry
from adnmesh.wire.keys import Keys
from msgspec import UNSET
from payloads import message
from test_control import config, der_grid  # noqa: F401 - config: the fixture (runtime-step.yaml)

MS = 1_000_000
DERS = ("A", "B", "C")


SENS = LimitSensitivities(        # 2 buses, 1 line, 1 trafo, 3 DERs (p.u./W, %/W)
    vm_pu=np.ones(2), line_pct=np.zeros(1), trafo_pct=np.zeros(1),
    dv_dp=np.array([[1e-8, 5e-9, 1e-9], [2e-9, 2e-9, 2e-9]]),
    dv_dq=np.array([[3e-8, 1e-8, 1e-9], [1e-9, 1e-9, 1e-9]]),
    dline_dp=np.array([[4e-6, -1e-6, 0.0]]), dline_dq=np.zeros((1, 3)),
    dtrafo_dp=np.array([[1e-6, 1e-6, 1e-6]]), dtrafo_dq=np.zeros((1, 3)), method="test")


def values(v0=1.0, v1=1.0, line=50.0, trafo=40.0) -> GuardValues:
    return GuardValues(np.array([v0, v1]), np.array([line]), np.array([trafo]),
                       ("bus X", "bus Y"), ("line L",), ("trafo T",))


class Counter:
    """Sensitivities on demand, counted."""

    def __init__(self, sens=SENS) -> None:
        self.sens, self.calls = sens, 0

    def __call__(self):
        self.calls += 1
        return self.sens


def guard(mode="directional", reactive=False, **settings) -> GridGuard:
    return GridGuard(Guard(mode=mode, **settings), GridLimits(), DERS, reactive)


def test_a_voltage_near_its_upper_limit_blocks_the_ders_that_raise_it() -> None:
    """Bus X at 1.095 p.u. (engages at 1.09): A raises it most, B by half (≥ 0.2 of A), C by
    a tenth (below the share): A and B may not raise P; lowering P is free."""
    g, sens = guard(), Counter()
    changed, events = g.observe(0, values(v0=1.095), sens)
    assert changed and sens.calls == 1
    assert g.state() == {"p_up": ["A", "B"], "p_down": [], "q_up": [], "q_down": [],
                         "hold": False}
    (event,) = events
    assert event["kind"] == "guard_block" and "A, B blocked from raising P" in event["text"]
    assert "bus X at 1.0950 p.u." in event["text"]
    changed, events = g.observe(10 * MS, values(v0=1.096), sens)
    assert not changed and events == [] and sens.calls == 1       # refreshed only every 1 s


def test_release_needs_the_release_level_for_the_release_time() -> None:
    """Hysteresis: below the engaging level but above the release level (1.085) nothing is
    released; inside it, only after release_s (2 s) without a break."""
    g, sens = guard(), Counter()
    g.observe(0, values(v0=1.095), sens)
    for t_ms, v in ((100, 1.088), (3000, 1.087)):                 # between the levels
        assert g.observe(t_ms * MS, values(v0=v), sens) == (False, [])
    g.observe(3100 * MS, values(v0=1.08), sens)                    # inside: the clock starts
    assert g.observe(4000 * MS, values(v0=1.09), sens)[0] is False  # a break: starts again
    g.observe(4100 * MS, values(v0=1.08), sens)
    assert g.observe(6000 * MS, values(v0=1.08), sens)[0] is False  # 1.9 s
    changed, events = g.observe(6100 * MS, values(v0=1.08), sens)   # 2.0 s
    assert changed and g.state()["p_up"] == []
    assert [e["kind"] for e in events] == ["guard_release"]
    assert "A, B free again for raising P" in events[0]["text"]


def test_a_low_voltage_blocks_lowering_and_a_loading_blocks_by_its_flow() -> None:
    g = guard()
    g.observe(0, values(v1=0.905), Counter())          # bus Y: all three lower it equally
    assert g.state()["p_down"] == ["A", "B", "C"] and g.state()["p_up"] == []
    g = guard()
    g.observe(0, values(line=97.0), Counter())         # line L: A loads it, B relieves it
    assert g.state()["p_up"] == ["A"] and g.state()["p_down"] == ["B"]


def test_reactive_power_is_guarded_only_with_a_q_loop() -> None:
    g = guard(reactive=True)
    g.observe(0, values(v0=1.095), Counter())
    assert g.state()["q_up"] == ["A", "B"] and g.state()["p_up"] == ["A", "B"]
    g = guard(reactive=False)
    g.observe(0, values(v0=1.095), Counter())
    assert g.state()["q_up"] == []


def test_a_der_blocked_once_stays_blocked_while_the_limit_is_engaged() -> None:
    """A refresh that finds B less sensitive does not free it before the limit is released."""
    later = replace(SENS, dv_dp=np.array([[1e-8, 1e-10, 1e-9], [2e-9, 2e-9, 2e-9]]))
    g = guard()
    g.observe(0, values(v0=1.095), Counter())
    g.observe(1000 * MS, values(v0=1.095), Counter(later))
    assert g.state()["p_up"] == ["A", "B"]


def test_off_only_counts_and_block_holds_the_whole_control() -> None:
    off = guard(mode="off")
    changed, events = off.observe(0, values(v0=1.12), Counter())
    assert not changed and off.state()["p_up"] == [] and off.watched == {}
    assert [e["kind"] for e in events] == ["limit_violated"]
    block, sens = guard(mode="block"), Counter()
    assert block.observe(0, values(v0=1.095), sens)[0] is False    # near is not violated
    changed, events = block.observe(10 * MS, values(v0=1.101), sens)
    assert changed and block.hold and sens.calls == 0
    assert [e["kind"] for e in events] == ["limit_violated", "guard_hold"]
    assert block.observe(20 * MS, values(v0=1.097), sens)[0] is False   # not 1.095 yet
    block.observe(30 * MS, values(v0=1.094), sens)
    changed, events = block.observe(2030 * MS, values(v0=1.094), sens)
    assert changed and not block.hold and "guard_resume" in [e["kind"] for e in events]


def test_a_violation_episode_is_said_with_its_worst_value_and_where() -> None:
    g = guard(mode="off")
    g.observe(0, values(trafo=101.0), Counter())
    g.observe(10 * MS, values(trafo=104.5), Counter())
    assert g.observe(20 * MS, values(trafo=103.0), Counter())[1] == []
    (end,) = g.observe(30 * MS, values(trafo=99.0), Counter())[1]
    assert end["kind"] == "limit_restored" and "after 0.03 s" in end["text"]
    assert "trafo trafo T at 104.5 %" in end["text"]
    assert g.counts["violations"] == 1


# --- the tap changer ------------------------------------------------------------------------


def test_the_tap_changer_steps_after_its_delay_the_way_back_into_the_band() -> None:
    tap = TapChangerControl(1.02, 0.015, 5.0, position=0, tap_min=-2, tap_max=2,
                            raises_voltage=-1)                       # tap on the HV side
    assert tap.observe(0, 1.04) == (0, "")                           # outside: clock starts
    assert tap.observe(4_990 * MS, 1.04) == (0, "")
    assert tap.observe(5_000 * MS, 1.04) == (1, "") and tap.position == 1   # higher ratio
    assert tap.observe(6_000 * MS, 1.03) == (0, "")                  # inside: clock stops
    assert tap.observe(7_000 * MS, 1.00) == (0, "")                  # below: starts again
    assert tap.observe(12_000 * MS, 1.00) == (-1, "") and tap.position == 0
    lv = TapChangerControl(1.0, 0.01, 1.0, 0, -1, 1, raises_voltage=1)
    lv.observe(0, 0.97)
    assert lv.observe(1000 * MS, 0.97) == (1, "")                    # LV side: up raises


def test_the_tap_changer_stays_at_the_end_of_its_range_and_says_so_once() -> None:
    tap = TapChangerControl(1.0, 0.01, 1.0, position=2, tap_min=-2, tap_max=2,
                            raises_voltage=-1)
    tap.observe(0, 1.05)
    step, note = tap.observe(1000 * MS, 1.05)
    assert step == 0 and "end of its range (position 2)" in note
    assert tap.observe(2000 * MS, 1.05) == (0, "") and tap.moves == 0
    with pytest.raises(ValueError):
        TapChangerControl(1.0, 0.01, 1.0, position=3, tap_min=-2, tap_max=2, raises_voltage=1)


# --- the CPFC -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def table(config: Config) -> SchedulingTable:
    """test_control's ``config``: two WTs (SGen1 from 0, SGen2 with a 0.5 MW schedule), a
    +1 MW step at 1 s; gains for both, each alone."""
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), 5e-8, 1.92e-7, {"SGen1": 1.0, "SGen2": 0.8}))
    table.add(TableEntry(("SGen1",), 1e-7, 3.84e-7, {"SGen1": 1.0}))
    table.add(TableEntry(("SGen2",), 1e-7, 3.84e-7, {"SGen2": 1.0}))
    return table


def drive(cpfc: CPFC, until_ns: int, p_meas, guard_at: dict) -> list:
    """The CPFC's samples to ``until_ns``, a grid_guard body delivered at the times of
    ``guard_at``; returns ``(t, key, body)`` of what it sends."""
    keys = Keys(cpfc.config.grid)
    out = []
    while cpfc.next_timer_ns() < until_ns:
        t = cpfc.next_timer_ns()
        if t % (1000 * MS) == 0:                 # SI, as a live availability monitor sends it
            cpfc.on_message(t, message(keys.of("si"), t, {"si": dict.fromkeys(
                cpfc.config.der_ids(), True)}, src="availability"))
        if t in guard_at:
            for o in cpfc.on_message(t, message(keys.of("grid_guard"), t, guard_at[t],
                                                src="measurement")):
                out.append((t, o.key, o.body))
        if p_meas(t) is not None:                # None: no measurement at that sample
            cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": p_meas(t)},
                                       src="measurement"))
        out += [(t, o.key, o.body) for o in cpfc.on_timer(t)]
    return out


def outputs(out, config) -> list:
    key = Keys(config.grid).of("p_y")
    return [(t, b) for t, k, b in out if k == key]


def test_the_cpfc_leaves_a_der_blocked_upwards_out_bumplessly(config, table) -> None:
    """Moving up after the step, SGen2 is blocked up at 2 s: at the next sample the CPFC
    switches to SGen1's entry and says why; SGen2 keeps the power it was commanded (``keep``:
    a cap, not a return to its schedule) and SGen1 its own, so nothing moves; when the guard
    frees SGen2 at 3 s the entry of both returns with their total commanded power kept."""
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="directional")
    out = drive(cpfc, 3500 * MS, lambda t: -2.5e6 + 0.5e6 * (t > 1.5e9),
                {2000 * MS: {"p_up": ["SGen2"]}, 3000 * MS: {}})
    events = [b for t, k, b in out if k.endswith("event/cpfc")]
    assert any("SGen2 left out moving up" in e["text"] for e in events)
    switched = [(t, b) for t, b in outputs(out, config) if "switch" in b]
    assert [t for t, _ in switched] == [2000 * MS, 3000 * MS]
    t, body = switched[0]
    assert body["w"] == {"SGen1": 1.0} and body["switch"].keep == ["SGen2"]
    kept_w = body["switch"].p_y_before * 0.8 * 2e6                  # SGen2's share, kept
    assert body["p_y"] == pytest.approx(body["switch"].p_y_before, rel=1e-9)  # SGen1's too
    assert body["switch"].handover_s is UNSET                        # nothing moves
    t, back = switched[1]
    assert back["w"] == {"SGen1": 1.0, "SGen2": 0.8} and back["switch"].keep is UNSET
    before = back["switch"].p_y_before * 2e6 + kept_w                 # SGen1 + SGen2 kept
    assert back["p_y"] * (2e6 + 0.8 * 2e6) == pytest.approx(before, rel=1e-6)


def test_when_every_der_is_blocked_that_way_the_output_stops_there(config, table) -> None:
    """Both WTs blocked up: P_Y no longer rises however large the error; it may fall."""
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="directional")
    out = drive(cpfc, 4000 * MS, lambda t: -2.5e6 if t < 3e9 else 0.0,
                {2000 * MS: {"p_up": ["SGen1", "SGen2"]}})
    p_y = dict(outputs(out, config))
    held = [p_y[t]["p_y"] for t in range(2010 * MS, 3000 * MS, 10 * MS)]
    assert held == [held[0]] * len(held) and held[0] > 0
    assert p_y[3500 * MS]["p_y"] < held[0]                           # down is free


def test_block_mode_holds_the_output_until_the_guard_lets_go(config, table) -> None:
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="block")
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6,
                {1500 * MS: {"hold": True}, 2500 * MS: {"hold": False}})
    p_y = dict(outputs(out, config))
    assert p_y[1500 * MS]["hold"] == "grid" and p_y[2490 * MS]["hold"] == "grid"
    assert p_y[1500 * MS]["p_y"] == p_y[2490 * MS]["p_y"]
    assert "hold" not in p_y[2500 * MS]
    one_sample = 1.92e-7 * 0.01 * 1e6                  # K_I T e: the integrator, no jump
    assert p_y[2500 * MS]["p_y"] - p_y[2490 * MS]["p_y"] == pytest.approx(one_sample)
    assert p_y[2510 * MS]["p_y"] - p_y[2500 * MS]["p_y"] == pytest.approx(one_sample)


# --- what the summary says ------------------------------------------------------------------


def test_the_summary_counts_violations_the_guards_time_and_its_cost() -> None:
    """A run of 10 s, P_ref +1 MW at 1 s; the guard blocks from 2 s to 4 s while P_IP stays
    0.5 MW short; one violation episode of 0.3 s at bus X; the tap changer steps twice."""
    from adnmesh.results.summary import RunSeries, grid_line, summarize

    series = RunSeries()
    env = {"src": "measurement", "seq": 0, "v": 1}
    series.add("p_ref", {"t_send_ns": 0, "p_ref_w": 0.0, **env})
    series.add("p_ref", {"t_send_ns": 1000 * MS, "p_ref_w": 1e6, **env})
    for k in range(1001):
        t = k * 10 * MS
        p = 0.0 if t < 1000 * MS else 0.5e6 if t < 6000 * MS else 1e6
        series.add("p_ip", {"t_send_ns": t, "p_ip_w": p, **env})
    for k in range(1, 11):
        series.add("grid_state", {
            "t_send_ns": k * 1000 * MS, "v_min_pu": 1.0, "v_max_pu": 1.105 if k == 3 else 1.09,
            "line_loading_max_pct": 50.0, "trafo_loading_max_pct": 40.0, "q_ip_var": 0.0,
            "samples": 100, "outside_band": 30 if k == 3 else 0, "not_converged": 0,
            "outside_s": 0.3 if k == 3 else 0.0, "v_max_at": "bus X" if k == 3 else "bus Y",
            "tap_pos": 0 if k < 5 else -1 if k < 8 else -2, **env})
    series.add("grid_guard", {"t_send_ns": 2000 * MS, "p_up": ["A"], **env})
    series.add("grid_guard", {"t_send_ns": 3000 * MS, "p_up": ["A"], **env})
    series.add("grid_guard", {"t_send_ns": 4000 * MS, **env})
    for t, kind in ((2000, "guard_block"), (2700, "limit_violated"), (3000, "limit_restored"),
                    (5000, "tap"), (8000, "tap")):
        series.add("event", {"t_send_ns": t * MS, "level": "INFO", "kind": kind, "text": "x",
                             **env})
    grid = summarize(series, end_ns=10_000 * MS).grid
    assert (grid.violations, grid.outside_s, grid.v_max_pu, grid.v_max_at) == (
        1, 0.3, 1.105, "bus X")
    assert grid.guard_blocks == 1 and grid.guarded_s == pytest.approx(2.0)
    assert grid.energy_short_kwh == pytest.approx(0.5e6 * 2.0 / 3.6e6, rel=1e-3)
    assert grid.steps_short == ()                      # settled at 6 s, inside its window
    assert (grid.tap_moves, grid.tap_range) == (2, (-2, 0))
    text = grid_line(grid)
    assert "1 violation(s), 0.30 s outside the band; extremes 1.1050 p.u. at bus X" in text
    assert "grid guard: acted 1 time(s), 2.00 s" in text and "0.278 kWh" in text
    assert "tap changer: 2 step(s), positions -2 to 0" in text


def test_the_gate_refuses_a_guard_state_naming_a_der_the_run_lacks() -> None:
    from adnmesh.wire.envelope import decode
    from adnmesh.wire.gate import names_known_ders
    from payloads import payload

    key = Keys("g").of("grid_guard")
    known = frozenset({"SGen1", "SGen2"})
    good = decode(key, payload(key, {"p_up": ["SGen1"], "q_down": ["SGen2"]}))
    bad = decode(key, payload(key, {"p_down": ["SGen1", "SGen9"]}))
    assert names_known_ders(good, known) and not names_known_ders(bad, known)


def test_the_tap_changer_on_the_extremes_lowers_for_the_highest_raises_for_the_lowest() -> None:
    tap = TapChangerControl(1.0, 0.015, 1.0, position=0, tap_min=-3, tap_max=3,
                            raises_voltage=-1)
    assert tap.observe_extremes(0, 0.95, 1.095, 0.91, 1.09) == (0, "")
    assert tap.observe_extremes(1000 * MS, 0.95, 1.095, 0.91, 1.09) == (1, "")  # lower
    assert tap.observe_extremes(1500 * MS, 0.95, 1.08, 0.91, 1.09) == (0, "")
    tap.observe_extremes(2000 * MS, 0.905, 1.08, 0.91, 1.09)
    assert tap.observe_extremes(3000 * MS, 0.905, 1.08, 0.91, 1.09) == (-1, "")  # raise
    tap.observe_extremes(4000 * MS, 0.905, 1.095, 0.91, 1.09)                    # both out:
    assert tap.observe_extremes(5000 * MS, 0.905, 1.095, 0.91, 1.09)[0] == 1      # lower


def test_block_mode_still_follows_a_move_back_towards_the_schedules(config, table) -> None:
    """While the guard holds, an error that would move the DERs further up is held against,
    one that moves them back down (relieving the limit) is followed."""
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="block")
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6 if t < 2e9 else -1.0e6,
                {1500 * MS: {"hold": True}})
    p_y = dict(outputs(out, config))
    assert p_y[1990 * MS]["p_y"] == p_y[1500 * MS]["p_y"]           # up: held
    assert p_y[2500 * MS]["p_y"] < p_y[2000 * MS]["p_y"] < p_y[1990 * MS]["p_y"]   # down
    assert p_y[2500 * MS]["hold"] == "grid"


def test_a_reference_beyond_reach_is_clipped_and_said_not_wound_up(config, table) -> None:
    """P_ref steps to -1.5 MW but the DERs can reach only -2.0 MW within the grid limits: the
    CPFC controls to -2.0 MW (at P_IP -2.0 MW its output stays put), records the P_ref asked
    for, and says so once."""
    cpfc = CPFC(config, GainSchedule(config, table), reachable=(-3.0e6, -2.0e6))
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6 if t < 1e9 else -2.0e6, {})
    refs = [b["p_ref_w"] for t, k, b in out if k.endswith("scenario/p_ref")]
    assert refs == [-2.5e6, -1.5e6]
    clipped = [b for t, k, b in out if k.endswith("event/cpfc")
               and b["kind"] == "reference_clipped"]
    assert len(clipped) == 1 and "controlled to -2.0000 MW" in clipped[0]["text"]
    p_y = dict(outputs(out, config))
    assert p_y[2990 * MS]["p_y"] == p_y[1000 * MS]["p_y"]       # no error, no wind-up
    free = CPFC(config, GainSchedule(config, table))
    p_y_free = dict(outputs(drive(free, 3000 * MS, lambda t: -2.5e6 if t < 1e9 else -2.0e6,
                                  {}), config))
    assert p_y_free[2990 * MS]["p_y"] > p_y_free[1000 * MS]["p_y"] + 0.1   # chases it


def test_the_reachable_range_of_the_reference_case(configs_dir) -> None:
    """The extent of 1-MV-rural's feasible region at lW with the DERs' Q at 0 (a P-only run):
    P_IP 10.95 to 23.19 MW (no grid limit binds: every DER between 0 and its available
    power), against the power flows at those ends."""
    from adnmesh.control.operating_point import grid_solver, reachable_ranges

    config = load_config(configs_dir / "simbench.yaml")
    (p_min, p_max), _ = reachable_ranges(config)
    solver = grid_solver(config)
    from adnmesh.control.operating_point import available_power_w
    top = solver.solve([available_power_w(config)[d.id] for d in config.ders],
                       [0.0] * len(config.ders)).p_ip_w
    bottom = solver.solve([0.0] * len(config.ders), [0.0] * len(config.ders)).p_ip_w
    assert p_max == pytest.approx(top, abs=1e3) and p_min == pytest.approx(bottom, abs=1e3)


def test_check_says_the_limits_the_reach_and_the_tap_changer(configs_dir, tmp_path,
                                                             capsys) -> None:
    """``check`` (and ``up``, before any agent starts) says the guard, what is reachable and
    the tap changer; a tap changer the net lacks is a one-line error."""
    from adnmesh.cli import main

    assert main(["check", str(configs_dir / "examples" / "stress-rural1-lW-tap.yaml")]) == 0
    out = capsys.readouterr().out
    assert "guard block (holds the control while a limit is violated)" in out
    assert "reachable within the limits: P_IP 30.3" in out
    assert ("tap changer of HV1-MV1.101-Trafo1, HV1-MV1.101-Trafo2: positions -9 to 9, at 0"
            in out)
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"extends: {configs_dir / 'simbench.yaml'}\n"
                   "grid_model: {tap_changer: {trafo: 7}}\n")
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the net has 2 transformer(s), no 7" in err


def test_no_release_while_the_loop_presses_the_way_it_blocks() -> None:
    """Every DER in use held up: a block of raising P is kept, however far inside the release
    level the voltage is; once they no longer press, release_s later it goes."""
    g, sens = guard(), Counter()
    g.observe(0, values(v0=1.095), sens)
    up = frozenset({("p", 1)})
    for t_ms in (100, 3000, 6000):
        assert g.observe(t_ms * MS, values(v0=1.07), sens, up) == (False, [])
    assert g.state()["p_up"] == ["A", "B"]
    g.observe(6100 * MS, values(v0=1.07), sens, frozenset({("p", -1)}))   # not that way
    changed, events = g.observe(8100 * MS, values(v0=1.07), sens)
    assert changed and g.state()["p_up"] == [] and events[0]["kind"] == "guard_release"


def output(der, kind: str, t_ms: int, fields: dict, entry: int, w=None, switch=None) -> None:
    """Deliver a P_Y or Q_Y (``kind``) of table entry ``entry`` to ``der`` at ``t_ms``, with
    the weights ``w`` and the switch record ``switch`` if given."""
    body = {**fields, "kp": 1e-7, "ki": 1e-7, "entry": entry}
    if w is not None:
        body["w"] = w
    if switch is not None:
        body["switch"] = switch
    der.on_message(t_ms * MS, message(Keys(der_grid(der)).of(kind), t_ms * MS, body,
                                      src="cpfc"))


def test_a_der_the_switch_keeps_holds_its_power_until_the_next_switch(config) -> None:
    """SGen2 at P_Y 0.5 (0.5 MW above its 0.5 MW schedule) is left out with ``keep``: it holds
    1.3 MW whatever P_Y does; the next switch that gives it a weight hands it over."""
    from adnmesh.control.der_controller import DERController
    from adnmesh.wire.messages import Switch

    (der_config,) = config.ders_by_id(["SGen2"])
    der = DERController(der_config, config, 2e6)

    def command(t_ms, p_y, entry, w=None, switch=None):
        output(der, "p_y", t_ms, {"p_y": p_y, "p_ref_w": 0.0}, entry, w, switch)

    command(0, 0.5, 0, {"SGen1": 1.0, "SGen2": 0.8})
    assert der.setpoint_w == pytest.approx(0.5 * 0.8 * 2e6 + 0.5e6)
    command(100, 0.5, 1, {"SGen1": 1.0}, Switch(0.5, 0.5, 1e-7, 1e-7, keep=["SGen2"]))
    command(200, 0.9, 1)
    command(5000, 0.1, 1)
    assert der.setpoint_w == pytest.approx(1.3e6)
    command(6000, 0.1, 2, {"SGen1": 1.0, "SGen2": 0.8},
            Switch(0.1, 0.1, 1e-7, 1e-7, handover_s=10.0))
    command(11000, 0.1, 2)                       # half way from 1.3 MW to its 0.66 MW share
    assert der.setpoint_w == pytest.approx(0.5 * (1.3e6 + 0.1 * 0.8 * 2e6 + 0.5e6))


def test_a_measurement_outage_in_a_grid_hold_holds_for_the_measurement(config, table) -> None:
    """Measurements stop at 2 s while the guard holds: the CPFC holds for the measurement
    (undoing what stale samples did), not integrating a stale error back and forth."""
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="block")
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6 if t < 2e9 else None,
                {1500 * MS: {"hold": True}})
    p_y = dict(outputs(out, config))
    assert p_y[2990 * MS]["hold"] == "measurement"
    assert p_y[2990 * MS]["p_y"] == p_y[1500 * MS]["p_y"]


def test_blocking_the_last_der_keeps_the_set_the_caps_and_the_output(config, table) -> None:
    """SGen2 blocked up at 2 s (capped), SGen1 too at 2.5 s: no switch back to both, SGen2
    stays capped, and P_Y does not rise when the error grows (K_P's part held too); one
    event says the output no longer moves up."""
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="directional")
    out = drive(cpfc, 4000 * MS, lambda t: -2.5e6 if t < 3e9 else -3.5e6,
                {2000 * MS: {"p_up": ["SGen2"]}, 2500 * MS: {"p_up": ["SGen1", "SGen2"]}})
    p_y = dict(outputs(out, config))
    assert [t for t, b in p_y.items() if "switch" in b] == [2000 * MS]
    assert cpfc._kept.keys() == {"SGen2"}
    assert p_y[3990 * MS]["p_y"] == p_y[2500 * MS]["p_y"]
    stops = [b["text"] for t, k, b in out if k.endswith("event/cpfc")
             and "no longer moves up" in b["text"]]
    assert len(stops) == 1


def test_blocks_apply_without_a_step_once_the_ders_have_moved(config, table) -> None:
    """No P_ref step: SGen2 blocked up at 0.5 s while the DERs stand at their schedules
    (direction 0: nothing to leave out); P_IP drops at 2 s, the DERs move up, and SGen2 is
    left out then."""
    from adnmesh.config import Scenario

    still = config.model_copy(update={"scenario": Scenario(duration_s=5.0)})
    cpfc = CPFC(still, GainSchedule(still, table), guard_mode="directional")
    out = drive(cpfc, 3000 * MS, lambda t: -2.5e6 if t < 2e9 else -3.0e6,
                {500 * MS: {"p_up": ["SGen2"]}})
    switched = [(t, b) for t, b in outputs(out, still) if "switch" in b]
    assert switched and switched[0][0] > 2000 * MS and switched[0][1]["w"] == {"SGen1": 1.0}


def test_the_cpfc_takes_only_what_the_configured_mode_does(config, table) -> None:
    """A directional guard's CPFC ignores ``hold``; a block one ignores the lists; off both."""
    for mode, body in (("directional", {"hold": True}), ("block", {"p_up": ["SGen2"]}),
                       ("off", {"p_up": ["SGen2"], "hold": True})):
        cpfc = CPFC(config, GainSchedule(config, table), guard_mode=mode)
        out = drive(cpfc, 3000 * MS, lambda t: -2.5e6 + 0.5e6 * (t > 1.5e9), {2000 * MS: body})
        p_y = dict(outputs(out, config))
        assert not any("switch" in b for t, b in p_y.items() if t >= 2000 * MS), mode
        assert not any("hold" in b for b in p_y.values()), mode


def test_a_der_the_q_switch_keeps_holds_its_reactive_power(config) -> None:
    """The Q loop's switch names SGen2 in ``keep``: its reactive set-point stays where it was
    whatever Q_Y does, until a switch gives it a weight again."""
    from adnmesh.config import Reactive
    from adnmesh.control.der_controller import DERController
    from adnmesh.wire.messages import Switch

    pq = config.model_copy(update={"reactive": Reactive()})
    (der_config,) = pq.ders_by_id(["SGen2"])
    der = DERController(der_config, pq, 2e6)

    def command(t_ms, q_y, entry, w=None, switch=None):
        output(der, "q_y", t_ms, {"q_y": q_y, "q_ref_var": 0.0}, entry, w, switch)

    command(0, 0.3, 0, {"SGen1": 1.0, "SGen2": 1.0})
    held = der.q_setpoint_var
    assert held > 0
    command(100, 0.3, 1, {"SGen1": 1.0}, Switch(0.3, 0.3, 1e-7, 1e-7, keep=["SGen2"]))
    command(200, 0.6, 1)
    assert der.q_setpoint_var == pytest.approx(held)
    command(300, 0.45, 2, {"SGen1": 1.0, "SGen2": 1.0}, Switch(0.45, 0.45, 1e-7, 1e-7))
    assert der.q_setpoint_var == pytest.approx(1.5 * held)   # its share of Q_Y 0.45 at once


def test_blocking_a_der_again_mid_handover_moves_no_der(config, table) -> None:
    """SGen2 blocked up at 2 s, released at 3 s (a handover of ~29 s starts), blocked again
    at 5 s: at that switch neither DER's set-point jumps (ideal plants: P_IP is the sum of
    the set-points), the other DER's running handover goes on."""
    from adnmesh.control.der_controller import DERController

    keys = Keys(config.grid)
    cpfc = CPFC(config, GainSchedule(config, table), guard_mode="directional")
    ders = {d.id: DERController(d, config, 2e6) for d in config.ders}
    guard_at = {2000 * MS: {"p_up": ["SGen2"]}, 3000 * MS: {}, 5000 * MS: {"p_up": ["SGen2"]}}
    setpoints = {}
    while cpfc.next_timer_ns() < 6000 * MS:
        t = cpfc.next_timer_ns()
        if t % (1000 * MS) == 0:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {"SGen1": True, "SGen2": True}},
                                       src="availability"))
        if t in guard_at:
            cpfc.on_message(t, message(keys.of("grid_guard"), t, guard_at[t], src="measurement"))
        p_ip = config.runtime.rest_of_grid_w + sum(d.setpoint_w for d in ders.values())
        cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": p_ip}, src="measurement"))
        for o in cpfc.on_timer(t):
            if o.key == keys.of("p_y"):
                for der in ders.values():
                    der.on_message(t, message(o.key, t, o.body, src="cpfc"))
        setpoints[t] = {d: der.setpoint_w for d, der in ders.items()}
    for d in ("SGen1", "SGen2"):                       # one integrator step, no more
        assert abs(setpoints[5000 * MS][d] - setpoints[4990 * MS][d]) < 2e3, d
