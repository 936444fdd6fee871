"""The compiled frequency-domain pass of a constraint check against the numpy path.

``adnmesh.loopmodel.frequency_kernels`` replaces, inside :meth:`TuningProblem.check`, the (M, N) numpy
arrays of the certified grid by one compiled pass per candidate, and ``margins.peak``'s
vectorised rule by the same rule compiled with the loop evaluated inside. These tests compute
the same figures the numpy way (the code before, kept here as the reference) and require the
same verdicts (stable, certified, unstable poles, the screen) and the same disk margins to
rounding, on PT1 plants (SimBench), PT2 and right-half-plane-zero plants, with grids coarse
enough to need the certificate's bisection.
"""
from __future__ import annotations

import numpy as np
import pytest

from adnmesh.loopmodel import stability
from adnmesh.loopmodel.frequency_kernels import first_above, last_at_least, refine_peaks
from adnmesh.loopmodel.frequency_response import as_candidates, loop_points
from adnmesh.loopmodel.evaluation import NyquistData, _grid_pass, _screened_part, disk_margin_bound
from adnmesh.loopmodel.margins import PEAK_XTOL, _dynamics, disk_margin, peak
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.stability import _poly_abs, certified_grid, nyquist_stability

from loops import CONFIG, plant


def _candidates(model: str = "pt1", m: int = 600, seed: int = 3, reach: float = 1.0):
    """A plant of every SimBench group (model ``model``) with M random power fractions and
    normalised gains spread over the global search's whole range (``reach`` times higher)."""
    rng = np.random.default_rng(seed)
    base = plant(list(CONFIG.der_ids())).with_model(model)
    acts = tuple(dict.fromkeys(base.actuators))
    fractions = rng.dirichlet([0.4] * len(acts), m)
    kp = np.exp(rng.uniform(np.log(1e-2), np.log(1.5 * reach), m))
    ki = np.exp(rng.uniform(np.log(1e-3), np.log(3.0 * reach), m))
    return Plant(acts, fractions, base.t_com_s, base.t_meas_s), kp, ki


def _sampled_alpha(loop):
    """The sampled disk-margin bound ``2 / max |1 - L| / |1 + L|`` of samples (M, N)."""
    return 2.0 / (np.abs(1.0 - loop) / np.abs(1.0 + loop)).max(axis=1)


def _numpy_screened(p: Plant, kp, ki, screen_min: float, per_decade: int = 100):
    """The constraint check's frequency part as numpy computed it (the reference)."""
    kp, ki, gains = as_candidates(p, kp, ki)
    grid = certified_grid(p, kp, ki, per_decade)
    upper = _sampled_alpha(grid[1])
    keep = upper >= screen_min
    nyq = nyquist_stability(p, kp, ki, per_decade, grid=grid, only=keep)
    alpha, omega = upper.copy(), np.full(kp.size, np.nan)
    if keep.any():
        sub = Plant(p.actuators, gains[keep], p.t_com_s, p.t_meas_s)
        part = NyquistData(nyq.omega, grid[1][keep], nyq.stable[keep], nyq.unstable_poles[keep],
                           nyq.certified[keep])
        d = disk_margin(sub, kp[keep], ki[keep], part)
        alpha[keep], omega[keep] = d.alpha, d.omega
    return nyq, alpha, omega, keep


