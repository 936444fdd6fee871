"""Tuning of the scheduling table on small configs (2-4 DERs)."""
import json
from pathlib import Path

import numpy as np
import pytest

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.tuning.table import load_table
from adnmesh.tuning import TuningProblem, tune_subset, tune_table
from adnmesh.tuning.paper import initial_values
from adnmesh.tuning.weights import W_STEP

CONFIGS = Path(__file__).resolve().parent.parent / "configs" / "examples"


@pytest.fixture(scope="module")
def wt_chp():
    config = load_config(CONFIGS / "wt-chp.yaml")
    return config, tune_table(config, "paper", chunk_size=1)


@pytest.fixture(scope="module")
def two_wt():
    config = load_config(CONFIGS / "two-wt.yaml")
    return config, tune_table(config, "paper")


def _deployed(config, entry, **kw):
    plant = plant_from_ders(config.ders_by_id(entry.ders), config.design_t_com_s, config.t_meas_s,
                            weights=entry.w)
    return evaluate(plant, entry.kp, entry.ki, **kw).row(0)


@pytest.mark.parametrize("name", ["wt_chp", "two_wt"])
def test_every_entry_meets_both_constraints_when_reevaluated(name, request):
    config, table = request.getfixturevalue(name)
    c = config.constraints
    assert len(table.entries) == 2 ** len(config.ders) - 1 and table.complete
    for entry in table.entries.values():
        assert entry.feasible, entry
        fresh = _deployed(config, entry)
        assert fresh["stable"] and fresh["certified"]
        assert fresh["disk_margin"] >= c.disk_margin_min
        assert fresh["overshoot_pct"] < c.overshoot_max_pct
        # equal up to the simulation error (batches may coarsen the step at other instants)
        assert fresh["rise_time_s"] == pytest.approx(entry.figures["rise_time_s"], rel=1e-4)
        # on the same (unweighted) plant the global optimum is never worse than the paper's
        assert entry.figures["global_rise_time_s"] <= entry.figures["design_rise_time_s"] * 1.001


def test_one_type_subsets_share_normalised_gains(two_wt):
    config, table = two_wt
    norm = []
    for entry in table.entries.values():
        total = sum(d.p_inst_w for d in config.ders_by_id(entry.ders))
        norm.append((entry.kp * total, entry.ki * total))
    np.testing.assert_allclose(norm, [norm[0]] * len(norm), rtol=1e-12)
    problem = TuningProblem(config)
    keys = {problem.key(problem.fractions(e.ders)[0]) for e in table.entries.values()}
    assert len(keys) == 1            # tuned once


def test_find_w_lowers_a_weight_only_when_the_single_loop_violates(wt_chp):
    config, table = wt_chp
    problem = TuningProblem(config)
    lowered = 0
    for entry in table.entries.values():
        back_off = entry.figures["gain_back_off"]
        kp, ki = entry.kp / back_off, entry.ki / back_off          # gains Find W worked with
        for der in entry.ders:
            w = entry.w[der]
            single = problem.group_power([der])
            at = lambda weight: problem.check(single * weight, kp, ki).feasible[0]  # noqa: E731
            if w == 1.0:
                assert at(1.0)
            else:
                lowered += 1
                assert not at(1.0) and at(w) and not at(round(w + W_STEP, 3))
    assert lowered >= 1              # the case exercises the lowering


def test_paper_and_global_agree_on_a_convex_problem(two_wt):
    # a single wind-turbine plant: its feasible set is one wedge, the path reaches its tip
    _, table = two_wt
    for entry in table.entries.values():
        design, best = entry.figures["design_rise_time_s"], entry.figures["global_rise_time_s"]
        assert best <= design * 1.001
        assert design == pytest.approx(best, rel=0.02)


def test_initial_values_are_infeasible_and_have_60_degree_margin():
    config = load_config(CONFIGS / "wt-chp.yaml")
    problem = TuningProblem(config)
    fractions = np.array([problem.fractions(s)[0] for s in (["SGen1"], ["SGen5"])])
    kp, ki = initial_values(problem, fractions)
    assert not problem.check(fractions, kp, ki).feasible.any()
    f = evaluate(problem.plant(fractions), kp, ki, time_domain=False)
    np.testing.assert_allclose(f.phase_margin_deg, 60.0, atol=1e-3)    # the 60 deg design


