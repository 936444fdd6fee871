"""Certified Nyquist stability against closed forms and python-control's Padé poles."""
import numpy as np
import pytest

from adnmesh.loopmodel.plant import Actuator, Plant
from adnmesh.loopmodel.stability import nyquist_stability

from loops import LOOPS, gains
from pade_reference import reference_models


def integrator_with_delay(k: float, tau: float, t_lag: float = 0.05):
    """PI with K_P/K_I = T cancels the lag: L(s) = k e^{-s tau} / s exactly."""
    plant = Plant((Actuator(tau - 0.1 - 0.0, t_lag),), np.array([1.0]), 0.1, 0.0)
    return plant, k * t_lag, k


@pytest.mark.parametrize("tau", [0.2, 0.5, 1.3])
def test_integrator_delay_boundary_is_k_tau_half_pi(tau):
    k_crit = np.pi / 2 / tau
    for factor, expect in ((0.999, True), (1.001, False), (0.5, True), (3.0, False)):
        plant, kp, ki = integrator_with_delay(factor * k_crit, tau)
        assert nyquist_stability(plant, kp, ki).stable[0] == expect, factor


def test_unstable_pole_count_of_integrator_delay():
    # k tau between 5pi/2 and 9pi/2 -> two pairs of right-half-plane roots
    plant, kp, ki = integrator_with_delay(3.0 * np.pi / 0.5, 0.5)
    res = nyquist_stability(plant, kp, ki)
    assert res.certified[0] and res.unstable_poles[0] == 4


@pytest.mark.parametrize("name", list(LOOPS))
def test_verdict_agrees_with_pade_poles(name):
    plant, kp0, ki0 = gains(name)
    rng = np.random.default_rng(1)
    scale = np.exp(rng.uniform(-1.0, 4.0, size=(12, 2)))
    kp, ki = kp0 * scale[:, 0], ki0 * scale[:, 1]
    ours = nyquist_stability(plant, kp, ki)
    assert ours.certified.all()
    checked = 0
    for i in range(kp.size):
        _, closed = reference_models(plant, kp[i], ki[i], order=12)
        margin = np.max(closed.poles().real)
        if abs(margin) < 1e-3:          # too close to call for the Padé model itself
            continue
        assert ours.stable[i] == (margin < 0), (i, margin)
        checked += 1
    assert checked >= 10
    assert ours.stable.any() and (~ours.stable).any()


def test_other_actuator_models_agree_with_pade():
    base, kp, ki = gains("wt_chp")
    for model in ("pt2", "rhpz"):
        for b in (0.3, 1.0, 3.0):
            plant = base.with_model(model, b)
            for f in (0.3, 1.0, 4.0):
                _, closed = reference_models(plant, kp * f, ki * f, order=12)
                margin = np.max(closed.poles().real)
                if abs(margin) < 1e-3:
                    continue
                assert nyquist_stability(plant, kp * f, ki * f).stable[0] == (margin < 0)


def test_gain_scaling_invariance():
    plant, kp, ki = gains("all")
    a = nyquist_stability(plant, kp, ki)
    b = nyquist_stability(plant.scaled(1e3), kp / 1e3, ki / 1e3)
    assert a.stable[0] and b.stable[0]
    np.testing.assert_allclose(a.loop, b.loop, rtol=1e-12)


@pytest.mark.parametrize("name", sorted(LOOPS))
def test_the_loop_taken_into_python_control_has_the_exact_frequency_response(name):
    # adnmesh.loopmodel.control_models (Padé order 14) against the exact delays of
    # loop_response, over the band where the loop is designed (an order-n Padé of a delay
    # tau is exact to ~1e-6 in magnitude and phase for omega * tau well below n)
    import control as ct
    from adnmesh.loopmodel.control_models import loop_models
    from adnmesh.loopmodel.frequency_response import loop_response

    plant, kp, ki = gains(name)
    loop, _ = loop_models(plant, kp, ki, order=14)
    omega = np.geomspace(1e-3, 5.0, 60)
    exact = loop_response(plant, kp, ki, omega)[0]
    approx = np.array([complex(ct.evalfr(loop, 1j * w)) for w in omega])
    np.testing.assert_allclose(approx, exact, rtol=1e-5)
