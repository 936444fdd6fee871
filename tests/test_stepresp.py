"""Step response with exact delays: closed forms, step-size error bound, python-control + Padé."""
from math import factorial

import numpy as np
import pytest

from adnmesh.loopmodel.plant import RISE_PER_LAG, Plant
from adnmesh.loopmodel.stability import nyquist_stability
from adnmesh.loopmodel.margins import disk_margin
from adnmesh.loopmodel.step_figures import StepFigureAccumulator
from adnmesh.loopmodel.step_response import choose_step, simulate_step, step_info, step_info_from_samples

from loops import CONFIG, LOOPS, gains, plant
from pade_reference import reference_figures
from step_figures_reference import accumulate_numpy
from test_stability import integrator_with_delay

#: stated bound of the simulation error on y (final value 1) at the default step
Y_ERROR_BOUND = 1e-4


def test_first_order_lag_figures():
    t_lag, h = 2.0, 1e-3
    t = np.arange(0, 40 + h / 2, h)
    info = step_info_from_samples(h, 1.0 - np.exp(-t / t_lag))
    assert info.rise_time_s[0] == pytest.approx(RISE_PER_LAG * t_lag, rel=1e-6)   # 2.197 T
    assert info.settling_time_s[0] == pytest.approx(t_lag * np.log(20), rel=1e-6)
    assert info.settling_time_2pct_s[0] == pytest.approx(t_lag * np.log(50), rel=1e-6)
    assert info.overshoot_pct[0] == 0.0


def test_second_order_overshoot_closed_form():
    zeta, wn, h = 0.3, 2.0, 1e-3
    t = np.arange(0, 30, h)
    wd = wn * np.sqrt(1 - zeta**2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / np.sqrt(1 - zeta**2) * np.sin(wd * t))
    info = step_info_from_samples(h, y)
    assert info.overshoot_pct[0] == pytest.approx(100 * np.exp(-np.pi * zeta / np.sqrt(1 - zeta**2)),
                                                  rel=1e-7)
    assert info.peak_time_s[0] == pytest.approx(np.pi / wd, abs=1e-6)


@pytest.mark.parametrize("k_tau", [0.3, 0.9])
def test_integrator_delay_matches_method_of_steps_series(k_tau):
    # y' = k (1 - y(t - tau)): y = sum_n (-1)^(n+1) k^n (t - n tau)_+^n / n!
    tau = 0.5
    k = k_tau / tau
    plant, kp, ki = integrator_with_delay(k, tau)
    errors = []
    for h in (0.01, 0.005):
        t, y = simulate_step(plant, kp, ki, 8 * tau, h=h)
        exact = sum((-1) ** (n + 1) * k**n * np.clip(t - n * tau, 0, None) ** n / factorial(n)
                    for n in range(1, 10))
        errors.append(np.max(np.abs(y[0] - exact)))
    assert errors[0] < Y_ERROR_BOUND
    assert errors[1] < errors[0] / 3.5          # second order in h


@pytest.mark.parametrize("name", list(LOOPS))
def test_default_step_meets_stated_error_bound(name):
    plant, kp, ki = gains(name)
    nyq = nyquist_stability(plant, kp, ki)
    bw = disk_margin(plant, kp, ki, nyq).omega[0]
    h = choose_step(plant, bw)
    t_end = 60.0
    _, coarse = simulate_step(plant, kp, ki, t_end, h)
    _, fine = simulate_step(plant, kp, ki, t_end, h / 4)
    assert np.max(np.abs(coarse[0] - fine[0, ::4])) < Y_ERROR_BOUND


@pytest.mark.parametrize("name", list(LOOPS))
def test_step_info_agrees_with_python_control(name):
    plant, kp, ki = gains(name)
    t_end = {"wt": 20.0, "all": 60.0}.get(name, 200.0)
    dt = 2e-3
    ref = reference_figures(plant, kp, ki, t_end_s=t_end, dt=dt, order=10)
    ours = step_info(plant, kp, ki)
    # same response at the same instants, once the Padé model's own ringing at the arrival of
    # the delayed step has died out (its error there shrinks only slowly with the order)
    t, y = simulate_step(plant, kp, ki, t_end, h=dt)
    later = t > plant.path_delays_s.max() + 1.0
    assert np.max(np.abs(y[0] - ref["y"][: y.shape[1]])[later]) < Y_ERROR_BOUND
    assert ours.overshoot_pct[0] == pytest.approx(ref["overshoot_pct"], abs=2e-3)
    # python-control reports the first sample past each threshold (no interpolation)
    for key in ("rise_time_s", "settling_time_s", "settling_time_2pct_s"):
        assert getattr(ours, key)[0] == pytest.approx(ref[key], abs=2 * dt), key
    if ref["overshoot_pct"] > 0.05:      # peak of a monotone response is just its horizon's end
        assert ours.peak[0] == pytest.approx(ref["peak"], abs=2e-5)
        assert ours.peak_time_s[0] == pytest.approx(ref["peak_time_s"], abs=0.05 * ref["peak_time_s"])