def test_resume_gives_the_same_table(tmp_path, wt_chp):
    config, full = wt_chp
    out = tmp_path / "t.json"

    def interrupt(done, total):
        if done >= 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tune_table(config, "paper", out=out, chunk_size=1, on_progress=interrupt)
    partial = load_table(out, config)
    assert 0 < len(partial.entries) < 3 and not partial.complete
    resumed = tune_table(config, "paper", out=out, resume=True, chunk_size=1)
    assert resumed.complete and len(resumed.entries) == 3
    for key, e in full.entries.items():
        r = resumed.entries[key]
        assert (r.kp, r.ki, r.w) == (e.kp, e.ki, e.w)


def test_infeasible_subset_is_recorded_with_a_reason():
    config = load_config(CONFIGS / "two-wt.yaml")
    table = tune_table(config, "global", constraints={"disk_margin_min": 1.99})
    for e in table.entries.values():
        assert not e.feasible and "no feasible pair" in e.reason


def test_on_demand_tuning_of_one_subset(wt_chp):
    config, table = wt_chp
    entry = tune_subset(config, ["SGen5", "SGen1"])
    assert entry.feasible and entry.ders == ("SGen1", "SGen5")
    fresh = _deployed(config, entry)
    assert fresh["disk_margin"] >= 1.5 and fresh["overshoot_pct"] < 1.0


def test_cli_writes_json_and_csv(tmp_path, capsys):
    out = tmp_path / "table.json"
    assert main(["tune", str(CONFIGS / "two-wt.yaml"), "--out", str(out), "--method",
                 "global"]) == 0
    obj = json.loads(out.read_text())
    assert {"config_sha256", "constraints", "method", "entries", "static"} <= set(obj)
    row = obj["entries"][0]
    for key in ("ders", "kp", "ki", "w", "feasible", "rise_time_s", "settling_time_s",
                "overshoot_pct", "disk_margin", "gain_margin", "phase_margin_deg",
                "delay_margin_s", "global_rise_time_s"):
        assert key in row, key
    assert obj["static"]["kp"] > 0
    assert out.with_suffix(".csv").read_text().count("\n") == 4


