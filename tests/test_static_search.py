"""The static pair's search shortcuts change no result: the screen of rays that cannot beat
the best one, and the least-limit bisection that stops at rows which cannot be the least."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from adnmesh.config import load_config
from adnmesh.tuning import static_controller as static
from adnmesh.tuning.problem import TuningProblem, all_subsets

CONFIGS = Path(__file__).resolve().parent.parent / "configs" / "examples"


def _every_row_bisected(problem, fractions, totals, rho, lo, hi, plants, ray, n_rays, t_max_s):
    """Reference for ``_least_limits``: every row bisected to the end, then the least."""
    lo, hi = lo.copy(), hi.copy()
    for _ in range(static.BISECTIONS):
        mid = 0.5 * (lo + hi)
        chk = problem.check(fractions[plants], np.exp(mid), rho * np.exp(mid), t_max_s=t_max_s)
        ok = chk.feasible | (chk.reason == "slow")
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    least = np.full(n_rays, np.inf)
    np.minimum.at(least, ray, np.exp(lo) / totals[plants])
    return least


def test_the_static_search_shortcuts_give_the_pair_of_the_full_search(monkeypatch) -> None:
    config = load_config(CONFIGS / "mixed-4.yaml")
    problem = TuningProblem(config)
    cases = all_subsets(list(config.der_ids()))
    screened = []
    screen = static._slower_than
    monkeypatch.setattr(static, "_slower_than",
                        lambda *a: screened.append(screen(*a)) or screened[-1])
    _, _, fast = static.design_over(problem, cases)
    assert fast.feasible and sum(screened) >= 5          # most rays never verified
    with monkeypatch.context() as full:
        full.setattr(static, "_slower_than", lambda *a: False)
        full.setattr(static, "_least_limits", _every_row_bisected)
        _, _, reference = static.design_over(problem, cases)
    assert (fast.kp, fast.ki, fast.worst_rise_time_s) == (
        reference.kp, reference.ki, reference.worst_rise_time_s)
