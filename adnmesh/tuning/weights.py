"""Find W (docs/method.md#find-w): lower a DER's weight while its single-DER loop violates a
constraint.

With the subset's gains fixed, DER a alone forms the loop ``C(s) e^{-s T_com} w_a P_a G_a(s)
e^{-s T_meas}``. While that loop violates the disk-margin or overshoot constraint, ``w_a`` is
lowered in steps of 0.001 from 1; the result is the first weight of the sequence 1, 0.999, ...
that meets both constraints (0.0 if none does).

How that first weight is found without checking the whole sequence (:func:`find_weights`;
the plain scan, kept as the reference, is ``tests/weights_reference.py``):

1. identical single-DER loops (same group, same loop gains) are checked once, every single-DER
   loop at w = 1 in one batch;
2. for the violating ones, the weights 0.999, 0.998, ... are screened on the sampled frequency
   response (``L_w = w L_1`` on a fixed grid: the balanced disk margin of 64 weights at a
   time, refined 20 x finer around each weight's coarse peak). A sampled peak of
   ``2 |S - 1/2|`` never exceeds the true one, so a weight whose sampled alpha is below the
   limit (less ``SCREEN_SLACK``) violates for certain and is skipped;
3. the weights the screen cannot rule out are checked exactly in sequence order, a few per
   DER and all DERs in one batch: the certified disk margin first, then the step response of
   each DER's first weight that meets it; the first feasible one is the answer.

No weight the scan would accept is ever skipped, so the answer is the sequential scan's
(tests compare both on many loops); a typical Find W is one screen and one or two batches.
"""
from __future__ import annotations

import numpy as np

from adnmesh.loopmodel.frequency_response import loop_response
from adnmesh.tuning.problem import TuningProblem, horizon_s

__all__ = ["find_weights", "W_STEP", "SCREEN_SLACK"]

W_STEP = 0.001
_BLOCK = 64
_N_STEPS = int(round(1 / W_STEP)) - 1                    # k = 1 .. 999, w = 1 - k W_STEP
#: sampled alpha this far below the limit still gets an exact check
SCREEN_SLACK = 0.002
_SCREEN_OMEGA = np.geomspace(1e-5, 1e3, 8 * 40 + 1)       # rad/s
_FINE = 20
_FINE_OMEGA = np.geomspace(1e-5, 1e3, 8 * 40 * _FINE + 1)
_WINDOW = np.arange(2 * _FINE + 1)                        # two coarse intervals, fine grid


def _jobs(problem: TuningProblem, entries):
    jobs = [(e, d) for e, (ders, _, _) in enumerate(entries) for d in ders]
    gains = np.array([problem.group_power([d]) for _, d in jobs]).reshape(len(jobs), -1)
    kp = np.array([entries[e][1] for e, _ in jobs], float)
    ki = np.array([entries[e][2] for e, _ in jobs], float)
    return jobs, gains, kp, ki


def _feasible(problem: TuningProblem, gains, kp, ki) -> np.ndarray:
    """Both constraints of single-DER loops, each simulated on its own :func:`horizon_s`."""
    return problem.check(gains, kp, ki, t_max_s=horizon_s(gains, kp, ki)).feasible


def _weight(k) -> np.ndarray:
    return np.round(1.0 - np.asarray(k) * W_STEP, 3)


def _screen_block(l_c, l_f, k, limit) -> np.ndarray:
    """Steps ``k`` whose sampled disk margin (coarse ``l_c``, fine ``l_f`` response of one
    single-DER loop at w = 1) is not below ``limit``: the others violate for certain."""
    w = _weight(k)[:, None]
    lw = w * l_c[None, :]
    q = np.abs(1.0 - lw) / np.abs(1.0 + lw)
    keep = 2.0 / q.max(axis=1) >= limit
    if keep.any():
        peak = np.argmax(q[keep], axis=1)
        win = (np.clip(peak, 1, _SCREEN_OMEGA.size - 2)[:, None] - 1) * _FINE + _WINDOW
        lf = w[keep] * l_f[win]
        qf = np.abs(1.0 - lf) / np.abs(1.0 + lf)
        keep[np.nonzero(keep)[0]] = 2.0 / np.maximum(qf.max(axis=1), q[keep].max(axis=1)) \
            >= limit
    return k[keep]