@pytest.mark.parametrize("args, message", [
    (["--workers", "0"], "--workers must be 1 to 1024, got 0"),
    (["--resume", "--out", "/nonexistent/t.json"], "--resume: no partial table"),
    (["--disk-margin-min", "2.5"], "--disk-margin-min must be in (0, 2)"),
])
def test_cli_bad_arguments(args, message, capsys):
    assert main(["tune", str(CONFIGS / "two-wt.yaml"), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def _literal_path(problem, fractions, kp, ki, step):
    """The path search (docs/method.md#path-search) move by move, one evaluation per move (the
    reference for path_search)."""
    from adnmesh.tuning.paper import ES_LIMIT
    best, es, seen, path = None, 0, False, []
    while es < ES_LIMIT and kp >= 1e-9 and len(path) < 5000:
        chk = problem.check(fractions[None], np.array([kp]), np.array([ki]))
        ok = bool(chk.feasible[0])
        path.append((kp, ki, ok))
        if ok and (best is None or chk.rise_time_s[0] < best[2]):
            best, es = (kp, ki, chk.rise_time_s[0]), 0
        elif seen or ok:
            es += 1
        seen |= ok
        kp, ki = (kp, ki * (1 + step)) if ok else (kp * (1 - step), ki)
    return best, path


def test_path_search_makes_exactly_the_moves_of_the_rule():
    from adnmesh.tuning.paper import path_search
    config = load_config(CONFIGS / "wt-chp.yaml")
    problem = TuningProblem(config)
    f = problem.fractions(["SGen1", "SGen5"])[0]
    kp0, ki0 = initial_values(problem, f[None])
    best, path = _literal_path(problem, f, kp0[0], 0.01 * ki0[0], 0.01)
    kp, ki, rise, _, paths = path_search(problem, f[None], kp0, 0.01 * ki0, 0.01, record=True)
    assert len(path) > 40 and not path[0][2]            # it walks into the feasible set first
    assert [p[2] for p in paths[0]] == [p[2] for p in path]
    np.testing.assert_allclose([p[:2] for p in paths[0]], [p[:2] for p in path], rtol=1e-12)
    assert (kp[0], ki[0]) == pytest.approx(best[:2], rel=1e-12)
    assert rise[0] == pytest.approx(best[2], rel=1e-9)


def test_paper_path_starts_again_with_a_lower_ki_when_it_never_meets_the_feasible_set():
    # a slow CHP with a small fast PV share: 1 % of the PI design's K_I is infeasible for any kp
    config = load_config(CONFIGS / "chp-pv.yaml")
    problem = TuningProblem(config)
    f = problem.fractions(["SGen5", "SGen10"])[0]
    kp0, ki0 = initial_values(problem, f[None])
    from adnmesh.tuning.paper import path_search
    *_, rise, _, _ = path_search(problem, f[None], kp0, 0.01 * ki0, 0.01)
    assert np.isnan(rise[0])                             # the literal start never gets there
    table = tune_table(config, "paper")
    for entry in table.entries.values():
        assert entry.feasible and entry.figures["tuned_by"] == "paper", entry
        fresh = _deployed(config, entry)
        assert fresh["disk_margin"] >= 1.5 and fresh["overshoot_pct"] < 1.0
        assert entry.figures["design_rise_time_s"] <= entry.figures["global_rise_time_s"] * 1.02


def test_static_controller_is_feasible_everywhere_and_matches_a_brute_force_search(wt_chp):
    config, table = wt_chp
    static = table.static
    assert static.feasible
    worst = 0.0
    for entry in table.entries.values():
        plant = plant_from_ders(config.ders_by_id(entry.ders), config.design_t_com_s, config.t_meas_s)
        f = evaluate(plant, static.kp, static.ki, classical=False).row(0)
        assert f["stable"] and f["disk_margin"] >= 1.5 and f["overshoot_pct"] < 1.0
        worst = max(worst, f["rise_time_s"])
    assert worst == pytest.approx(static.figures["worst_rise_time_s"], rel=1e-3)
    # brute force over absolute gains: the best worst-case rise time of a 48 x 48 log grid
    problem = TuningProblem(config)
    powers = np.array([problem.group_power(e.ders) for e in table.entries.values()])
    kp, ki = np.meshgrid(np.geomspace(static.kp / 10, static.kp * 3, 48),
                         np.geomspace(static.ki / 30, static.ki * 30, 48))
    kp, ki = kp.ravel(), ki.ravel()
    rows = np.repeat(np.arange(len(powers)), kp.size)
    chk = problem.check(powers[rows], np.tile(kp, len(powers)), np.tile(ki, len(powers)))
    rise = np.where(chk.feasible, chk.rise_time_s, np.inf).reshape(len(powers), -1)
    grid_best = rise.max(axis=0).min()
    assert np.isfinite(grid_best)
    assert static.figures["worst_rise_time_s"] <= grid_best * 1.01


def test_two_workers_give_the_one_process_table_with_its_static_controller(wt_chp):
    # the static controller is designed in a worker beside the chunks; nothing may differ
    config, one = wt_chp
    two = tune_table(config, "paper", workers=2, chunk_size=1)
    assert two.static is not None and two.static.feasible
    assert (two.static.kp, two.static.ki) == (one.static.kp, one.static.ki)
    assert two.static.figures == one.static.figures
    assert set(two.entries) == set(one.entries)
    for key, e in one.entries.items():
        assert (two.entries[key].kp, two.entries[key].ki, two.entries[key].w) == (e.kp, e.ki, e.w)


def test_phase_unwrapped_to_the_crossing_is_numpys():
    """The initial design's -90° crossing from phases unwrapped only where needed is the one
    of the whole numpy unwrap: SimBench's plants (no jump before -90°), PT2 and RHPZ models,
    and rows made to jump before they cross (a phase that rises past +180° first, one that
    starts below -90°)."""
    from adnmesh.tuning.build import group_subsets
    from adnmesh.tuning.paper import _unwrapped_to_crossing
    from adnmesh.tuning.problem import all_subsets
    from loops import CONFIG
    problem = TuningProblem(CONFIG)
    f = np.array([g.fractions for g in group_subsets(problem, all_subsets(list(CONFIG.der_ids())))])
    omega = np.geomspace(1e-4, 1e3, 7001)
    t = np.linspace(0.0, 1.0, 7001)
    synthetic = np.angle(np.exp(1j * np.vstack([3.0 - 10.0 * (t - 0.3) ** 2 * 9.0,
                                                 -2.0 - 8.0 * t, 2.9 + 4.0 * t - 14.0 * t ** 2])))
    rows = [np.angle(f @ problem.plant(f[0]).with_model(m).group_responses(omega))
            for m in ("pt1", "pt2", "rhpz")] + [synthetic]
    for raw in rows:
        want = np.unwrap(raw, axis=1)
        got = _unwrapped_to_crossing(raw)
        k = np.argmax(want <= -np.pi / 2, axis=1)
        r = np.arange(raw.shape[0])
        assert np.array_equal(np.argmax(got <= -np.pi / 2, axis=1), k)
        assert np.array_equal(got[r, k], want[r, k])
        assert np.array_equal(got[r, np.maximum(k - 1, 0)], want[r, np.maximum(k - 1, 0)])
    jumped = _unwrapped_to_crossing(rows[-1])
    assert not np.array_equal(jumped, rows[-1])                 # the jumping rows unwrapped
