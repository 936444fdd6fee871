"""Find W (SPEC §3.4): lower a DER's weight while its single-DER loop violates a constraint.

With the subset's gains fixed, DER a alone forms the loop ``C(s) e^{-s T_com} w_a P_a G_a(s)
e^{-s T_meas}``. While that loop violates the disk-margin or overshoot constraint, ``w_a`` is
lowered in steps of 0.001 from 1. The steps are evaluated in blocks of 64, every pending DER's
block in one batch, but the result is exactly the first weight of the sequence 1, 0.999, ...
that meets both constraints.
"""
from __future__ import annotations

import numpy as np

from .problem import TuningProblem

__all__ = ["find_weights", "W_STEP"]

W_STEP = 0.001
_BLOCK = 64


def find_weights(problem: TuningProblem, entries: list[tuple[tuple[str, ...], float, float]]):
    """Weights for each ``(ders, K_P, K_I)`` (gains in 1/W and 1/(W s)).

    Returns a list of dicts ``{der id: w}``; ``w`` is 0.0 if even ``w = 0.001`` violates (the DER
    is then left out of the loop, which the caller reports).
    """
    jobs = [(e, d) for e, (ders, _, _) in enumerate(entries) for d in ders]
    weights = [{d: 1.0 for d in ders} for ders, _, _ in entries]
    if not jobs:
        return weights
    # every single-DER loop at w = 1 in one batch
    gains = np.array([problem.group_power([d]) for _, d in jobs])
    kp = np.array([entries[e][1] for e, _ in jobs])
    ki = np.array([entries[e][2] for e, _ in jobs])
    violating = np.nonzero(~problem.check(gains, kp, ki).feasible)[0]
    steps = np.arange(1, int(round(1 / W_STEP)))            # w = 1 - k * 0.001, k >= 1
    found = np.zeros(violating.size)                        # 0.0 until a weight meets both
    pending = np.arange(violating.size)
    # block b of the sequence for every job still pending, all jobs in one batch
    for start in range(0, steps.size, _BLOCK):
        if pending.size == 0:
            break
        w = np.round(1.0 - steps[start:start + _BLOCK] * W_STEP, 3)
        jobs_v = violating[pending]
        rows = np.repeat(jobs_v, w.size)
        ww = np.tile(w, jobs_v.size)
        ok = problem.check(gains[rows] * ww[:, None], kp[rows], ki[rows]).feasible
        ok = ok.reshape(jobs_v.size, w.size)
        hit = ok.any(axis=1)
        found[pending[hit]] = w[np.argmax(ok[hit], axis=1)]
        pending = pending[~hit]
    for j, w_found in zip(violating, found):
        e, d = jobs[j]
        weights[e][d] = float(w_found)
    return weights
