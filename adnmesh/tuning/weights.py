"""Find W (SPEC §3.4): lower a DER's weight while its single-DER loop violates a constraint.

With the subset's gains fixed, DER a alone forms the loop ``C(s) e^{-s T_com} w_a P_a G_a(s)
e^{-s T_meas}``. While that loop violates the disk-margin or overshoot constraint, ``w_a`` is
lowered in steps of 0.001 from 1. The steps are evaluated in blocks (vectorised) but the result
is exactly the first weight of the sequence 1, 0.999, ... that meets both constraints.
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
    for j in violating:
        e, d = jobs[j]
        w_found = 0.0
        for start in range(0, steps.size, _BLOCK):
            w = np.round(1.0 - steps[start:start + _BLOCK] * W_STEP, 3)
            ok = problem.check(np.outer(w, gains[j]), np.full(w.size, kp[j]),
                               np.full(w.size, ki[j])).feasible
            if ok.any():
                w_found = float(w[np.argmax(ok)])
                break
        weights[e][d] = w_found
    return weights