def test_adaptive_horizon_and_coarsening_keep_accuracy():
    plant, kp, ki = gains("wt")
    kp, ki = kp, ki / 60.0            # slow integral action: a long creeping tail
    fast = step_info(plant, kp, ki)
    t, y = simulate_step(plant, kp, ki, float(fast.horizon_s[0]) + 10, h=0.005)
    ref = step_info_from_samples(0.005, y)
    assert fast.horizon_s[0] > 100
    for key in ("rise_time_s", "settling_time_s", "settling_time_2pct_s", "overshoot_pct"):
        assert getattr(fast, key)[0] == pytest.approx(getattr(ref, key)[0], rel=1e-4, abs=1e-4)


def test_compiled_step_info_accumulator_equals_the_numpy_reference():
    from adnmesh.loopmodel.step_response import _Simulator
    rng = np.random.default_rng(0)
    m = 60
    lags = plant(list(CONFIG.der_ids()))
    gains = rng.dirichlet(np.ones(len(lags.actuators)), m) * 1e6
    sim = _Simulator(Plant(lags.actuators, gains, lags.t_com_s, lags.t_meas_s),
                     rng.uniform(0.05, 1.5, m) / 1e6, rng.uniform(0.02, 3.0, m) / 1e6, 0.01)
    fast, ref = (StepFigureAccumulator(m, (0.05, 0.02, 0.005)) for _ in range(2))
    t0 = 0.0
    for n in (1, 2, 3, 50, 700, 2000, 3000):
        y = sim.run(n)
        curvature = fast.add(t0, 0.01, y)
        accumulate_numpy(ref, t0, 0.01, y)
        if n > 2:
            assert curvature.max() == np.abs(np.diff(y, 2, axis=1)).max()
        t0 += n * 0.01
    for name in ("t10", "t90", "peak", "peak_t", "last", "settle"):
        assert np.array_equal(getattr(fast, name), getattr(ref, name), equal_nan=True), name


def test_sparse_candidates_run_on_their_active_groups_bit_identically():
    """A candidate whose plant has gain in a few groups only is simulated on those groups
    (``_by_active_groups``): every figure equals, bit for bit, the simulation of the full
    plant (the zero-gain groups included), on the exact-delay and the interpolating path."""
    from adnmesh.loopmodel.plant import Actuator
    from adnmesh.loopmodel.step_response import _simulate_until_settled, _horizon_floor, choose_steps

    acts = (Actuator(0.01, 0.25), Actuator(1.0, 11.0), Actuator(0.01, 0.05),
            Actuator(0.013, 0.4))                 # the last delay is no multiple of 10 ms
    gains_w = np.array([[2e6, 0, 0, 0], [0, 3e5, 0, 0], [2e6, 3e5, 0, 0], [0, 0, 1e5, 0],
                        [0, 0, 0, 6.5e3], [2e6, 3e5, 1e5, 4e5]])
    plant_ = Plant(acts, gains_w, 0.1, 0.1)
    kp = np.full(gains_w.shape[0], 0.2 / 2.4e6)
    ki = np.full(gains_w.shape[0], 1.0 / 2.4e6)
    fast = step_info(plant_, kp, ki, t_max_s=5e4)
    h = choose_steps(plant_)
    t_min = _horizon_floor(plant_, gains_w, np.full(kp.size, np.nan))
    for i in range(kp.size):                      # the full plant, every group simulated
        ref = _simulate_until_settled(plant_, kp[[i]], ki[[i]], gains_w[[i]], float(h[i]),
                                      t_min[[i]], 5.0, 5e4)
        for key, field in (("os", "overshoot_pct"), ("tr", "rise_time_s"),
                           ("ts", "settling_time_s"), ("ts2", "settling_time_2pct_s"),
                           ("pk", "peak"), ("tp", "peak_time_s"), ("hor", "horizon_s")):
            assert getattr(fast, field)[i] == ref[key][0], (i, field)
    assert np.all(np.isfinite(fast.settling_time_s))
