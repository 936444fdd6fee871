"""The constraint check's compiled kernels, made ready in shares that pool workers split.

A fresh checkout has no compiled kernels: the first constraint check in a process compiles
the frequency pass (:mod:`adnmesh.loopmodel.frequency_kernels`) and the settle loop
(:mod:`adnmesh.loopmodel.settle_kernel`, with the step kernels it calls), ~6 s of CPU on the 2-core
machine, and numba writes each to its cache (``__pycache__``) as it finishes. Tuning workers
used to do all of it at once, each the whole of it. :func:`warm_share` makes one tiny check
that needs only one share of the kernels, so that two workers compile one share each, wait
for each other (:func:`adnmesh.tuning.build._start_worker`) and then find the other share in
the cache. With the cache warm a share only loads, as the first check would have.
"""
from __future__ import annotations

import numpy as np

from adnmesh.tuning.problem import TuningProblem

__all__ = ["SHARES", "warm_share"]

#: the shares, in the order the workers take them
SHARES = ("time", "frequency")


def warm_share(problem: TuningProblem, share: str) -> None:
    """Run the kernels of ``share`` ("time": the step responses' settle loop, "frequency":
    the certified frequency pass, the disk-margin refinement and the certificates' limits)
    once on two candidates of ``problem``'s plant, compiling them (or loading them from
    numba's cache) with the argument types a search passes them."""
    g = len(problem.actuators)
    fractions = np.full((2, g), 1.0 / g)
    kp, ki = np.array([0.1, 0.2]), np.array([0.05, 0.1])          # normalised, moderate
    if share == "time":
        problem.first_rise_s(fractions, kp, ki)
    elif share == "frequency":
        problem.may_meet_disk_margin(fractions, kp, ki)
        problem.check(fractions, kp, ki, simulate=np.zeros(2, bool))
    else:
        raise ValueError(f"unknown share {share!r}; expected one of {SHARES}")
