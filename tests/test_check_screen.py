"""The constraint check's disk-margin screen and the staged back-off give the unscreened
answers exactly: they only skip work whose result is already decided."""
import numpy as np
import pytest

from adnmesh.loopmodel.evaluation import disk_margin_bound, evaluate
from adnmesh.loopmodel.stability import nyquist_stability
from adnmesh.tuning import TuningProblem
from adnmesh.tuning import certify

from loops import CONFIG, LOOPS, gains


def _candidates(name, n=120, seed=3):
    plant, kp0, ki0 = gains(name)
    rng = np.random.default_rng(seed)
    scale = np.exp(rng.uniform(-2.0, 2.5, size=(n, 2)))      # stable, marginal and unstable
    return plant, kp0 * scale[:, 0], ki0 * scale[:, 1]


@pytest.mark.parametrize("name", list(LOOPS))
def test_partial_certification_equals_the_full_one_on_its_rows(name):
    plant, kp, ki = _candidates(name)
    full = nyquist_stability(plant, kp, ki)
    only = np.arange(kp.size) % 3 == 0
    part = nyquist_stability(plant, kp, ki, only=only)
    assert np.array_equal(part.stable[only], full.stable[only])
    assert np.array_equal(part.unstable_poles[only], full.unstable_poles[only])
    assert not part.certified[~only].any() and (part.unstable_poles[~only] == -1).all()


@pytest.mark.parametrize("name", list(LOOPS))
def test_screened_check_has_the_unscreened_verdicts(name):
    plant, kp, ki = _candidates(name)
    limit = CONFIG.constraints.disk_margin_min
    kw = dict(classical=False, disk_margin_min=limit, overshoot_stop_pct=1.0)
    plain = evaluate(plant, kp, ki, **kw)
    screened = evaluate(plant, kp, ki, screen=True, **kw)
    met = plain.stable & (plain.disk_margin >= limit)
    assert 0 < met.sum() < kp.size                       # both kinds among the candidates
    kept = screened.certified
    # every candidate meeting the disk margin is kept and gets identical figures
    assert kept[met].all()
    for f in ("stable", "disk_margin", "overshoot_pct", "rise_time_s", "settling_time_s"):
        a, b = getattr(plain, f)[kept], getattr(screened, f)[kept]
        assert np.array_equal(a, b, equal_nan=True), f
    # a screened-out one violates for certain: its reported value bounds the exact one
    out = ~kept
    assert out.any()
    assert (screened.disk_margin[out] < limit).all()
    exact = np.where(plain.stable[out], plain.disk_margin[out], 0.0)
    assert (screened.disk_margin[out] >= exact).all()
    assert np.isnan(screened.rise_time_s[out]).all()


def test_check_reports_screened_candidates_as_disk_margin_violations():
    problem = TuningProblem(CONFIG)
    ids, kpn, kin = LOOPS["all"]
    f, _ = problem.fractions(ids)
    scale = np.geomspace(0.5, 40.0, 16)
    g = np.tile(f, (scale.size, 1))
    chk = problem.check(g, kpn * scale, kin * scale)
    plain = evaluate(problem.plant(g), kpn * scale, kin * scale, classical=False)
    below = plain.stable & (plain.disk_margin < problem.disk_margin_min)
    assert below.any() and (~plain.stable).any()
    assert (chk.reason[below] == "disk margin").all()
    # an unstable loop is either certified unstable or screened out by its disk margin
    assert set(chk.reason[~plain.stable]) <= {"unstable", "disk margin"}
    assert not chk.feasible[below | ~plain.stable].any()


def test_staged_back_off_finds_each_entrys_first_feasible_step():
    problem = TuningProblem(CONFIG)
    ids, kpn, kin = LOOPS["wt_chp"]
    f, total = problem.fractions(ids)
    # an edge pair (the last feasible of a ray), then raised by 1 to 7 back-off steps
    ray = np.geomspace(0.5, 3.0, 200)
    ok = problem.check(np.tile(f, (ray.size, 1)), kpn * ray, kin * ray).feasible
    edge = ray[np.nonzero(ok)[0].max()]
    raise_by = 0.99 ** -np.arange(1, 8)
    kp, ki = kpn * edge * raise_by, kin * edge * raise_by
    gains_ = np.tile(f, (kp.size, 1))
    scale = certify.back_off(problem, gains_, kp, ki)
    # brute force: every step of every entry, the first feasible one
    factors = 0.99 ** np.arange(1, certify.BACK_OFF_STEPS + 1)
    for i in range(kp.size):
        chk = problem.check(np.tile(f, (factors.size, 1)), kp[i] * factors, ki[i] * factors)
        assert chk.feasible.any()
        assert scale[i] == factors[np.argmax(chk.feasible)]
    assert (scale < 0.99 ** 2).any()                     # the second stage was needed


