"""The compiled step-response kernels agree bit for bit where they overlap."""
from __future__ import annotations

import numpy as np
import pytest

from adnmesh import _kernels, stepresp
from adnmesh.plant import Actuator, Plant
from adnmesh.stepresp import _Simulator


def _simulator(m: int, seed: int, lanes: bool | None = None) -> _Simulator:
    """M loops of a three-group first-order plant (SimBench's dynamics), varied gains."""
    rng = np.random.default_rng(seed)
    acts = (Actuator(0.01, 0.234), Actuator(1.0, 11.18), Actuator(0.01, 0.0455))
    gains = rng.dirichlet(np.ones(3), m)
    plant = Plant(acts, gains, 0.1, 0.1)
    return _Simulator(plant, rng.uniform(0.05, 0.6, m), rng.uniform(0.01, 0.3, m), 0.0025,
                      lanes=lanes)


def _general(kernel):
    """``kernel`` (a general one) called with the first-order kernels' arguments: the
    one-state arrays as views of the general shapes, (M, G, 1) and (G, 1, 1)."""
    def call(steps, k0, ring, h, kp, ki, kc, phi, gl, gr, x, *rest):
        kernel(steps, k0, ring, h, kp, ki, kc[:, :, None], phi[:, None, None], gl[:, None],
               gr[:, None], x[:, :, None], *rest)
    return call


@pytest.mark.parametrize("m", [5, _kernels.PARALLEL_FROM + 3])       # serial and parallel
def test_first_order_kernels_are_the_general_ones_bit_for_bit(m: int, monkeypatch) -> None:
    """The specialised first-order kernels (which :class:`_Simulator` runs for PT1 plants:
    with the candidates as the inner loop, "lanes", and candidate by candidate) give exactly
    the outputs and states of the general kernels, across block boundaries and step
    doublings: 2.5 ms and 5 ms (whole-step delays, :func:`advance_exact`), then 20 ms and
    40 ms (interpolated delays, :func:`advance`)."""
    lanes, fast, general = _simulator(m, 3), _simulator(m, 3, False), _simulator(m, 3, False)
    assert fast.order == 1 and lanes.lanes and not fast.lanes

    def general_run(steps: int) -> np.ndarray:
        with monkeypatch.context() as patch:
            patch.setattr(stepresp, "advance_exact_first_order", _general(_kernels.advance_exact))
            patch.setattr(stepresp, "advance_first_order", _general(_kernels.advance))
            return general.run(steps)

    exact = []
    for steps in (1, 37, 2000, 400, 300):
        exact.append(fast.exact_delays)
        out = general_run(steps)
        assert np.array_equal(fast.run(steps), out)
        assert np.array_equal(lanes.run(steps), out)
        if fast.k % 2:
            out = general_run(1)
            assert np.array_equal(fast.run(1), out) and np.array_equal(lanes.run(1), out)
        if fast.can_coarsen():
            for sim in (lanes, fast, general):
                sim.coarsen()
    assert exact == [True, True, True, False, False]
    for name in ("x", "p_y", "y_hist", "x_int", "err"):
        assert np.array_equal(getattr(fast, name), getattr(general, name)), name
    # the lanes layout: buffers (ring + 1, M), states (G, M)
    assert np.array_equal(lanes.x.T, fast.x[:, :, 0])
    for name in ("p_y", "y_hist"):
        assert np.array_equal(getattr(lanes, name).T, getattr(fast, name)), name
    for name in ("x_int", "err"):
        assert np.array_equal(getattr(lanes, name), getattr(fast, name)), name
    keep = np.arange(m)[::2]
    lanes.keep(keep)
    fast.keep(keep)
    assert np.array_equal(lanes.run(50), fast.run(50))
    assert np.abs(fast.run(10)).max() > 0.5                            # a real response


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
        got = _kernels.delay_taps(first, steps, n, f, 113, right_end)
        want = _taps_numpy(n, f, first, steps, 113, right_end)
        for g, w in zip(got, want):
            assert g.shape == w.shape and np.array_equal(g, w)
