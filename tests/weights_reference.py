"""Find W by the plain scan of 1, 0.999, ... (slow): the reference that
:func:`adnmesh.tuning.weights.find_weights` is tested against (``tests/test_tuning_speed.py``).

The scan checks the weights of every violating single-DER loop in sequence order (blocks of
64 at a time) and takes the first feasible one; the package's search skips the weights the
sampled disk margin rules out and must give the same answer.
"""
from __future__ import annotations

import numpy as np

from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.weights import _BLOCK, _N_STEPS, _feasible, _jobs, _weight

__all__ = ["find_weights_sequential"]


def _scan(problem, gains, kp, ki, violating) -> np.ndarray:
    """The sequential scan (blocks of 64 weights) for jobs ``violating``; weights found."""
    steps = np.arange(1, _N_STEPS + 1)
    found = np.zeros(violating.size)
    pending = np.arange(violating.size)
    for start in range(0, steps.size, _BLOCK):
        if pending.size == 0:
            break
        w = _weight(steps[start:start + _BLOCK])
        jobs_v = violating[pending]
        rows = np.repeat(jobs_v, w.size)
        ww = np.tile(w, jobs_v.size)
        ok = _feasible(problem, gains[rows] * ww[:, None], kp[rows], ki[rows])
        ok = ok.reshape(jobs_v.size, w.size)
        hit = ok.any(axis=1)
        found[pending[hit]] = w[np.argmax(ok[hit], axis=1)]
        pending = pending[~hit]
    return found


def find_weights_sequential(problem: TuningProblem, entries):
    """:func:`~adnmesh.tuning.weights.find_weights` by the plain scan of 1, 0.999, ..."""
    weights = [{d: 1.0 for d in ders} for ders, _, _ in entries]
    jobs, gains, kp, ki = _jobs(problem, entries)
    if not jobs:
        return weights
    violating = np.nonzero(~_feasible(problem, gains, kp, ki))[0]
    for j, w_found in zip(violating, _scan(problem, gains, kp, ki, violating)):
        e, d = jobs[j]
        weights[e][d] = float(w_found)
    return weights
