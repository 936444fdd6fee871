"""The compiled simulate-until-settled loop gives the Python loop's figures bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from adnmesh.loopmodel import step_response
from adnmesh.loopmodel.plant import Actuator, Plant
from adnmesh.loopmodel.step_response import (_OUTPUTS, _simulate_until_settled,
                              _simulate_until_settled_stepwise)

#: SimBench's three dynamics (WT, CHP, PV): delays 0.01 s / 1 s / 0.01 s, lags in s
SIMBENCH = (Actuator(0.01, 0.234), Actuator(1.0, 11.18), Actuator(0.01, 0.0455))


def _bucket(seed: int, m: int, acts=SIMBENCH, t_com=0.1, t_meas=0.1):
    """M loops of one plant structure with random shares and gains around the feasible
    edge (some overshoot, some slow, some fast)."""
    rng = np.random.default_rng(seed)
    gains = rng.dirichlet(np.ones(len(acts)) * 0.7, m)
    plant = Plant(acts, gains, t_com, t_meas)
    kp = np.exp(rng.uniform(np.log(0.02), np.log(0.8), m))
    ki = kp * np.exp(rng.uniform(np.log(0.05), np.log(3.0), m))
    return plant, kp, ki, gains


def _both(plant, kp, ki, gains, h, t_min, t_max, stop=None, until_rise=False,
          limit=None, band_pct=5.0):
    compiled = _simulate_until_settled(plant, kp, ki, gains, h, t_min, band_pct, t_max,
                                       stop, limit, until_rise)
    stepwise = _simulate_until_settled_stepwise(plant, kp, ki, gains, h, t_min, band_pct,
                                                t_max, stop, limit, until_rise)
    return compiled, stepwise


def _assert_identical(compiled: dict, stepwise: dict) -> None:
    for key in _OUTPUTS:
        a, b = compiled[key], stepwise[key]
        assert a.shape == b.shape
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        assert same.all(), (key, np.nonzero(~same)[0], a[~same], b[~same])


@pytest.mark.parametrize("seed,m", [(1, 1), (2, 7), (3, 40), (4, 130)])
@pytest.mark.parametrize("stop", [None, 1.01])
def test_compiled_loop_is_the_stepwise_loop_bit_for_bit(seed: int, m: int, stop) -> None:
    """Whole-step delays (the step divides every delay), candidates dropping out at every
    block (settled, overshot, at their horizon), step doublings: every figure identical."""
    plant, kp, ki, gains = _bucket(seed, m)
    h = step_response.choose_step(plant.with_gains(gains[:1]))
    t_min = np.full(m, 50.0)
    t_max = np.where(np.arange(m) % 5 == 0, 300.0, 20000.0)
    compiled, stepwise = _both(plant, kp, ki, gains, h, t_min, t_max, stop)
    _assert_identical(compiled, stepwise)
    if m >= 40:                   # a real mixture: settled, overshooting, at the horizon
        assert np.isfinite(compiled["ts"]).any() and np.isinf(compiled["ts"]).any()
        assert (compiled["os"] > 1.0).any()
        if stop is not None:
            assert np.isnan(compiled["ts"]).any()


@pytest.mark.parametrize("h", [0.03, 0.0125])
def test_interpolated_delays_and_doubling_into_them(h: float) -> None:
    """A step that is no divisor of the delays (thirds) and one whose doublings stop
    dividing them: the interpolating kernel, from the first block or after a doubling."""
    plant, kp, ki, gains = _bucket(11, 23)
    t_min = np.full(23, 30.0)
    compiled, stepwise = _both(plant, kp, ki, gains, h, t_min, np.full(23, 5000.0), 1.01)
    _assert_identical(compiled, stepwise)
    levels = step_response._levels(plant.actuators, tuple(plant.path_delays_s.tolist()),
                              float(plant.t_meas_s), h, float(plant.path_delays_s.min()))
    assert not levels[-1][-1]                 # the coarsest step has interpolated delays


def test_until_rise_and_a_limit_from_the_full_plant() -> None:
    """``until_rise`` (searches' rise-time bounds) and the coarsening limit of a larger
    plant (a reduced plant's buckets double as the full plant's would)."""
    plant, kp, ki, gains = _bucket(5, 31)
    h = 0.005
    t_min = np.linspace(5.0, 80.0, 31)
    compiled, stepwise = _both(plant, kp, ki, gains, h, t_min, np.full(31, 20000.0),
                               until_rise=True, limit=0.04)
    _assert_identical(compiled, stepwise)
    assert np.isfinite(compiled["tr"]).all()


def test_single_group_slow_loops_and_the_general_kernels() -> None:
    """One group (a DER alone, as Find W simulates it), weak gains that settle only after
    hours of simulated time; the compiled loop also agrees with the general (row by row)
    kernels."""
    acts = (Actuator(1.0, 11.18),)
    rng = np.random.default_rng(8)
    m = 9
    gains = np.full((m, 1), 1.0)
    plant = Plant(acts, gains, 0.1, 0.1)
    kp = rng.uniform(1e-3, 0.05, m)
    ki = rng.uniform(2e-5, 1e-3, m)
    t_min = np.full(m, 100.0)
    t_max = np.full(m, 1e6)
    compiled = _simulate_until_settled(plant, kp, ki, gains, 0.05, t_min, 5.0, t_max)
    rows = _simulate_until_settled_stepwise(plant, kp, ki, gains, 0.05, t_min, 5.0, t_max,
                                            lanes=False)
    _assert_identical(compiled, rows)
    assert (compiled["hor"] > 20000.0).any()


def test_a_delay_buffer_too_short_to_double_is_an_error_in_both() -> None:
    """The buffer check of a step doubling stays a check: a ring that cannot hold the
    doubled step's samples raises in the compiled loop as in the Python one."""
    from adnmesh.loopmodel.settle_kernel import coarsen_buffer

    with pytest.raises(ValueError, match="too short"):
        coarsen_buffer(np.zeros((4, 2)), 40, 3, 30)
