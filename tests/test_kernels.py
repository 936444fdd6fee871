"""The compiled step-response kernels agree bit for bit where they overlap."""
from __future__ import annotations

import numpy as np
import pytest

from adnmesh.loopmodel import step_kernels
from adnmesh.loopmodel.plant import Actuator, Plant
from adnmesh.loopmodel.step_response import _Simulator


def _simulator(m: int, seed: int, lanes: bool | None = None) -> _Simulator:
    """M loops of a three-group first-order plant (SimBench's dynamics), varied gains."""
    rng = np.random.default_rng(seed)
    acts = (Actuator(0.01, 0.234), Actuator(1.0, 11.18), Actuator(0.01, 0.0455))
    gains = rng.dirichlet(np.ones(3), m)
    plant = Plant(acts, gains, 0.1, 0.1)
    return _Simulator(plant, rng.uniform(0.05, 0.6, m), rng.uniform(0.01, 0.3, m), 0.0025,
                      lanes=lanes)


@pytest.mark.parametrize("m", [5, step_kernels.PARALLEL_FROM + 3])       # serial and parallel
def test_lanes_kernels_are_the_general_ones_bit_for_bit(m: int) -> None:
    """The first-order kernels with the candidates as the inner loop ("lanes", which
    :class:`_Simulator` runs for PT1 plants) give exactly the outputs and states of the
    general kernels run candidate by candidate, across block boundaries, step doublings
    and dropped candidates: 2.5 ms and 5 ms (whole-step delays, :func:`advance_exact`), then
    20 ms and 40 ms (interpolated delays, :func:`advance`); serial and parallel."""
    lanes, general = _simulator(m, 3), _simulator(m, 3, False)
    assert general.order == 1 and lanes.lanes and not general.lanes
    exact = []
    for steps in (1, 37, 2000, 400, 300):
        exact.append(general.exact_delays)
        assert np.array_equal(lanes.run(steps), general.run(steps))
        if general.k % 2:
            assert np.array_equal(lanes.run(1), general.run(1))
        if general.can_coarsen():
            lanes.coarsen()
            general.coarsen()
    assert exact == [True, True, True, False, False]
    # the lanes layout: buffers (ring + 1, M), states (G, M)
    assert np.array_equal(lanes.x.T, general.x[:, :, 0])
    for name in ("p_y", "y_hist"):
        assert np.array_equal(getattr(lanes, name).T, getattr(general, name)), name
    for name in ("x_int", "err"):
        assert np.array_equal(getattr(lanes, name), getattr(general, name)), name
    keep = np.arange(m)[::2]
    lanes.keep(keep)
    general.keep(keep)
    assert np.array_equal(lanes.run(50), general.run(50))
    assert np.abs(general.run(10)).max() > 0.5                         # a real response


@pytest.mark.parametrize("h", [0.04, 0.03])
def test_lanes_with_interpolated_delays_from_the_first_step(h: float) -> None:
    """A step that is no divisor of the delays from t = 0 on (0.11 s, 1.1 s forward, 0.1 s
    measured; 0.03 s gives thirds, not exact in binary): the lanes kernel, which follows
    each tap from one step to the next, reads the same columns as the taps computed for
    every sample, also where they start before t = 0."""
    rng = np.random.default_rng(5)
    acts = (Actuator(0.01, 0.234), Actuator(1.0, 11.18), Actuator(0.01, 0.0455))
    gains = rng.dirichlet(np.ones(3), 7)
    plant = Plant(acts, gains, 0.1, 0.1)
    kp, ki = rng.uniform(0.05, 0.6, 7), rng.uniform(0.01, 0.3, 7)
    lanes, rows = (_Simulator(plant, kp, ki, h, lanes=flag) for flag in (True, False))
    assert not lanes.exact_delays and lanes.lanes and not rows.lanes
    for steps in (1, 2, 5, 300, 41):
        assert np.array_equal(lanes.run(steps), rows.run(steps))
    assert np.array_equal(lanes.p_y.T, rows.p_y) and np.array_equal(lanes.x.T, rows.x[:, :, 0])


def _taps_numpy(n, f, first: int, steps: int, ring: int, right_end: bool):
    """The delay taps in numpy (the implementation before the compiled one)."""
    pos = np.arange(first, first + steps)[:, None] - n[None, :] - f[None, :]
    j0 = np.floor(pos + 1e-9).astype(int)
    zero = pos < -1e-9
    if right_end:
        zero |= np.abs(pos) < 1e-9
    c0 = np.where(zero | (j0 < 0), ring, j0 % ring)
    c1 = np.where(zero, ring, (j0 + 1) % ring)
    return c0, c1, np.where(zero, 0.0, pos - j0)


@pytest.mark.parametrize("right_end", [False, True])
def test_compiled_delay_taps_are_the_numpy_ones(right_end: bool) -> None:
    """Columns and weights of delayed samples, from before t = 0 (the zero column) to far
    into a run, whole and fractional delays (including thirds, not exact in binary)."""
    n = np.array([0, 5, 27, 110, 3])
    f = np.array([0.0, 0.75, 0.5, 1 / 3, 0.875])
    for first, steps in ((0, 40), (1, 300), (999_983, 64)):
        got = step_kernels.delay_taps(first, steps, n, f, 113, right_end)
        want = _taps_numpy(n, f, first, steps, 113, right_end)
        for g, w in zip(got, want):
            assert g.shape == w.shape and np.array_equal(g, w)
