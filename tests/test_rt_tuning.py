"""The realtime wake-up tuning of an agent process (adnmesh.runtime.os_scheduling): the spin-wait
on a fake clock, priorities granted and refused (stand-ins for the OS calls), the spin from the
environment. Nothing is timed."""

import os

import pytest

from adnmesh.runtime.os_scheduling import (FIFO_PRIORITY, NICE, SPIN_ENV, SPIN_NS, SpinPlan,
                                       raise_priority, spin_ns_from_env)


class FakeClock:
    """A monotonic clock that advances ``step`` ns per reading."""

    def __init__(self, start: int = 0, step: int = 10_000) -> None:
        self.t, self.step, self.reads = start, step, 0

    def __call__(self) -> int:
        self.t += self.step
        self.reads += 1
        return self.t


def test_the_sleep_ends_the_spin_before_the_instant():
    clock = FakeClock(start=0, step=0)
    plan = SpinPlan(200_000, clock)
    assert plan.sleep_s(1_000_000) == pytest.approx(800e-6)
    assert plan.sleep_s(100_000) < 0          # within the spin: no sleep


def test_the_spin_polls_until_the_instant_and_no_further():
    clock = FakeClock(start=0, step=10_000)
    plan = SpinPlan(200_000, clock)
    assert plan.spin(150_000)
    assert 150_000 <= clock.t < 150_000 + 2 * clock.step
    assert clock.reads == 15                   # one look at 10 µs, 14 polls to 150 µs


def test_the_spin_refuses_an_instant_beyond_it_and_stops_when_interrupted():
    clock = FakeClock(start=0, step=10_000)
    assert not SpinPlan(100_000, clock).spin(500_000)    # the caller must sleep first
    assert clock.reads == 1
    polls = []
    assert not SpinPlan(1_000_000, clock).spin(900_000, lambda: polls.append(1) or
                                               len(polls) >= 3)
    assert len(polls) == 3


def test_a_granted_fifo_priority_reaches_every_thread():
    calls = []
    result = raise_priority("fifo", threads=lambda: [11, 12],
                            setscheduler=lambda tid, policy, param: calls.append(
                                (tid, policy, param.sched_priority)))
    assert result.granted and "SCHED_FIFO" in result.text
    assert calls == [(11, os.SCHED_FIFO, FIFO_PRIORITY), (12, os.SCHED_FIFO, FIFO_PRIORITY)]


def test_a_refused_priority_is_said_in_one_line_and_not_raised():
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    for priority in ("fifo", "nice"):
        result = raise_priority(priority, threads=lambda: [1], setscheduler=refuse,
                                setpriority=refuse)
        assert not result.granted
        assert "not granted (Operation not permitted)" in result.text
        assert "\n" not in result.text


def test_nice_sets_every_thread_and_off_does_nothing():
    calls = []
    result = raise_priority("nice", threads=lambda: [5, 6],
                            setpriority=lambda which, tid, value: calls.append((tid, value)))
    assert result.granted and calls == [(5, NICE), (6, NICE)]
    assert raise_priority("off", threads=lambda: pytest.fail("no thread is touched")).granted
    with pytest.raises(ValueError, match="unknown realtime priority"):
        raise_priority("max")


def test_the_spin_comes_from_the_environment_in_microseconds():
    assert spin_ns_from_env({SPIN_ENV: "250"}) == 250_000
    assert spin_ns_from_env({}) == SPIN_NS
    assert spin_ns_from_env({SPIN_ENV: "fast"}) == SPIN_NS
    assert spin_ns_from_env({SPIN_ENV: "-5"}) == 0


def test_freeze_heap_takes_what_lives_now_out_of_the_collections() -> None:
    import gc

    from adnmesh.runtime.os_scheduling import freeze_heap

    try:
        gc.collect()             # what lives, without the cyclic garbage earlier tests left
        alive = len(gc.get_objects())
        frozen = freeze_heap()
        assert frozen >= 0.9 * alive
        assert len(gc.get_objects()) < 0.1 * alive        # what a full collection walks
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0
