"""The CPFC runs the static controller while an on-demand tuning is under way (agent level, no
network): on the sim clock the tuned gains arrive a fixed sim time later, in realtime runs when
the background thread is done; both switches are bumpless."""
from __future__ import annotations

import threading
from pathlib import Path

import pytest

from adnmesh.config import Config, load_config
from adnmesh.control.cpfc_controller import CPFC, GainSchedule
from adnmesh.tuning.table import SchedulingTable, TableEntry
from adnmesh.wire.keys import Keys
from payloads import message

MS = 1_000_000  # ns
STATIC = (2e-8, 1e-7)
TUNED = (1e-7, 3.84e-7)


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    """Two WTs (SGen2 with a 0.5 MW schedule), a step at 1 s."""
    return load_config(configs_dir / "examples" / "runtime-step.yaml")


def _table(config: Config) -> SchedulingTable:
    """The set of both DERs and the static controller only: {SGen1} is missing."""
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), 5e-8, 1.92e-7, {"SGen1": 1.0, "SGen2": 0.8}))
    table.static = TableEntry(("SGen1", "SGen2"), *STATIC, {"SGen1": 1.0, "SGen2": 1.0})
    return table


def _run(cpfc: CPFC, t0_ns: int, until_ns: int, si_at: int | None = None) -> list:
    """Drive the CPFC's samples from ``t0_ns`` to ``until_ns`` (measurement ramping up, SGen2
    leaving at ``si_at``); its P_Y bodies as (t, body)."""
    keys = Keys(cpfc.config.grid)
    out = []
    while cpfc.next_timer_ns() < until_ns:
        t = cpfc.next_timer_ns()
        if t == si_at:
            cpfc.on_message(t, message(keys.of("si"), t, {"si": {"SGen1": True, "SGen2": False}},
                                       src="availability"))
        if t >= t0_ns:
            cpfc.on_message(t, message(keys.of("p_ip"), t, {"p_ip_w": -2.5e6 + 0.6e6 * min(1, t / 4e9)},
                                       src="measurement"))
        out += [(t, o.body) for o in cpfc.on_timer(t) if o.key.endswith("/p_y")]
    return out


def test_on_the_sim_clock_the_static_controller_bridges_a_fixed_tuning_time(config) -> None:
    calls = []

    def tune(cfg, ids):
        calls.append(ids)
        return TableEntry(tuple(ids), *TUNED, dict.fromkeys(ids, 1.0))

    schedule = GainSchedule(config, _table(config), tune=tune, tuning_delay_s=0.5)
    cpfc = CPFC(config, schedule)
    out = _run(cpfc, 0, 5200 * MS, si_at=4500 * MS)
    switches = [(t, b) for t, b in out if "switch" in b]
    assert [t for t, _ in switches] == [4500 * MS, 5000 * MS]
    (t1, to_static), (t2, to_tuned) = switches
    assert (to_static["kp"], to_static["ki"]) == STATIC
    assert (to_tuned["kp"], to_tuned["ki"]) == TUNED
    for _, b in switches:                                    # both switches bumpless
        assert b["p_y"] == pytest.approx(b["switch"].p_y_before, rel=1e-12)
    assert to_tuned["entry"] == to_static["entry"] + 1 and to_tuned["w"] == {"SGen1": 1.0}
    between = [b for t, b in out if t1 < t < t2]
    assert between and all((b["kp"], b["ki"]) == STATIC for b in between)
    assert [e.source for e in cpfc.switches] == ["static_tuning", "tuned"]
    assert calls == [["SGen1"]]
    assert cpfc.stats()["gains_static_tuning"] == 1.0


def test_a_run_on_the_sim_clock_is_deterministic(config) -> None:
    def tune(cfg, ids):
        return TableEntry(tuple(ids), *TUNED, dict.fromkeys(ids, 1.0))

    runs = [_run(CPFC(config, GainSchedule(config, _table(config), tune=tune,
                                           tuning_delay_s=0.25)), 0, 5000 * MS, si_at=4500 * MS)
            for _ in range(2)]
    assert runs[0] == runs[1]


def test_in_realtime_runs_the_tuning_runs_in_the_background(config) -> None:
    release = threading.Event()

    def tune(cfg, ids):
        release.wait()
        return TableEntry(tuple(ids), *TUNED, dict.fromkeys(ids, 1.0))

    schedule = GainSchedule(config, _table(config), tune=tune, background=True)
    cpfc = CPFC(config, schedule)
    out = _run(cpfc, 0, 4600 * MS, si_at=4500 * MS)       # the tuning cannot finish yet
    assert [(b["kp"], b["ki"]) for t, b in out if t >= 4500 * MS] == [STATIC] * 10
    release.set()
    (future,) = schedule._jobs[frozenset({"SGen1"})]
    future.result(timeout=60)                              # the thread is done
    out = _run(cpfc, 0, 4700 * MS)
    (t_switch, body), = [(t, b) for t, b in out if "switch" in b]
    assert t_switch == 4600 * MS and (body["kp"], body["ki"]) == TUNED
    assert body["p_y"] == pytest.approx(body["switch"].p_y_before, rel=1e-12)


def test_without_a_static_controller_the_cpfc_waits_for_the_tuning(config) -> None:
    table = _table(config)
    table.static = None

    def tune(cfg, ids):
        return TableEntry(tuple(ids), *TUNED, dict.fromkeys(ids, 1.0))

    cpfc = CPFC(config, GainSchedule(config, table, tune=tune, tuning_delay_s=0.5))
    out = _run(cpfc, 0, 4600 * MS, si_at=4500 * MS)
    (t_switch, body), = [(t, b) for t, b in out if "switch" in b]
    assert t_switch == 4500 * MS and (body["kp"], body["ki"]) == TUNED


def test_the_cpfc_tunes_in_the_background_once_it_knows_the_run_is_realtime(config) -> None:
    schedule = GainSchedule(config, _table(config))
    cpfc = CPFC(config, schedule)
    cpfc.on_clock("sim")
    assert schedule.background is False
    cpfc.on_clock("realtime")
    assert schedule.background is True
