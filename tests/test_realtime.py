"""The realtime clock's parts without processes: the delivery-error histogram
(:mod:`adnmesh.sim.latency`), the scaled clock, the overrun watch and tolerance
(:mod:`adnmesh.runtime.realtime`), and what the summary says about timing
(:mod:`adnmesh.results.realtime_report`). The runs themselves: tests/test_runtime_up.py."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from adnmesh.config import load_config
from adnmesh.runtime.realtime import OVERRUN_EVERY_NS, OverrunWatch, ScaledClock, tolerance_ns
from adnmesh.results.realtime_report import realtime_figures
from adnmesh.sim.latency import BINS, Latency, bin_of, merge, percentile, upper_edge_ns
from adnmesh.names import ICT_LINKS
from adnmesh.sim.topology import Topology
from up_runs import CASE

# --- the histogram ---------------------------------------------------------------------------


def test_bins_are_logarithmic_and_cover_what_they_say() -> None:
    assert bin_of(0) == bin_of(1_000) == 0
    for error in (1_001, 5_000, 123_456, 9_999_999, 4_000_000_000):
        index = bin_of(error)
        assert upper_edge_ns(index - 1) < error <= upper_edge_ns(index) * (1 + 1e-12)
    assert bin_of(10**15) == BINS - 1


def test_percentiles_bound_numpy_from_above_within_a_bin() -> None:
    rng = np.random.default_rng(3)
    errors = rng.lognormal(np.log(3e5), 1.0, 20_000).astype(np.int64)
    latency = Latency()
    for e in errors:
        latency.add("cpfc_to_der", int(e))
    entry = latency.links["cpfc_to_der"]
    for q in (0.5, 0.9, 0.99):
        exact = np.quantile(errors, q)
        assert exact <= percentile(entry, q) <= exact * 10 ** (1 / 8) * 1.001
    assert percentile(entry, 1.0) == entry.max_ns == errors.max()


def test_histograms_of_several_agents_add_up_and_junk_adds_nothing() -> None:
    a, b = Latency(), Latency()
    a.add("timer", 2_000)
    b.add("timer", 7_000_000)
    b.add("physical", -5)                # a negative error is counted as on time
    merged = merge([a.to_wire(), b.to_wire(), {"timer": []}])
    assert sum(merged["timer"].counts) == 2 and merged["timer"].max_ns == 7_000_000
    assert merged["physical"].counts[0] == 1
    assert np.isnan(percentile(merge([{}]).get("x", type(merged["timer"])()), 0.5))


# --- the clock and the watch -------------------------------------------------------------------


def test_the_scaled_clock_runs_at_its_speed_from_its_epoch() -> None:
    epoch = time.time_ns() + 2_000_000_000          # sim time 0 is two wall seconds away
    clock = ScaledClock(epoch, 4.0)
    now = clock.now_ns()
    assert -8.2e9 < now < -7.5e9                    # (wall - epoch) * speed
    assert clock.wait_s(0) == pytest.approx(2.0, abs=0.1)
    assert clock.wait_s(4_000_000_000) - clock.wait_s(0) == pytest.approx(1.0, abs=0.05)
    # the monotonic reading of a sim instant: a quarter of its sim distance per wall unit
    assert clock.monotonic_ns(4_000_000_000) - clock.monotonic_ns(0) == 1_000_000_000


def test_overruns_are_counted_always_and_said_once_per_sim_second() -> None:
    watch = OverrunWatch("der/SGen1", 5_000_000, 2.0)
    assert watch.check(0, (5_000_000, "timer")) is None          # at the tolerance: fine
    first = watch.check(10, (7_000_000, "physical"))
    assert first["kind"] == "overrun" and first["subject"] == "der/SGen1"
    assert "7.0 ms of sim time" in first["text"] and "3.5 ms wall" in first["text"]
    assert watch.check(OVERRUN_EVERY_NS, (9_000_000, "timer")) is None
    assert watch.check(OVERRUN_EVERY_NS + 10, (9_000_000, "timer")) is not None
    assert watch.count == 3


def test_the_tolerance_is_a_share_of_the_shortest_ict_delay_unless_configured() -> None:
    config = load_config(CASE)
    topology = Topology.from_config(config)
    shortest = min(link.delay_ns for link in topology.links.values() if link.delay_ns > 0
                   and link.name in ICT_LINKS)
    assert tolerance_ns(None, topology) == round(0.05 * shortest)
    assert tolerance_ns(2e-3, topology) == 2_000_000
    assert tolerance_ns(1e-12, topology) == 1


# --- the report ----------------------------------------------------------------------------------


def _bye(late: int = 0, overruns: int = 0, latency=None):
    return SimpleNamespace(stats={"late": late, "overruns": overruns}, latency=latency or {})


def test_an_alarm_with_an_overrun_and_no_other_cause_is_the_machines_doing() -> None:
    config = load_config(CASE)
    timeout = config.runtime.heartbeat_timeout_s
    alarms = [(3.0, "availability", "overrun", "availability", "availability is 9 ms behind"),
              (3.0 + timeout / 2, "availability", "unavailable", "der/SGen2", "no heartbeat"),
              (30.0, "availability", "unavailable", "der/SGen1", "no heartbeat")]
    figures = realtime_figures([_bye(late=4, overruns=2)], alarms, [], config, speed=2.0,
                               tolerance_ns=5_000_000)
    assert not figures.real_time and figures.late_arrivals == 4 and figures.overruns == 2
    (alarm,) = figures.late_alarms                 # the one at 30 s had no overrun near it
    assert (alarm.subject, alarm.kind, alarm.overrun_by) == ("der/SGen2", "unavailable",
                                                             "availability")


def test_an_alarm_a_fault_explains_is_not_blamed_on_the_machine() -> None:
    config = load_config(CASE)
    alarms = [(3.0, "der/SGen1", "overrun", "der/SGen1", "late"),
              (3.5, "der/SGen1", "watchdog_fallback", "der/SGen1", "no P_Y")]
    fault = {"start_ns": 2_000_000_000, "end_ns": 2_500_000_000}
    figures = realtime_figures([_bye()], alarms, [fault], config, speed=1.0,
                               tolerance_ns=5_000_000)
    assert figures.late_alarms == ()


def test_a_run_without_overruns_is_real_time() -> None:
    latency = Latency()
    latency.add("timer", 300_000)
    figures = realtime_figures([_bye(latency=latency.to_wire())], [], [], load_config(CASE),
                               speed=1.0, tolerance_ns=5_000_000)
    assert figures.real_time and figures.first_overrun is None
    (link,) = figures.links
    assert link.link == "timer" and link.events == 1 and link.max_ms == pytest.approx(0.3)