@pytest.mark.parametrize("model", ["pt1", "pt2", "rhpz"])
@pytest.mark.parametrize("screened", [True, False])
def test_check_frequency_part_matches_numpy(model, screened):
    p, kp, ki = _candidates(model, reach=1.0 if screened else 10.0)
    # the check's limit, or none (every candidate certified: the unstable ones too)
    limit = CONFIG.constraints.disk_margin_min if screened else 0.0
    nyq, alpha, omega, keep = _numpy_screened(p, kp, ki, limit)
    new_nyq, new_dm, _ = _screened_part(p, kp, ki, limit)
    if screened:
        assert keep.sum() > 50 and (~keep).sum() > 50              # both sides exercised
    else:
        assert keep.all() and (nyq.unstable_poles > 0).sum() > 30
    assert nyq.stable.sum() > 20
    np.testing.assert_array_equal(new_nyq.stable, nyq.stable)
    np.testing.assert_array_equal(new_nyq.certified, nyq.certified)
    np.testing.assert_array_equal(new_nyq.unstable_poles, nyq.unstable_poles)
    np.testing.assert_allclose(new_dm.alpha, alpha, rtol=1e-12, atol=0)
    # the peak's place: located to PEAK_XTOL in ln omega where the value is flat
    both = np.isfinite(omega)
    np.testing.assert_array_equal(np.isfinite(new_dm.omega), both)
    np.testing.assert_allclose(np.log(new_dm.omega[both]), np.log(omega[both]), rtol=0,
                               atol=1e-4)


def test_certificate_bisection_gives_the_same_verdicts():
    # 3 frequencies per decade: most grid intervals fail the Lipschitz test and are bisected
    # (every candidate certified, unstable ones among them)
    p, kp, ki = _candidates("pt1", m=300, seed=5, reach=10.0)
    limit = 0.0
    nyq, _, _, keep = _numpy_screened(p, kp, ki, limit, per_decade=3)
    omega, out = _grid_pass(p, kp, ki, limit, per_decade=3)
    bad, new_keep = out[6], out[4]
    np.testing.assert_array_equal(new_keep, keep)
    assert bad[keep].sum() > 10 * keep.sum()                       # the bisection is used
    kp_b, ki_b, gains = as_candidates(p, kp, ki)
    st, poles, cert = stability.winding_verdict(
        Plant(p.actuators, gains[keep], p.t_com_s, p.t_meas_s), kp_b[keep], ki_b[keep],
        gains[keep], omega, out[5][keep], bad[keep])
    np.testing.assert_array_equal(st, nyq.stable[keep])
    np.testing.assert_array_equal(poles, nyq.unstable_poles[keep])
    np.testing.assert_array_equal(cert, nyq.certified[keep])
    assert (poles > 0).any() and (poles == 0).any()


def test_disk_margin_bound_matches_the_sampled_numpy_bound():
    p, kp, ki = _candidates("pt1", m=500, seed=7)
    for per_decade in (25, 100):
        ref = _sampled_alpha(certified_grid(p, kp, ki, per_decade)[1])
        np.testing.assert_allclose(disk_margin_bound(p, kp, ki, per_decade), ref, rtol=1e-13)


@pytest.mark.parametrize("model", ["pt1", "pt2", "rhpz"])
def test_compiled_peak_refinement_is_numpys(model):
    p, kp, ki = _candidates(model, m=300, seed=11)
    kp, ki, gains = as_candidates(p, kp, ki)
    omega, loop = certified_grid(p, kp, ki)
    q = np.abs(1.0 - loop) / np.abs(1.0 + loop)
    k = np.clip(np.argmax(q, axis=1), 1, omega.size - 2)
    rows = np.arange(kp.size)
    logw = np.log(omega)

    def value(x, i):
        lw = loop_points(p, kp[i], ki[i], gains[i], np.exp(x))
        return np.abs(1.0 - lw) / np.abs(1.0 + lw)

    x_ref, f_ref = peak(value, logw[k - 1], logw[k], logw[k + 1], q[rows, k - 1], q[rows, k],
                        q[rows, k + 1])
    num, den, delays = _dynamics(p.actuators, float(p.t_com_s + p.t_meas_s))
    x, f = refine_peaks(np.ascontiguousarray(kp), np.ascontiguousarray(ki),
                        np.ascontiguousarray(gains), num, den, delays, logw[k - 1], logw[k],
                        logw[k + 1], q[rows, k - 1], q[rows, k], q[rows, k + 1], PEAK_XTOL, 60)
    np.testing.assert_allclose(f, f_ref, rtol=1e-13)
    # the place: to PEAK_XTOL where the peak is sharp; where it is flat to rounding, the
    # last bits of the values move it further (one of 300 here: 1.4e-6)
    close = np.abs(x - x_ref) <= 10 * PEAK_XTOL
    assert close.mean() > 0.98 and np.all(np.abs(x - x_ref) < 1e-4)
    np.testing.assert_allclose(value(x, rows), value(x_ref, rows), rtol=1e-13)
    assert np.all(f >= q[rows, k])                     # never below the sampled peak


