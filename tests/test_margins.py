"""Disk and classical margins against closed forms and python-control with Padé delays."""
import numpy as np
import pytest

from adnmesh.loopmodel.margins import classical_margins, disk_margin
from adnmesh.loopmodel.stability import nyquist_stability

from loops import LOOPS, gains
from pade_reference import reference_figures
from test_stability import integrator_with_delay


def _margins(plant, kp, ki):
    nyq = nyquist_stability(plant, kp, ki)
    return nyq, disk_margin(plant, kp, ki, nyq), classical_margins(plant, kp, ki, nyq)


@pytest.mark.parametrize("k_tau", [0.2, 0.6, 1.0, 1.4])
def test_integrator_delay_closed_forms(k_tau):
    tau = 0.4
    k = k_tau / tau
    plant, kp, ki = integrator_with_delay(k, tau)
    _, dm, cm = _margins(plant, kp, ki)
    # L = k e^{-s tau}/s: |L| = 1 at w = k, phase crossover at w tau = pi/2
    assert cm.phase_margin_deg[0] == pytest.approx(90.0 - np.degrees(k_tau), rel=1e-9)
    assert cm.phase_margin_omega[0] == pytest.approx(k, rel=1e-9)
    assert cm.gain_margin[0] == pytest.approx(np.pi / (2 * k_tau), rel=1e-9)
    assert cm.gain_margin_omega[0] == pytest.approx(np.pi / (2 * tau), rel=1e-9)
    assert cm.delay_margin_s[0] == pytest.approx((np.pi / 2 - k_tau) / k, rel=1e-9)
    # disk margin: 2 min |1+L|/|1-L| by brute force on a very fine grid
    w = np.geomspace(1e-3, 1e3, 2_000_001) / tau
    lw = k * np.exp(-1j * w * tau) / (1j * w)
    alpha = 2.0 * np.min(np.abs(1 + lw) / np.abs(1 - lw))
    assert dm.alpha[0] == pytest.approx(alpha, rel=1e-7)
    lo, hi = dm.gain_margin[0]
    assert lo == pytest.approx((2 - alpha) / (2 + alpha), rel=1e-6)
    assert hi == pytest.approx((2 + alpha) / (2 - alpha), rel=1e-6)
    assert dm.phase_margin_deg[0] == pytest.approx(np.degrees(2 * np.arctan(alpha / 2)), rel=1e-6)


@pytest.mark.parametrize("name", list(LOOPS))
def test_margins_agree_with_python_control(name):
    plant, kp, ki = gains(name)
    ref = reference_figures(plant, kp, ki)
    nyq, dm, cm = _margins(plant, kp, ki)
    assert nyq.stable[0] and ref["stable"]
    assert dm.alpha[0] == pytest.approx(ref["disk_margin"], rel=2e-5)
    assert cm.phase_margin_deg[0] == pytest.approx(ref["phase_margin_deg"], rel=1e-5)
    assert cm.phase_margin_omega[0] == pytest.approx(ref["phase_margin_omega"], rel=1e-5)
    assert cm.delay_margin_s[0] == pytest.approx(ref["delay_margin_s"], rel=1e-5)
    if np.isfinite(ref["gain_margin"]):
        assert cm.gain_margin[0] == pytest.approx(ref["gain_margin"], rel=1e-4)
        assert cm.gain_margin_omega[0] == pytest.approx(ref["gain_margin_omega"], rel=1e-4)


def test_all_crossovers_are_reported():
    # a large delay makes the Nyquist curve cross the negative real axis many times
    plant, kp, ki = integrator_with_delay(0.5, 2.0)
    _, _, cm = _margins(plant, kp, ki)
    gms = cm.all_gain_margins[0]
    assert gms.size >= 5
    # crossings at w tau = pi/2 + 2 pi n: GM_n = w_n / k
    n = np.arange(gms.size)
    np.testing.assert_allclose(gms, (np.pi / 2 + 2 * np.pi * n) / 2.0 / 0.5, rtol=1e-9)


def _crossings_of(plant, kp, ki):
    """Phase and gain crossings of a loop on its certified grid: (fun, lo, hi) per kind."""
    from adnmesh.loopmodel.frequency_response import as_candidates, loop_points
    nyq = nyquist_stability(plant, kp, ki)
    kp, ki, g = as_candidates(plant, kp, ki)
    logw = np.log(nyq.omega)
    out = []
    for part in (lambda v: v.imag, lambda v: np.abs(v) - 1.0):
        val = part(nyq.loop)
        m, k = np.nonzero(np.sign(val[:, :-1]) != np.sign(val[:, 1:]))

        def fun(x, i, m=m, part=part):
            return part(loop_points(plant, kp[m[i]], ki[m[i]], g[m[i]], np.exp(x)))
        out.append((fun, logw[k], logw[k + 1]))
    return out


