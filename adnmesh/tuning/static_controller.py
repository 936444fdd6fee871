"""The static controller: one (K_P, K_I) feasible for every subset (w = 1), best worst case.

Absolute gains meet subset A as normalised gains ``K * P_A`` (``P_A = sum_A P_inst``), so a pair
that suits the largest subsets is slow on the smallest. The search runs along rays
``K_I = rho K_P``: a ray in absolute gains is the same ray in every subset's normalised plane,
so on ray ``rho`` subset A is feasible up to ``K_P <= s_A(rho) / P_A``, where ``s_A(rho)`` is
the largest feasible normalised ``kp_n`` of A's plant on that ray (feasibility is taken to be
monotone along a ray: lower gains, more margin). The static pair of a ray is the largest
``K_P`` below every subset's limit:

1. the limits ``s_A`` of the largest subsets (which bind first) are found by bisection in
   ``log kp_n`` and their minimum gives a candidate ``K_P``;
2. every subset is checked at that ``K_P`` in one batch; the limits of those that fail are
   bisected too and ``K_P`` lowered to their minimum, until every subset passes;
3. the passing batch gives the ray's worst-case rise time (the smallest subsets are the
   slowest). The middle ray is done first; the others are simulated for at most 10 x its
   worst case, and a ray with a subset slower than that is out. They are taken outward from
   the middle, and a ray whose first pair (step 1) already has one of the slowest subsets
   rising slower than the best ray so far is out without steps 2 and 3 (lowering its gains
   can only make it slower).

The bisections of steps 1 and 2 want only the least limit of a ray, so a subset is bisected no
further once its limit is certainly above another's (:func:`_least_limits`). Both shortcuts
give the pair of the full search (tested); on SimBench they cut the design from 18 s to 10 s.

Absolute gains that suit the largest subsets are tiny for the smallest: a 6.5 kW DER alone
at ``K_I`` ~ 6.5e-9 1/(W s) rises in ~14 h. Such a loop is simulated for as long as it needs
(:func:`~.problem.horizon_s`, beyond :data:`~.problem.T_MAX_S`), so its overshoot is known
and its rise time counts in the worst case like any other's.

Rays are first spread log-evenly over ``rho`` in 0.01 ... 10 1/s, then the best one is refined
by golden-section search in ``log rho``. The result is verified on every subset (step 2), so a
wrong monotonicity assumption can only cost optimality, never feasibility.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.step_response import integral_rate
from adnmesh.tuning.paper import initial_values
from adnmesh.tuning.problem import T_MAX_S, TuningProblem, horizon_s
from adnmesh.tuning.subset_selection import spread_random_subsets

__all__ = ["StaticResult", "static_controller", "design_over", "RATIOS", "AnySizeStatic",
           "extreme_subsets", "check_pair", "static_any_size"]

#: initial rays K_I / K_P, 1/s
RATIOS = np.geomspace(0.01, 10.0, 13)
#: subsets (largest installed power first) whose limits seed every ray
SEED_SUBSETS = 24
BISECTIONS = 14
GOLDEN_STEPS = 8
_VERIFY_ROUNDS = 6
#: a ray's responses are simulated for at most this many times the best worst case so far
CAP_FACTOR = 10.0
#: plants (the slowest) whose rise times decide whether a ray can beat the best one
SCREEN_PLANTS = 24


@dataclass
class StaticResult:
    """The static pair (1/W, 1/(W s)) and its worst case over the plants."""

    kp: float
    ki: float
    worst_rise_time_s: float
    worst_plant: int
    feasible: bool


@dataclass
class _Ray:
    """Outcome of one ray: absolute K_P (1/W), worst rise time (s) and its plant."""

    kp: float
    worst_rise_time_s: float
    worst_plant: int


def _least_limits(problem: TuningProblem, fractions, totals, rho, lo, hi, plants, ray,
                  n_rays: int, t_max_s) -> np.ndarray:
    """Per ray, the least absolute limit ``min exp(lo_A) / P_A`` (1/W) over its rows, where
    ``lo_A`` is the largest feasible normalised ``log kp_n`` of plant A on the ray found by
    bisection in log; shape (n_rays,), inf for a ray without rows.

    ``plants``, ``ray`` (K,) index ``fractions`` / ``totals`` and the rays; ``rho``, ``lo``,
    ``hi`` (K,) are each row's ray and log-``kp_n`` bracket (``lo`` assumed feasible). A
    response too slow to settle within ``t_max_s`` counts as below the limit: the limit is
    where the margin or overshoot constraint breaks.

    Only the least limit is wanted, so a row is bisected no further once its feasible end
    (absolute) is above another row's infeasible end on the same ray: its limit cannot be
    the least. Every row's bisection is its own, so the least one is found exactly as if
    every row were bisected to the end, at a fraction of the checks (the largest subsets'
    limits differ by up to 10x across SimBench's plants).
    """
    lo, hi = lo.copy(), hi.copy()
    tot = totals[plants]
    live = np.arange(plants.size)
    for _ in range(BISECTIONS):
        # the least infeasible end per ray bounds every row's limit on that ray from above
        upper = np.full(n_rays, np.inf)
        np.minimum.at(upper, ray[live], np.exp(hi[live]) / tot[live])
        live = live[~(np.exp(lo[live]) / tot[live] > upper[ray[live]])]
        mid = 0.5 * (lo[live] + hi[live])
        chk = problem.check(fractions[plants[live]], np.exp(mid), rho[live] * np.exp(mid),
                            t_max_s=t_max_s)
        ok = chk.feasible | (chk.reason == "slow")
        lo[live] = np.where(ok, mid, lo[live])
        hi[live] = np.where(ok, hi[live], mid)
    least = np.full(n_rays, np.inf)
    np.minimum.at(least, ray[live], np.exp(lo[live]) / tot[live])
    return least


def _slower_than(problem: TuningProblem, fractions, totals, kp, rho, bound_s, t_max_s) -> bool:
    """Whether the ray ``rho`` at absolute ``kp`` has a plant rising slower than ``bound_s``
    (s) or not at all by ``t_max_s``: simulated until 90 % only (a fifth of a check), for the
    :data:`SCREEN_PLANTS` plants with the slowest integral mode there
    (:func:`~adnmesh.loopmodel.step_response.integral_rate`: the small subsets)."""
    kpn, kin = kp * totals, rho * kp * totals
    slow = np.argsort(integral_rate(fractions, kpn, kin), kind="stable")[:SCREEN_PLANTS]
    rise = problem.first_rise_s(fractions[slow], kpn[slow], kin[slow], t_max_s=t_max_s)
    return bool(np.any(~(rise <= bound_s)))


def _rays(problem: TuningProblem, fractions, totals, kp_init, rhos, t_max_s,
          out_above: float = np.inf) -> list[_Ray]:
    """The static pair of every ray in ``rhos`` (1/s), lock-step over rays.

    Step responses are simulated for their :func:`~.problem.horizon_s`, at most ``t_max_s``
    (s): a ray with a subset too slow to settle by then gets an infinite worst-case rise
    time. So does a ray whose first pair (from the largest subsets' limits) already has a
    plant rising slower than ``out_above`` (s; :func:`_slower_than`): lowering its gains to
    pass every check makes it slower still, so its worst case cannot be below ``out_above``
    and it is not verified (a ray far from the best one costs up to 20 times a check of the
    best, its small subsets simulated for hours until they settle).
    """
    n_rays, n_plants = rhos.size, fractions.shape[0]
    seeds = np.argsort(-totals)[:SEED_SUBSETS]
    lo0 = np.log(kp_init * 1e-4)
    hi0 = np.log(kp_init * 4.0)
    r_idx = np.repeat(np.arange(n_rays), seeds.size)
    p_idx = np.tile(seeds, n_rays)
    kp = _least_limits(problem, fractions, totals, rhos[r_idx], lo0[p_idx], hi0[p_idx], p_idx,
                       r_idx, n_rays, min(t_max_s, T_MAX_S))
    worst = np.full(n_rays, np.inf)
    worst_plant = np.zeros(n_rays, int)
    pending = np.arange(n_rays)
    if np.isfinite(out_above):
        pending = np.array([r for r in pending if np.isfinite(kp[r]) and not _slower_than(
            problem, fractions, totals, kp[r], rhos[r], out_above, t_max_s)], int)
    for _ in range(_VERIFY_ROUNDS):
        if pending.size == 0:
            break
        r_idx = np.repeat(pending, n_plants)
        p_idx = np.tile(np.arange(n_plants), pending.size)
        kpn = kp[r_idx] * totals[p_idx]
        kin = rhos[r_idx] * kpn
        chk = problem.check(fractions[p_idx], kpn, kin,
                            t_max_s=np.minimum(horizon_s(fractions[p_idx], kpn, kin),
                                               t_max_s))
        slow = chk.reason == "slow"
        fail = ~chk.feasible & ~slow
        if fail.any():
            # lower the failing rays to the least limit of their failing subsets
            fr, fp = r_idx[fail], p_idx[fail]
            least = _least_limits(problem, fractions, totals, rhos[fr], lo0[fp],
                                  np.log(kpn[fail]), fp, fr, n_rays, min(t_max_s, T_MAX_S))
            kp = np.minimum(kp, least * (1.0 - 1e-9))
        # a lowered ray is checked again; a ray with a subset too slow to settle is out (its
        # worst case stays inf); every other ray is done
        failed = np.unique(r_idx[fail])
        slowed = np.unique(r_idx[slow])
        for r in np.setdiff1d(pending, np.union1d(failed, slowed)):
            rise = chk.rise_time_s[r_idx == r]
            worst[r] = float(np.max(rise))
            worst_plant[r] = int(np.argmax(rise))
        pending = failed
    return [_Ray(float(kp[r]), float(worst[r]), int(worst_plant[r])) for r in range(n_rays)]


def static_controller(problem: TuningProblem, fractions, totals, kp_init) -> StaticResult:
    """Search the static pair for plants ``fractions`` (P, G) with powers ``totals`` (P,) in W.

    ``kp_init`` (P,) are the plants' initial (too aggressive) normalised ``kp_n``; they set
    the bisection brackets ``[1e-4, 4] x kp_init``.
    """
    fractions = np.atleast_2d(fractions)
    totals = np.asarray(totals, float)
    kp_init = np.asarray(kp_init, float)
    log_rho = np.log(RATIOS)
    # the middle ray first: its worst case bounds how long the others need simulating
    mid = RATIOS.size // 2
    seen = {float(log_rho[mid]): _rays(problem, fractions, totals, kp_init, RATIOS[[mid]],
                                       np.inf)[0]}

    def cap() -> float:
        best = min(r.worst_rise_time_s for r in seen.values())
        return CAP_FACTOR * best if np.isfinite(best) else np.inf

    # the other rays outward from the middle, each verified only if it can beat the best so
    # far (they are all simulated for the cap the middle ray sets)
    scan_cap = cap()
    for j in sorted(set(range(RATIOS.size)) - {mid}, key=lambda j: (abs(j - mid), j)):
        best = min(r.worst_rise_time_s for r in seen.values())
        seen[float(log_rho[j])] = _rays(problem, fractions, totals, kp_init, RATIOS[[j]],
                                        scan_cap, best)[0]
    cost = np.array([seen[float(lr)].worst_rise_time_s for lr in log_rho])
    if not np.isfinite(cost).any():
        return StaticResult(float("nan"), float("nan"), float("inf"), -1, False)
    i = int(np.argmin(cost))

    def worst_at(x: float) -> float:
        if x not in seen:
            seen[x] = _rays(problem, fractions, totals, kp_init, np.exp(np.array([x])), cap())[0]
        return seen[x].worst_rise_time_s

    # golden-section search in log rho between the best ray's neighbours (one ray per step)
    a = float(log_rho[max(i - 1, 0)])
    b = float(log_rho[min(i + 1, log_rho.size - 1)])
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = worst_at(c), worst_at(d)
    for _ in range(GOLDEN_STEPS):
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = worst_at(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = worst_at(d)
    best_lr = min(seen, key=lambda x: seen[x].worst_rise_time_s)
    best = seen[best_lr]
    return StaticResult(best.kp, best.kp * float(np.exp(best_lr)), best.worst_rise_time_s,
                        best.worst_plant, True)


@dataclass
class AnySizeStatic:
    """The static pair designed on the extreme plants, verified on them and a random sample.

    ``designed_on`` counts the distinct plants (group-power vectors) of the final design;
    ``verified`` the sampled subsets checked, ``added`` those that failed a design and joined
    the next one; ``lowered`` how often the pair of a reduced design plant was lowered along
    its ray to pass every check on the exact plant.
    """

    result: StaticResult
    designed_on: int
    verified: int
    added: int
    cases: list[tuple[str, ...]]
    """One subset per row of ``powers``: the design's and the sample's (the pair's checks)."""
    powers: np.ndarray
    """Their distinct group-power vectors on the exact plant, W (``result.worst_plant``
    indexes them)."""
    lowered: int = 0


def extreme_subsets(problem: TuningProblem, ids) -> list[tuple[str, ...]]:
    """Subsets whose plants bound a config's family: every single DER, the set of all, and
    for each dynamics class and each DER type the class (type) alone and the set of all less
    it (by class: the largest and the smallest installed power of each mix; by type as well,
    since a config whose DERs' dynamics all differ has classes of one or two DERs)."""
    ids = list(ids)
    ders = problem.config.ders_by_id(ids)
    out = [(d,) for d in ids] + [tuple(ids)]
    for key in (lambda d: problem.group_of[d.id], lambda d: d.type):
        for value in dict.fromkeys(key(d) for d in ders):
            alone = tuple(d.id for d in ders if key(d) == value)
            rest = tuple(d.id for d in ders if key(d) != value)
            out += [s for s in (alone, rest) if s]
    return list(dict.fromkeys(out))


def design_over(problem: TuningProblem, cases) -> tuple[np.ndarray, np.ndarray, StaticResult]:
    """The static pair over the subsets ``cases``: absolute gains meet each subset through its
    group powers, so one case per distinct power vector. Returns (powers W, totals W, pair)."""
    powers = np.unique(np.array([problem.group_power(s) for s in cases]), axis=0)
    tot = powers.sum(axis=1)
    f = powers / tot[:, None]
    kp0, _ = initial_values(problem, f)
    return powers, tot, static_controller(problem, f, tot, kp0)


def _distinct(problem: TuningProblem, subsets) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """One subset per distinct group-power vector (W) of ``subsets``, and those vectors."""
    powers = np.array([problem.group_power(s) for s in subsets])
    _, first = np.unique(powers, axis=0, return_index=True)
    first = np.sort(first)
    return [subsets[i] for i in first], powers[first]


def check_pair(problem: TuningProblem, powers: np.ndarray, kp: float, ki: float):
    """The exact check of the pair (1/W, 1/(W s)) on plants ``powers`` (W), each simulated
    for its own :func:`~.problem.horizon_s`."""
    tot = powers.sum(axis=1)
    f = powers / tot[:, None]
    return problem.check(f, kp * tot, ki * tot, t_max_s=horizon_s(f, kp * tot, ki * tot))


def _lowered_on_ray(problem: TuningProblem, powers: np.ndarray, kp: float, rho: float):
    """The largest ``K_P <= kp`` on the ray ``K_I = rho K_P`` that passes the exact check on
    every plant ``powers`` (W), its check and how often it was lowered; ``None`` if the
    check still fails after :data:`_VERIFY_ROUNDS` lowerings (or a plant is too slow to
    settle). Lowering a ray's gains is taken to restore its margins (the same monotonicity
    as the design); each result is checked, never assumed."""
    tot = powers.sum(axis=1)
    f = powers / tot[:, None]
    for lowered in range(_VERIFY_ROUNDS + 1):
        chk = check_pair(problem, powers, kp, rho * kp)
        if chk.feasible.all():
            return kp, chk, lowered
        fail = np.nonzero(~chk.feasible & (chk.reason != "slow"))[0]
        if lowered == _VERIFY_ROUNDS or fail.size == 0:
            return None
        hi = np.log(kp * tot[fail])
        least = _least_limits(problem, f, tot, np.full(fail.size, rho), hi + np.log(1e-4), hi,
                              fail, np.zeros(fail.size, int), 1, T_MAX_S)
        kp = float(least[0]) * (1.0 - 1e-9)
    return None                                         # not reached: the loop returns


def static_any_size(problem: TuningProblem, ids, sample: int = 1000, seed: int = 7,
                    rounds: int = 3, extra=()) -> AnySizeStatic:
    """The static pair of a config whose subsets cannot be enumerated.

    Designed (:func:`static_controller`) on :func:`extreme_subsets` and the subsets ``extra``
    (e.g. those a table holds), then checked on them and on every subset of a random sample
    of ``sample`` (:func:`~.subset_selection.spread_random_subsets`: sizes from 1 to all) at
    the pair (w = 1, absolute gains), each loop on the exact plant for as long as it takes to
    settle. With more than :data:`~.problem.MAX_EXACT_CLASSES` dynamics classes the design runs on
    the per-type plant (``by_type``, ~10x faster for 100 DERs of 70 classes) and the pair is
    lowered along its ray until every check on the exact plant passes; otherwise the failing
    subsets join the design, at most ``rounds`` times. Not feasible if a check still fails.
    """
    design = problem.design()
    reduced = design is not problem
    cases = list(dict.fromkeys(extreme_subsets(problem, ids) + [tuple(s) for s in extra]))
    drawn = spread_random_subsets(ids, sample, seed)
    added = lowered = 0
    res = StaticResult(float("nan"), float("nan"), float("inf"), -1, False)
    designed_cases = set(cases)
    subsets, powers = _distinct(problem, cases + [s for s in drawn if s not in designed_cases])
    for _ in range(rounds + 1):
        designed, _, res = design_over(design, cases)
        if not res.feasible:
            break
        chk = check_pair(problem, powers, res.kp, res.ki)
        if reduced and not chk.feasible.all():
            got = _lowered_on_ray(problem, powers, res.kp, res.ki / res.kp)
            if got is not None:
                kp, chk, lowered = got
                res = StaticResult(kp, kp * res.ki / res.kp, res.worst_rise_time_s, -1, True)
        if chk.feasible.all():
            worst = int(np.argmax(chk.rise_time_s))
            res = StaticResult(res.kp, res.ki, float(chk.rise_time_s[worst]), worst, True)
            return AnySizeStatic(res, len(designed), len(drawn), added, subsets, powers, lowered)
        if reduced:
            break
        bad = [subsets[i] for i in np.nonzero(~chk.feasible)[0] if subsets[i] not in cases]
        if not bad:
            break
        added += len(bad)
        cases += bad
    res = StaticResult(res.kp, res.ki, res.worst_rise_time_s, -1, False)
    return AnySizeStatic(res, len(cases), len(drawn), added, subsets, powers, lowered)