class _Candidates:
    """Screened steps of one single-DER loop, generated lazily in blocks of ``_BLOCK``."""

    def __init__(self, l_c, l_f, limit):
        self.l_c, self.l_f, self.limit = l_c, l_f, limit
        self.next_k = 1
        self.buffer = np.zeros(0, int)

    def take(self, n: int) -> np.ndarray:
        """The next ``n`` (or fewer, at the end of the sequence) screened steps, in order."""
        while self.buffer.size < n and self.next_k <= _N_STEPS:
            k = np.arange(self.next_k, min(_N_STEPS, self.next_k + _BLOCK - 1) + 1)
            self.next_k = int(k[-1]) + 1
            self.buffer = np.concatenate([self.buffer,
                                          _screen_block(self.l_c, self.l_f, k, self.limit)])
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def put_back(self, k: np.ndarray) -> None:
        """Return steps taken but not checked to the front of the queue."""
        self.buffer = np.concatenate([k, self.buffer])


#: screened weights whose exact disk margin is checked per DER and batch
_PER_BATCH = 8


def _screened_scan(problem, gains, kp, ki, violating) -> np.ndarray:
    """First feasible weight per job in ``violating`` (0.0 if none): the sequential scan's
    answer, with every weight the sampled disk margin rules out skipped."""
    plant = problem.plant(gains[violating])
    l_c = loop_response(plant, kp[violating], ki[violating], _SCREEN_OMEGA)
    l_f = loop_response(plant, kp[violating], ki[violating], _FINE_OMEGA)
    limit = problem.disk_margin_min - SCREEN_SLACK
    gens = [_Candidates(l_c[j], l_f[j], limit) for j in range(violating.size)]
    found = np.zeros(violating.size)
    pending = list(range(violating.size))
    while pending:
        batch = [(j, gens[j].take(_PER_BATCH)) for j in pending]
        batch = [(j, k) for j, k in batch if k.size]
        if not batch:
            break
        rows = np.concatenate([np.full(k.size, j) for j, k in batch])
        ks = np.concatenate([k for _, k in batch])
        jr = violating[rows]
        # exact disk margin of the batch first; a step response only for each DER's first
        # weight that meets it (the weights after it go back to the DER's queue)
        dm_ok = problem.check(gains[jr] * _weight(ks)[:, None], kp[jr], ki[jr],
                              simulate=np.zeros(ks.size, bool)).reason == ""
        sim_j, sim_k = [], []
        for j, k in batch:
            hit = np.nonzero(dm_ok[rows == j])[0]
            if hit.size:
                sim_j.append(j)
                sim_k.append(k[hit[0]])
                gens[j].put_back(k[hit[0] + 1:])
        done = set()
        if sim_j:
            jr = violating[np.array(sim_j)]
            ks = np.array(sim_k)
            ok = _feasible(problem, gains[jr] * _weight(ks)[:, None], kp[jr], ki[jr])
            for j, k, good in zip(sim_j, sim_k, ok):
                if good:
                    found[j] = _weight(k)
                    done.add(j)
        pending = [j for j, _ in batch if j not in done]
    return found


def find_weights(problem: TuningProblem, entries: list[tuple[tuple[str, ...], float, float]]):
    """Weights for each ``(ders, K_P, K_I)`` (gains in 1/W and 1/(W s)).

    Returns a list of dicts ``{der id: w}``; ``w`` is 0.0 if even ``w = 0.001`` violates (the DER
    is then left out of the loop, which the caller reports).
    """
    weights = [{d: 1.0 for d in ders} for ders, _, _ in entries]
    jobs, gains, kp, ki = _jobs(problem, entries)
    if not jobs:
        return weights
    # identical single-DER loops are one job
    _, first, inverse = np.unique(np.column_stack([gains, kp, ki]), axis=0, return_index=True,
                                  return_inverse=True)
    inverse = inverse.ravel()
    g_u, kp_u, ki_u = gains[first], kp[first], ki[first]
    w_u = np.ones(first.size)
    violating = np.nonzero(~_feasible(problem, g_u, kp_u, ki_u))[0]
    if violating.size:
        w_u[violating] = _screened_scan(problem, g_u, kp_u, ki_u, violating)
    for j, (e, d) in enumerate(jobs):
        weights[e][d] = float(w_u[inverse[j]])
    return weights