@pytest.mark.parametrize("name", list(LOOPS))
def test_crossings_are_scipys_roots(name):
    # the regula falsi of the margins against scipy's bracketing root finder (Chandrupatla)
    from scipy.optimize import elementwise
    from adnmesh.loopmodel.margins import CROSSING_XTOL, crossing
    plant, kp, ki = gains(name)
    for fun, lo, hi in _crossings_of(plant, kp, ki):
        assert lo.size
        ours = crossing(fun, lo, hi)
        ref = elementwise.find_root(lambda x, i: fun(x, i.astype(int)), (lo, hi),
                                    args=(np.arange(lo.size).astype(float),),
                                    tolerances={"xatol": CROSSING_XTOL, "xrtol": 0.0})
        assert ref.success.all()
        assert np.all((ours >= lo) & (ours <= hi))
        np.testing.assert_allclose(ours, ref.x, rtol=0, atol=4 * CROSSING_XTOL)


def test_crossing_on_hard_brackets():
    # a root at an end, a flat-then-steep function, and many brackets at once
    from adnmesh.loopmodel.margins import crossing
    lo = np.array([0.0, 0.0, -1.0, 0.1])
    hi = np.array([1.0, 2.0, 1.0, 3.0])
    funs = [lambda x: x, lambda x: x ** 9 - 1.0, lambda x: np.cbrt(x - 0.3), lambda x: np.cos(x)]
    roots = crossing(lambda x, i: np.array([funs[j](v) for j, v in zip(i, x)]), lo, hi)
    np.testing.assert_allclose(roots, [0.0, 1.0, 0.3, np.pi / 2], atol=1e-12)


def test_disk_margin_peak_is_scipys_maximum():
    # the parabolic peak search of the disk margin against scipy's bracketed minimiser on the
    # same bracket of the certified grid, for 200 random SimBench-like loops
    from scipy.optimize import elementwise
    from adnmesh.config import load_config
    from adnmesh.loopmodel.frequency_response import as_candidates, loop_points
    from adnmesh.tuning import TuningProblem
    from conftest import REPO_ROOT
    problem = TuningProblem(load_config(REPO_ROOT / "configs" / "simbench.yaml"))
    rng = np.random.default_rng(3)
    m = 200
    f = rng.dirichlet(np.full(len(problem.actuators), 0.5), m)
    kp = np.exp(rng.uniform(np.log(0.01), 0.0, m))
    ki = np.exp(rng.uniform(np.log(1e-3), np.log(0.5), m))
    plant = problem.plant(f)
    nyq = nyquist_stability(plant, kp, ki)
    dm = disk_margin(plant, kp, ki, nyq)
    kp_, ki_, g = as_candidates(plant, kp, ki)
    q = np.abs(1 - nyq.loop) / np.abs(1 + nyq.loop)
    k = np.argmax(q, axis=1)
    ok = nyq.stable & (k > 0) & (k < q.shape[1] - 1)
    assert ok.sum() > 100
    idx = np.nonzero(ok)[0]
    logw = np.log(nyq.omega)

    def minus_q(x, i):
        i = idx[i.astype(int)]
        lw = loop_points(plant, kp_[i], ki_[i], g[i], np.exp(x))
        return -np.abs(1 - lw) / np.abs(1 + lw)
    ref = elementwise.find_minimum(minus_q, (logw[k[idx] - 1], logw[k[idx]], logw[k[idx] + 1]),
                                   args=(np.arange(idx.size).astype(float),),
                                   tolerances={"xatol": 1e-9, "xrtol": 0.0})
    assert ref.success.all()
    np.testing.assert_allclose(dm.alpha[idx], 2.0 / -ref.f_x, rtol=1e-11)


def test_peak_on_hard_brackets():
    # a sharp non-quadratic peak, a flat top, a peak at the bracket's edge of its middle
    from adnmesh.loopmodel.margins import PEAK_XTOL, peak
    funs = [lambda x: -np.abs(x - 0.3) ** 1.5, lambda x: -np.maximum(np.abs(x) - 0.2, 0.0) ** 2,
            lambda x: -(x - 0.999) ** 2, lambda x: np.exp(-1e4 * (x - 0.123) ** 2)]
    x0, x1, x2 = np.zeros(4) - 1.0, np.array([0.0, 0.0, 0.99, 0.1]), np.ones(4)
    fun = lambda x, i: np.array([funs[j](v) for j, v in zip(i, x)])      # noqa: E731
    x, f = peak(fun, x0, x1, x2, fun(x0, np.arange(4)), fun(x1, np.arange(4)),
                fun(x2, np.arange(4)))
    assert abs(x[0] - 0.3) < 1e-5 and abs(x[2] - 0.999) < 1e-5 and abs(x[3] - 0.123) < 1e-5
    assert abs(x[1]) <= 0.2 and f[1] == 0.0
    np.testing.assert_allclose(f, [0.0, 0.0, 0.0, 1.0], atol=1e-8)
    assert PEAK_XTOL <= 1e-6
