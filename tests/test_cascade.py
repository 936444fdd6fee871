"""The cascade's numerics against independent evaluations: python-control with Padé
approximants of every delay, the reference loop's own step simulation, a halved step."""
import math

import numpy as np
import control as ct
import pytest

from adnmesh.cascade.certificate import BACK_OFF_STEP, back_off, cascade_figures
from adnmesh.cascade.control_models import cascade_models
from adnmesh.cascade.equivalent import equivalent, first_crossing
from adnmesh.cascade.lower_adn import LowerAdn
from adnmesh.cascade.nested_loop import upper_loop
from adnmesh.cascade.nested_step import choose_step, simulate
from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.control_models import loop_models
from adnmesh.loopmodel.plant import Actuator, Plant
from adnmesh.loopmodel.step_figures import step_figures
from adnmesh.loopmodel.step_response import step_info

WT = Actuator(0.01, 0.515 / math.log(9))
CHP = Actuator(1.0, 24.57 / math.log(9))
PV = Actuator(0.05, 1.0 / math.log(9))


def adn(name, groups, gains_w, kp_n=0.5, ki_n=0.6, t_com=0.1, t_meas=0.1):
    """An ADN under a PI given per W of its plant's DC gain (``kp_n / sum K``)."""
    plant = Plant(groups, np.array(gains_w, float), t_com, t_meas)
    total = float(plant.total_gain_w)
    return LowerAdn(name, plant, kp_n / total, ki_n / total, total)


A = adn("a", (WT, CHP), [6e6, 1e6])
B = adn("b", (WT, PV), [3e6, 2e6], kp_n=0.4, ki_n=0.8, t_com=0.05, t_meas=0.1)
TWO = Cascade((A, B), (7e6, 5e6), (0.2, 0.3), 0.2)
KP, KI = 0.1 / 12e6, 0.3 / 12e6


def padé_step(cascade, kp, ki, t):
    _, closed = cascade_models(cascade, kp, ki, order=10)
    return np.squeeze(ct.step_response(closed, T=t).outputs)


def test_step_response_matches_pade_and_a_halved_step():
    run = simulate(TWO, (KP, KI), 60.0)
    fine = simulate(TWO, (KP, KI), 60.0, h=run.h / 2)
    assert run.h == choose_step(TWO)
    assert np.max(np.abs(fine.y[::2] - run.y)) < 1e-5
    assert np.max(np.abs(padé_step(TWO, KP, KI, run.t_s) - run.y)) < 2e-3
    # the shares of the ADNs add up to the whole and settle at K_i / sum K_i
    assert np.allclose(run.y_adn.sum(axis=0), run.y)
    assert run.y_adn[:, -1] == pytest.approx([7 / 12, 5 / 12], abs=2e-3)


def test_open_upper_loop_is_the_lower_loops_own_step_response():
    alone = Cascade((A,), (1.0,), (0.0,), 0.0)
    run = simulate(alone, None, 120.0)
    ours = step_figures(run.t_s, run.y)
    ref = step_info(A.plant, A.kp, A.ki)
    assert ours.rise_time_s == pytest.approx(ref.rise_time_s[0], rel=2e-3)
    assert ours.overshoot_pct == pytest.approx(ref.overshoot_pct[0], abs=0.02)
    assert ours.settling_time_s == pytest.approx(ref.settling_time_s[0], rel=5e-3)


@pytest.mark.parametrize("factor", [0.3, 1.0, 4.0, 10.0, 16.0, 25.0, 60.0])
def test_stability_verdict_agrees_with_pade_poles(factor):
    ours = upper_loop(TWO, KP * factor, KI * factor)
    _, closed = cascade_models(TWO, KP * factor, KI * factor, order=12)
    margin = float(np.max(closed.poles().real))
    assert abs(margin) > 1e-3
    assert ours.lower_stable and ours.resolved
    assert ours.stable == (margin < 0)
    assert (ours.unstable_poles == 0) == (margin < 0)


