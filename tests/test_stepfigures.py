"""The one step-figure rule: closed forms, python-control's step_info, the numpy reference,
the uniform grid as a special case of sampled times, and the figures of a run's P_ref steps."""
import dataclasses
import math

import control
import numpy as np
import pytest

from adnmesh.loopmodel.step_figures import (
    StepFigureAccumulator,
    reference_step_figures,
    step_figures,
)

from step_figures_reference import accumulate_numpy

ZETA, WN = 0.3, 2.0


def assert_same(a, b) -> None:
    """Equal figures (NaN equal to NaN)."""
    np.testing.assert_equal(dataclasses.astuple(a), dataclasses.astuple(b))


def second_order(t, zeta=ZETA, wn=WN):
    wd = wn * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2)
                                         * np.sin(wd * t))


def first_order(t, lag=2.0):
    return 1 - np.exp(-t / lag)


def jittered(t_end, h, seed=0):
    """Times from 0 to t_end with spacings uniform in [0.5 h, 1.5 h]."""
    rng = np.random.default_rng(seed)
    return np.concatenate([[0.0], np.cumsum(rng.uniform(0.5 * h, 1.5 * h, int(t_end / h)))])


# --- closed forms -------------------------------------------------------------------------------

@pytest.mark.parametrize("grid", ["uniform", "jittered"])
def test_first_order_lag_closed_forms(grid):
    lag, h = 2.0, 1e-3
    t = np.arange(0, 40 + h / 2, h) if grid == "uniform" else jittered(40, h)
    f = step_figures(t, first_order(t, lag), band_pct=5.0)
    # linear interpolation of a smooth curve: O(h^2 y'' / y') in time
    assert f.rise_time_s == pytest.approx(math.log(9) * lag, abs=1e-6)
    assert f.settling_time_s == pytest.approx(math.log(20) * lag, abs=1e-6)
    assert f.settling_time_2pct_s == pytest.approx(math.log(50) * lag, abs=1e-6)
    assert f.overshoot_pct == 0.0 and f.band_pct == 5.0
    assert (f.peak, f.peak_time_s) == (first_order(t[-1], lag), t[-1])   # monotone: last sample
    assert f.steady_error == pytest.approx(math.exp(-t[-1] / lag), rel=1e-9)


@pytest.mark.parametrize("grid", ["uniform", "jittered"])
def test_second_order_overshoot_and_peak_closed_forms(grid):
    h = 1e-3
    t = np.arange(0, 30, h) if grid == "uniform" else jittered(30, h, seed=1)
    f = step_figures(t, second_order(t))
    wd = WN * math.sqrt(1 - ZETA**2)
    overshoot = 100 * math.exp(-math.pi * ZETA / math.sqrt(1 - ZETA**2))
    # the parabola through three samples: peak error O(h^3 y'''), time error O(h^2)
    assert f.overshoot_pct == pytest.approx(overshoot, rel=1e-7)
    assert f.peak == pytest.approx(1 + overshoot / 100, rel=1e-9)
    assert f.peak_time_s == pytest.approx(math.pi / wd, abs=1e-5)


# --- python-control ------------------------------------------------------------------------------

@pytest.mark.parametrize("response", ["second_order", "first_order", "second_order_jittered"])
@pytest.mark.parametrize("band_pct", [5.0, 2.0])
def test_agrees_with_python_control_to_the_sampling_interval(response, band_pct):
    h = 0.01
    t = jittered(30, h, seed=2) if response.endswith("jittered") else np.arange(0, 30 + h / 2, h)
    y = (first_order if response == "first_order" else second_order)(t)
    ours = step_figures(t, y, band_pct=band_pct)
    ref = control.step_info(y, t, yfinal=1.0, SettlingTimeThreshold=band_pct / 100,
                            RiseTimeLimits=(0.1, 0.9))
    # python-control takes the first sample past each threshold; we interpolate between the
    # two samples around it, so each time is within one sampling interval (at most 1.5 h)
    spacing = float(np.max(np.diff(t)))
    assert abs(ours.rise_time_s - ref["RiseTime"]) < spacing
    assert ref["SettlingTime"] - spacing <= ours.settling_time_s <= ref["SettlingTime"]
    assert abs(ours.peak_time_s - ref["PeakTime"]) <= spacing / 2
    # the refined peak lies above the largest sample, by at most h^2 max|y''| / 8
    assert 0 <= ours.peak - ref["Peak"] <= spacing**2 * WN**2 / 8
    assert 0 <= ours.overshoot_pct - ref["Overshoot"] <= 100 * spacing**2 * WN**2 / 8


# --- one rule: the uniform grid is the case of equally spaced times -----------------------------