def _low_reference(p: Plant, kp, ki, gains):
    """:func:`stability._low_frequency_limit` on whole arrays (the numpy code before)."""
    grid = stability._LOW_GRID
    frac = gains / gains.sum(axis=1, keepdims=True)
    theta = p.loop_delays_s
    rho, beta = [], []
    for act in p.actuators:
        n = np.zeros(max(act.numerator.size, act.denominator.size))
        d = np.zeros_like(n)
        n[: act.numerator.size] = act.numerator
        d[: act.denominator.size] = act.denominator
        rho.append(_poly_abs(act.numerator, grid))
        beta.append(_poly_abs(np.concatenate([[0.0], (n - d)[1:]]), grid))
    rho, beta = np.array(rho), np.array(beta)
    bound = grid * (kp / ki)[:, None] * (frac @ rho) + frac @ (beta + rho * grid * theta[:, None])
    bad = bound > 0.5
    return grid[np.where(bad.any(axis=1), np.argmax(bad, axis=1), bad.shape[1]) - 1]


def _high_reference(p: Plant, kp, ki, gains, level):
    grid = stability._HIGH_GRID
    lo, hi = grid[:-1], grid[1:]
    rho, _ = stability._group_bounds(p, lo, hi)
    env = (kp[:, None] + ki[:, None] / lo) * (gains @ rho)
    big = env >= level
    last = np.where(big.any(axis=1), big.shape[1] - 1 - np.argmax(big[:, ::-1], axis=1), -1)
    return np.where(last >= 0, hi[np.maximum(last, 0)], lo[0])


@pytest.mark.parametrize("model", ["pt1", "pt2", "rhpz"])
def test_certificate_limits_match_numpy(model):
    p, kp, ki = _candidates(model, m=400, seed=13)
    kp, ki, gains = as_candidates(p, kp, ki)
    np.testing.assert_array_equal(stability._low_frequency_limit(p, kp, ki, gains),
                                  _low_reference(p, kp, ki, gains))
    for level in (1.0, 0.01):
        np.testing.assert_array_equal(stability._high_frequency_limit(p, kp, ki, gains, level),
                                      _high_reference(p, kp, ki, gains, level))


def test_limit_scans_on_edge_cases():
    grid = np.array([1.0, 2.0, 3.0])
    rho = np.ones((1, 3))
    # never above the level: the grid's size; above at once: 0
    assert first_above(np.array([0.0]), np.ones((1, 1)), rho, np.zeros((1, 3)), grid,
                       0.5)[0] == 3
    assert first_above(np.array([1.0]), np.ones((1, 1)), rho, np.zeros((1, 3)), grid,
                       0.5)[0] == 0
    lo = np.array([1.0, 2.0])
    for monotone in (True, False):                 # bisection and scan
        assert last_at_least(np.array([0.0]), np.array([1e-9]), np.ones((1, 1)),
                             np.ones((1, 2)), lo, 1.0, monotone)[0] == -1
        assert last_at_least(np.array([5.0]), np.array([0.0]), np.ones((1, 1)),
                             np.ones((1, 2)), lo, 1.0, monotone)[0] == 1
        assert last_at_least(np.array([1.0]), np.array([2.0]), np.ones((1, 1)),
                             np.ones((1, 2)), lo, 2.5, monotone)[0] == 0