def test_an_unstable_lower_loop_makes_the_cascade_unstable():
    wild = adn("w", (WT, PV), [3e6, 2e6], kp_n=5.0, ki_n=40.0)
    _, closed = cascade_models(Cascade((wild,), (5e6,), (0.2,), 0.2), KP, KI)
    assert np.max(closed.poles().real) > 0
    loop = upper_loop(Cascade((wild,), (5e6,), (0.2,), 0.2), KP, KI)
    assert not loop.lower_stable and not loop.stable
    fig = cascade_figures(Cascade((wild,), (5e6,), (0.2,), 0.2), KP, KI)
    assert fig.problem(1.5, 1.0) == "a lower ADN's own loop is unstable"


@pytest.mark.parametrize("factor", [1.0, 8.0])
def test_disk_margin_matches_python_control(factor):
    ours = upper_loop(TWO, KP * factor, KI * factor)
    loop, _ = cascade_models(TWO, KP * factor, KI * factor, order=12)
    # python-control's on a wide grid: never below ours (ours is the refined minimum) ...
    wide, _, _ = ct.disk_margins(loop, np.geomspace(1e-3, 1e2, 2001))
    assert float(wide) >= ours.disk_margin * (1 - 1e-6)
    # ... and on a dense grid around the critical frequency, ours
    near = np.geomspace(ours.disk_omega / 1.5, ours.disk_omega * 1.5, 4001)
    dense, _, _ = ct.disk_margins(loop, near)
    assert ours.disk_margin == pytest.approx(float(dense), rel=1e-6)


@pytest.mark.parametrize("lower", [A, B], ids=["slow-start", "dead-time"])
def test_equivalent_model_has_the_closed_loops_10_and_90_percent_times(lower):
    eq = equivalent(lower)
    t = np.arange(0.0, 60.0, 1e-3)
    _, closed = loop_models(lower.plant, lower.kp, lower.ki, 12)
    y = np.squeeze(ct.step_response(closed, T=t).outputs)
    t10, t90 = first_crossing(t, y, 0.1), first_crossing(t, y, 0.9)
    assert eq.rise_time_s == pytest.approx(t90 - t10, abs=5e-3)
    model = lambda s: 1.0 - np.exp(-np.maximum(s - eq.delay_s, 0.0) / eq.lag_s)  # noqa: E731
    assert model(t90) == pytest.approx(0.9, abs=1e-3)
    dead = float(lower.plant.path_delays_s.min())        # nothing moves before it
    exact = simulate(Cascade((lower,), (1.0,), (0.0,), 0.0), None, 2.0)
    assert np.abs(exact.y[exact.t_s < dead - 1e-9]).max() == 0.0 and exact.y[-1] > 0
    assert eq.delay_s >= dead - 1e-12
    if eq.delay_s > dead + 1e-9:
        assert model(t10) == pytest.approx(0.1, abs=1e-3)
    else:       # faster than a lag from its 10 % time: its true dead time, the 90 % time kept
        assert model(t10) < 0.1


def test_back_off_finds_the_largest_step_that_meets_the_constraints():
    factor, fig = back_off(TWO, KP * 6, KI * 6, 1.5, 1.0)
    assert factor is not None and factor < 1.0
    assert fig.disk_margin >= 1.5 and fig.overshoot_pct < 1.0
    bigger = cascade_figures(TWO, KP * 6 * factor / BACK_OFF_STEP, KI * 6 * factor / BACK_OFF_STEP)
    assert bigger.problem(1.5, 1.0) is not None
    # the step response of the backed-off loop is python-control's too
    run = simulate(TWO, (KP * 6 * factor, KI * 6 * factor), 80.0)
    assert step_figures(run.t_s, padé_step(TWO, KP * 6 * factor, KI * 6 * factor, run.t_s)) \
        .overshoot_pct == pytest.approx(fig.overshoot_pct, abs=0.05)


def test_delays_without_a_common_millisecond_are_refused():
    tenth = Cascade((A,), (1.0,), (0.2003,), 0.2)           # a unit of 0.1 ms: taken
    assert choose_step(tenth) == pytest.approx(1e-4)
    odd = Cascade((A,), (1.0,), (0.20003,), 0.2)
    with pytest.raises(ValueError, match="share no unit of at least 0.1 ms"):
        simulate(odd, (KP, KI), 10.0)
    finer = Cascade((A,), (1.0,), (0.2000003,), 0.2)       # below the 1 us the unit is taken to
    with pytest.raises(ValueError, match="not a whole number of steps"):
        simulate(finer, (KP, KI), 10.0)
