"""Find W (SPEC §3.4): lower a DER's weight while its single-DER loop violates a constraint.

With the subset's gains fixed, DER a alone forms the loop ``C(s) e^{-s T_com} w_a P_a G_a(s)
e^{-s T_meas}``. While that loop violates the disk-margin or overshoot constraint, ``w_a`` is
lowered in steps of 0.001 from 1; the result is the first weight of the sequence 1, 0.999, ...
that meets both constraints (0.0 if none does).

How that first weight is found without checking the whole sequence
(:func:`find_weights`; :func:`find_weights_sequential` is the plain scan, kept as reference):

1. every single-DER loop is checked at w = 1 in one batch;
2. for the violating ones, the step ``k`` (w = 1 - 0.001 k) where the loop meets the disk
   margin is bisected on the exact (certified) frequency-domain check, ten rounds for 999
   steps, every pending DER in one batch; the weight found is then checked fully (step
   response too);
3. the sequence above the bisected step is screened on the sampled frequency response
   (``L_w = w L_1`` on a fine grid: the balanced disk margin of every weight at once); each
   weight the screen cannot rule out (sampled alpha within ``SCREEN_SLACK`` of the limit) is
   checked exactly, and the first feasible one wins. A bisection that ends on a weight the
   exact check rejects falls back to the sequential scan for that DER.

So the answer is the sequential scan's whenever the sampled disk margin is within
``SCREEN_SLACK`` of the exact one (tests compare both on many loops).
"""
from __future__ import annotations

import numpy as np

from ..freqresp import loop_response
from .problem import TuningProblem

__all__ = ["find_weights", "find_weights_sequential", "W_STEP", "SCREEN_SLACK"]

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


def _weight(k) -> np.ndarray:
    return np.round(1.0 - np.asarray(k) * W_STEP, 3)


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
        ok = problem.check(gains[rows] * ww[:, None], kp[rows], ki[rows]).feasible
        ok = ok.reshape(jobs_v.size, w.size)
        hit = ok.any(axis=1)
        found[pending[hit]] = w[np.argmax(ok[hit], axis=1)]
        pending = pending[~hit]
    return found


def _bisect(problem, gains, kp, ki, jobs_v) -> np.ndarray:
    """Smallest step k (1..999) whose weight meets the disk margin, assuming the violation
    ends once: ``hi`` passes, ``lo`` fails (k = 0 is the violating w = 1). Frequency domain
    only; the caller checks the result fully."""
    lo = np.zeros(jobs_v.size, int)
    hi = np.full(jobs_v.size, _N_STEPS + 1)                  # virtual passing end (w = 0)
    while np.any(hi - lo > 1):
        act = np.nonzero(hi - lo > 1)[0]
        mid = (lo[act] + hi[act]) // 2
        w = _weight(mid)
        rows = jobs_v[act]
        chk = problem.check(gains[rows] * w[:, None], kp[rows], ki[rows],
                            simulate=np.zeros(rows.size, bool))
        ok = chk.reason == ""                    # meets the disk margin (not simulated)
        hi[act] = np.where(ok, mid, hi[act])
        lo[act] = np.where(ok, lo[act], mid)
    return hi


def _screen(problem, gains, kp, ki, jobs_v, k_hit) -> list[np.ndarray]:
    """Steps k < k_hit per job whose sampled disk margin does not rule them out.

    A sampled peak of ``2 |S - 1/2|`` is at most the true one, so a sampled alpha below the
    limit rules a weight out for certain (stable or not: alpha is 0 if unstable). The coarse
    grid rules out most weights; the rest are sampled again 20 x finer around their coarse
    peak, and what still reaches ``limit - SCREEN_SLACK`` is returned for an exact check.
    """
    plant = problem.plant(gains[jobs_v])
    l_c = loop_response(plant, kp[jobs_v], ki[jobs_v], _SCREEN_OMEGA)             # (J, N)
    l_f = loop_response(plant, kp[jobs_v], ki[jobs_v], _FINE_OMEGA)               # (J, 20N)
    limit = problem.disk_margin_min - SCREEN_SLACK
    out = []
    for j in range(jobs_v.size):
        k = np.arange(1, k_hit[j])
        if k.size == 0:
            out.append(k)
            continue
        w = _weight(k)[:, None]
        lw = w * l_c[j][None, :]
        q = np.abs(1.0 - lw) / np.abs(1.0 + lw)
        keep = 2.0 / q.max(axis=1) >= limit
        if keep.any():
            peak = np.argmax(q[keep], axis=1)
            win = (np.clip(peak, 1, _SCREEN_OMEGA.size - 2)[:, None] - 1) * _FINE + _WINDOW
            lf = w[keep] * l_f[j][win]
            qf = np.abs(1.0 - lf) / np.abs(1.0 + lf)
            keep[np.nonzero(keep)[0]] = 2.0 / np.maximum(qf.max(axis=1), q[keep].max(axis=1)) \
                >= limit
        out.append(k[keep])
    return out


def find_weights(problem: TuningProblem, entries: list[tuple[tuple[str, ...], float, float]]):
    """Weights for each ``(ders, K_P, K_I)`` (gains in 1/W and 1/(W s)).

    Returns a list of dicts ``{der id: w}``; ``w`` is 0.0 if even ``w = 0.001`` violates (the DER
    is then left out of the loop, which the caller reports).
    """
    weights = [{d: 1.0 for d in ders} for ders, _, _ in entries]
    jobs, gains, kp, ki = _jobs(problem, entries)
    if not jobs:
        return weights
    violating = np.nonzero(~problem.check(gains, kp, ki).feasible)[0]
    found = np.zeros(violating.size)
    if violating.size:
        k_hit = _bisect(problem, gains, kp, ki, violating)
        in_range = k_hit <= _N_STEPS
        chk = problem.check(gains[violating[in_range]] * _weight(k_hit[in_range])[:, None],
                            kp[violating[in_range]], ki[violating[in_range]])
        good = np.zeros(violating.size, bool)
        good[np.nonzero(in_range)[0][chk.feasible]] = True
        found[good] = _weight(k_hit[good])
        # weights above the bisected one that the sampled disk margin cannot rule out
        idx = np.nonzero(good)[0]
        cand = _screen(problem, gains, kp, ki, violating[idx], k_hit[idx])
        rows = np.concatenate([np.full(c.size, i) for i, c in zip(idx, cand)] + [[]]).astype(int)
        ks = np.concatenate(cand + [[]]).astype(int)
        if rows.size:
            jr = violating[rows]
            ok = problem.check(gains[jr] * _weight(ks)[:, None], kp[jr], ki[jr]).feasible
            for i in np.unique(rows[ok]):
                found[i] = _weight(ks[ok & (rows == i)].min())
        # a bisection that ended on a rejected weight: the sequential scan decides
        rest = np.nonzero(~good)[0]
        if rest.size:
            found[rest] = _scan(problem, gains, kp, ki, violating[rest])
    for j, w_found in zip(violating, found):
        e, d = jobs[j]
        weights[e][d] = float(w_found)
    return weights


def find_weights_sequential(problem: TuningProblem, entries):
    """:func:`find_weights` by the plain scan of 1, 0.999, ... (reference, slow)."""
    weights = [{d: 1.0 for d in ders} for ders, _, _ in entries]
    jobs, gains, kp, ki = _jobs(problem, entries)
    if not jobs:
        return weights
    violating = np.nonzero(~problem.check(gains, kp, ki).feasible)[0]
    for j, w_found in zip(violating, _scan(problem, gains, kp, ki, violating)):
        e, d = jobs[j]
        weights[e][d] = float(w_found)
    return weights