def test_uniform_grid_and_its_sample_times_give_the_same_figures():
    h = 0.01
    t = np.arange(0, 3001) * h
    y = np.vstack([second_order(t), first_order(t), second_order(t, 0.7, 5.0)])
    uniform, sampled = (StepFigureAccumulator(3, (0.05, 0.02)) for _ in range(2))
    uniform.last[:] = sampled.last[:] = y[:, 0]
    uniform.add(0.0, h, y[:, 1:])
    sampled.add(0.0, 0.0, y[:, 1:], times=t)
    for name in ("t10", "t90", "peak", "peak_t", "settle"):
        np.testing.assert_allclose(getattr(sampled, name), getattr(uniform, name), rtol=1e-12,
                                   atol=1e-12, err_msg=name)


# --- the compiled kernel is its numpy reference -------------------------------------------------

@pytest.mark.parametrize("layout", ["rows", "lanes"])
@pytest.mark.parametrize("grid", ["uniform", "jittered"])
def test_compiled_kernel_equals_the_numpy_reference(grid, layout):
    """Both compiled kernels: blocks candidate by candidate (C order) and sample by sample
    (the (n, M) block of a lanes simulation, given as its transposed view)."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 4001) * 0.01 if grid == "uniform" else jittered(40, 0.01, seed=3)
    zeta = rng.uniform(0.1, 1.2, 40)
    wn = rng.uniform(0.3, 5.0, 40)
    y = np.vstack([second_order(t, min(z, 0.99), w) for z, w in zip(zeta, wn)])
    y += rng.normal(0, 1e-3, y.shape) * (np.arange(40) % 4 == 0)[:, None]     # some noisy
    fast, ref = (StepFigureAccumulator(40, (0.05, 0.02, 0.005)) for _ in range(2))
    start = 0
    for n in (1, 2, 3, 50, 700, 2000, t.size - 2757):
        chunk = y[:, start + 1:start + 1 + n]
        times = None if grid == "uniform" else t[start:start + n + 1]
        block = chunk if layout == "rows" else np.ascontiguousarray(chunk.T).T
        assert layout == "rows" or n == 1 or not block.flags.c_contiguous
        curvature = fast.add(t[start], 0.01, block, times=times)
        accumulate_numpy(ref, t[start], 0.01, chunk, times=times)
        if n > 2:
            second = chunk[:, 2:] - 2.0 * chunk[:, 1:-1] + chunk[:, :-2]
            assert np.array_equal(curvature, np.abs(second).max(axis=1))
        start += n
    assert start == t.size - 1
    for name in ("t10", "t90", "peak", "peak_t", "last", "settle"):
        assert np.array_equal(getattr(fast, name), getattr(ref, name), equal_nan=True), name


# --- definitions at the edges -------------------------------------------------------------------

def test_figures_that_do_not_exist():
    t = np.arange(0, 10.0, 0.1)
    half = step_figures(t, 0.5 * (1 - np.exp(-t)))
    assert math.isnan(half.rise_time_s) and half.settling_time_s == math.inf
    assert half.overshoot_pct == 0.0 and half.steady_error == pytest.approx(0.5, abs=1e-4)
    inside = step_figures(t, np.full(t.size, 1.01))       # in the band from the first sample
    assert math.isnan(inside.rise_time_s) and inside.settling_time_s == 0.0
    assert inside.overshoot_pct == pytest.approx(1.0) and inside.peak_time_s == 0.0
    below = step_figures(t, -np.ones(t.size))             # the wrong way: peak is a sample
    assert below.peak == -1.0 and below.overshoot_pct == 0.0


@pytest.mark.parametrize("t, y, message", [
    ([0.0], [0.0], "same length >= 2"),
    ([0.0, 1.0], [0.0], "same length >= 2"),
    ([0.0, 1.0, 1.0], [0.0, 0.5, 1.0], "strictly increasing"),
    ([0.0, 1.0], [0.0, math.nan], "finite"),
])
def test_bad_samples_are_refused_in_one_line(t, y, message):
    with pytest.raises(ValueError, match=message):
        step_figures(t, y)


# --- a run's P_ref steps ------------------------------------------------------------------------

S = 1_000_000_000     # ns


def run_samples():
    """P_IP every 10 ms for 30 s, following +1 MW at 5 s and -0.5 MW at 20 s with a 1 s lag,
    from a measured level 20 kW off the reference (an offset the figures must show)."""
    t = np.arange(0, 3001) * 10_000_000
    ts = t / S
    p = 2e4 + np.where(ts < 5, 0.0, 1e6 * first_order(np.clip(ts - 5, 0, None), 1.0))
    p -= np.where(ts < 20, 0.0, 5e5 * first_order(np.clip(ts - 20, 0, None), 1.0))
    return t, p


def test_reference_steps_are_normalised_by_the_reference():
    t, p = run_samples()
    first, second = reference_step_figures(t, p, [0, 5 * S, 20 * S], [0.0, 1e6, 5e5], [],
                                           30 * S)
    assert (first.t_s, first.step_w, first.p_ref_w, first.window_s) == (5.0, 1e6, 1e6, 15.0)
    assert (second.t_s, second.step_w, second.p_ref_w, second.window_s) == (20.0, -5e5, 5e5, 10.0)
    ts = (t[(t >= 5 * S) & (t < 20 * S)] - 5 * S) / S
    expected = step_figures(ts, (p[(t >= 5 * S) & (t < 20 * S)] - 0.0) / 1e6)
    assert_same(first.figures, expected)
    assert first.figures.steady_error == pytest.approx(-0.02, abs=1e-6)      # the 20 kW offset
    assert first.steady_error_w == pytest.approx(-2e4, abs=1.0)
    assert second.figures.steady_error == pytest.approx(-2e4 / -5e5, abs=1e-4)  # 4 %


def test_windows_end_at_the_next_event_and_inclusively_at_the_run_end():
    t, p = run_samples()
    steps = reference_step_figures(t, p, [0, 5 * S, 20 * S], [0.0, 1e6, 5e5],
                                   [3 * S, 5 * S, 12 * S, 12 * S + 1], 30 * S)
    assert [s.window_s for s in steps] == [7.0, 10.0]        # not at 5 s (the step itself)
    short = reference_step_figures(t, p, [0, 5 * S], [0.0, 1e6], [5 * S + 10_000_000], 30 * S)
    assert short[0].figures is None and short[0].steady_error_w == pytest.approx(1e6 - 2e4)
    end = reference_step_figures(t, p, [0, 20 * S], [0.0, 1e6], [], 30 * S)
    last = step_figures((t[t >= 20 * S] - 20 * S) / S, p[t >= 20 * S] / 1e6)
    assert_same(end[0].figures, last)               # the sample at the run's end is in


def test_repeated_references_unsorted_nan_and_duplicate_samples():
    t, p = run_samples()
    plain = reference_step_figures(t, p, [0, 5 * S], [0.0, 1e6], [], 30 * S)
    order = np.random.default_rng(0).permutation(t.size)
    noisy_t = np.concatenate([t[order], [t[10], 7 * S + 1]])
    noisy_p = np.concatenate([p[order], [p[10] + 1e5, math.nan]])
    # the first sample at an instant counts (a stable sort keeps the permuted ones first)
    again = reference_step_figures(noisy_t, noisy_p, [0, 2 * S, 5 * S, 9 * S], [0.0, 0.0, 1e6, 1e6],
                                   [], 30 * S)
    assert len(again) == 1 and again[0].window_s == plain[0].window_s   # a repeated value
    assert_same(again[0].figures, plain[0].figures)      # is no step and ends no window
    shifted = reference_step_figures(t, p, [0, 5 * S], [0.0, 1e6], [], 30 * S, origin_ns=S)
    assert shifted[0].t_s == 4.0
    assert reference_step_figures([], [], [0], [1e6], [], 30 * S) == ()


def test_accumulator_refuses_mismatched_times_and_skips_empty_blocks():
    acc = StepFigureAccumulator(2, (0.05,))
    with pytest.raises(ValueError, match="3 samples need 4 times"):
        acc.add(0.0, 0.0, np.ones((2, 3)), times=np.arange(3.0))
    assert np.array_equal(acc.add(0.0, 0.1, np.empty((2, 0))), np.zeros(2))
    assert np.array_equal(acc.last, np.zeros(2)) and np.all(acc.peak == -np.inf)


def test_a_peak_at_the_last_sample_has_that_samples_time_whatever_lies_beyond_the_times():
    # The sample times are a view of a longer buffer whose next element is NaN: the kernel
    # must not read past the times it was given (it once did, for a peak at the last sample,
    # and the figure came out NaN in one run and right in the next).
    buffer = np.array([0.0, 0.5, 1.0, 1.5, 2.0, np.nan, np.inf])
    times = buffer[:5]
    y = np.array([0.0, 0.3, 0.6, 0.8, 0.95])        # still rising: the peak is the last sample
    acc = StepFigureAccumulator(1, (0.05,))
    acc.add(0.0, 0.0, y[None, 1:], times=times)
    assert acc.peak[0] == 0.95 and acc.peak_t[0] == 2.0
    figures = step_figures(times, y)
    assert figures.peak == 0.95 and figures.peak_time_s == 2.0