@pytest.mark.parametrize("name", list(LOOPS))
def test_disk_margin_bound_is_never_below_the_exact_disk_margin(name):
    plant, kp, ki = _candidates(name)
    limit = CONFIG.constraints.disk_margin_min
    bound = disk_margin_bound(plant, kp, ki)
    plain = evaluate(plant, kp, ki, classical=False, time_domain=False)
    exact = np.where(plain.stable, plain.disk_margin, 0.0)
    assert (bound >= exact).all()
    # it is the screen's value: the check reports it for the candidates it screened out
    screened = evaluate(plant, kp, ki, classical=False, time_domain=False,
                        disk_margin_min=limit, screen=True)
    out = ~screened.certified & (screened.disk_margin > 0)
    assert out.any()
    assert np.array_equal(screened.disk_margin[out], bound[out])
    # and it rules candidates out: some meet the limit, some (stable ones too) do not
    problem = TuningProblem(CONFIG)
    may = bound >= problem.disk_margin_min
    assert may[plain.stable & (plain.disk_margin >= limit)].all()
    assert (~may & plain.stable).any() and may.any()


def test_column_tops_on_the_bound_are_those_on_the_full_check(monkeypatch):
    """The global grid screened on the cheap bound has the tops (and best points) of the
    grid screened by full checks, which certify every point."""
    from adnmesh.tuning import global_search as gs
    from adnmesh.tuning.paper import initial_values

    problem = TuningProblem(CONFIG)
    fractions = np.array([problem.fractions(LOOPS[n][0])[0] for n in LOOPS])
    kp0, ki0 = initial_values(problem, fractions)
    ukp = np.linspace(np.log(gs.KP_RANGE[0]), np.log(gs.KP_RANGE[1]), 8)
    uki = np.linspace(np.log(gs.KI_RANGE[0]), np.log(gs.KI_RANGE[1]), 12)
    lkp, lki = np.broadcast_arrays(np.log(kp0)[:, None, None] + ukp[None, None, :],
                                   np.log(ki0)[:, None, None] + uki[None, :, None])
    plants = np.arange(len(fractions))

    def tops():
        best = gs._Best(len(fractions))
        top, bound, _ = gs._column_tops(problem, fractions, plants, lkp, lki, best)
        return top, bound, best

    new_top, new_bound, new_best = tops()

    def full_check_screen(gains, kp, ki):
        return problem.check(gains, kp, ki, simulate=np.zeros(np.size(kp), bool)).reason == ""

    monkeypatch.setattr(problem, "may_meet_disk_margin", full_check_screen)
    old_top, old_bound, old_best = tops()
    assert np.array_equal(new_top, old_top)
    assert np.array_equal(new_bound, old_bound)
    assert (new_top >= 0).any()
    for f in ("lkp", "lki", "rise"):
        assert np.array_equal(getattr(new_best, f), getattr(old_best, f), equal_nan=True)


def test_first_rise_is_the_full_simulations_rise_time():
    problem = TuningProblem(CONFIG)
    ids, kpn, kin = LOOPS["wt_chp"]
    f, _ = problem.fractions(ids)
    # one column (K_P fixed, K_I rising): feasible, then overshoot, then the disk margin
    kp, ki = np.full(12, 0.3 * kpn), kin * np.geomspace(0.5, 4.0, 12)
    g = np.tile(f, (kp.size, 1))
    chk = problem.check(g, kp, ki)
    first = problem.first_rise_s(g, kp, ki)
    seen = np.isfinite(chk.simulated_rise_s)
    assert set(chk.reason[seen]) == {"", "overshoot"}     # infeasible ones simulated too
    # alone, a candidate is simulated on the same steps as in a full simulation
    for i in np.nonzero(seen)[0][::3]:
        alone = problem.first_rise_s(f[None], kp[i:i + 1], ki[i:i + 1])
        full = problem.check(f[None], kp[i:i + 1], ki[i:i + 1])
        assert alone[0] == full.simulated_rise_s[0]
    # in a batch the others may stop earlier and the step coarsen sooner: within the slack
    from adnmesh.tuning.global_search import RISE_SLACK
    assert np.allclose(first[seen], chk.simulated_rise_s[seen], rtol=RISE_SLACK, atol=0)
    # the rise time falls as K_I grows with K_P fixed (what the bound relies on), also where
    # the disk margin is violated and the check simulates nothing
    assert np.isfinite(first).all() and (~seen).sum() >= 3
    assert (np.diff(first) < 0).all()


def test_dropping_columns_by_their_rise_bound_changes_no_result(monkeypatch):
    """The global search drops columns whose rise-time bound is not below the plant's best;
    without any bound (nothing dropped) it finds the same pairs."""
    from adnmesh.tuning import global_search as gs
    from adnmesh.tuning.paper import initial_values

    problem = TuningProblem(CONFIG)
    fractions = np.array([problem.fractions(LOOPS[n][0])[0] for n in LOOPS])
    kp0, ki0 = initial_values(problem, fractions)
    pruned = gs.tune_global(problem, fractions, kp0, ki0)
    monkeypatch.setattr(gs, "_raise_bound", lambda bound, c, ok: bound)
    monkeypatch.setattr(problem, "first_rise_s", lambda g, kp, ki: np.full(np.size(kp), np.nan))
    plain = gs.tune_global(problem, fractions, kp0, ki0)
    assert pruned.feasible.all()
    assert pruned.evaluations < 0.9 * plain.evaluations
    for f in ("kp", "ki", "rise_time_s"):
        assert np.array_equal(getattr(pruned, f), getattr(plain, f)), f
