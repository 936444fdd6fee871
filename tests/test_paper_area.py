"""The paper's area search (docs/method.md#convexity-indicator-and-area-search) finds the fastest
feasible point of its rectangle
without checking every point: the same point as checking them all."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from adnmesh.config import load_config
from adnmesh.tuning import paper
from adnmesh.tuning.build import group_subsets
from adnmesh.tuning.problem import TuningProblem, all_subsets

CONFIGS = Path(__file__).resolve().parent.parent / "configs" / "examples"


def test_the_area_search_finds_the_point_a_check_of_every_point_finds() -> None:
    config = load_config(CONFIGS / "mixed-4.yaml")
    problem = TuningProblem(config)
    groups = group_subsets(problem, all_subsets(list(config.der_ids())))
    fractions = np.array([g.fractions for g in groups])
    res = paper.tune_paper(problem, fractions)
    # rectangles from below each plant's result (many feasible points in each)
    f, kp, ki, ki0 = fractions, res.kp, 0.2 * res.ki, res.ki_init
    rows, kps, kis = paper._rectangles(kp, ki, ki0, paper.STEPS[-1])
    chk = problem.check(f[rows], kps, kis)                 # every point, as before
    rise = np.where(chk.feasible, chk.rise_time_s, np.inf)
    best = np.array([np.nonzero(rows == p)[0][np.argmin(rise[rows == p])]
                     for p in range(len(f))])
    assert np.isfinite(rise[best]).sum() >= 8
    ak, ai, ar, evaluations = paper.area_search(problem, f, kp, ki, ki0, paper.STEPS[-1])
    assert evaluations < 1.5 * rows.size                    # screened and simulated to 90 %
    found = np.isfinite(rise[best])
    assert np.array_equal(np.isfinite(ar), found)
    assert np.array_equal(ak[found], kps[best[found]])
    assert np.array_equal(ai[found], kis[best[found]])
    np.testing.assert_allclose(ar[found], rise[best[found]], rtol=1e-6)
    # a bound to beat: the same point if it is faster, none if it is not
    beat = np.where(np.arange(len(f)) % 2, rise[best] * 1.001, rise[best] * 0.999)
    bk, _, br, _ = paper.area_search(problem, f, kp, ki, ki0, paper.STEPS[-1], beat)
    faster = found & (np.arange(len(f)) % 2 == 1)
    assert np.array_equal(bk[faster], kps[best[faster]])
    assert np.isnan(br[~faster]).all()
