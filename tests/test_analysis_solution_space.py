"""Solution space of one subset: classes, rise times, extent, search path, figure."""
import numpy as np
import pytest

from adnmesh.analysis import plots
from adnmesh.analysis import solution_space as solution_space_module
from adnmesh.analysis.solution_space import REASONS, paper_path, solution_space
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.plant import plant_from_ders

from coarse_table import example


@pytest.fixture(scope="module")
def space():
    return solution_space(example("wt-chp"), ["SGen5", "SGen1"], n=14)


def test_grid_covers_the_normalised_ranges_and_classifies_every_point(space):
    assert space.ders == ("SGen1", "SGen5") and space.p_inst_w == pytest.approx(2.31e6)
    assert space.kp[0] * space.p_inst_w == pytest.approx(0.01)
    assert space.ki[-1] * space.p_inst_w == pytest.approx(5.0)
    assert set(np.unique(space.reason)) <= set(REASONS)
    assert sum(space.counts().values()) == 14 * 14
    assert space.counts()["feasible"] > 0 and space.counts()["disk margin"] > 0


def test_classes_agree_with_the_loop_figures(space):
    config = example("wt-chp")
    c = config.constraints
    plant = plant_from_ders(config.ders_by_id(space.ders), config.design_t_com_s, config.t_meas_s)
    rng = np.random.default_rng(7)
    for i, j in rng.integers(0, 14, size=(6, 2)):
        f = evaluate(plant, space.kp[j], space.ki[i], classical=False).row(0)
        if not f["stable"]:
            expected = "unstable"
        elif f["disk_margin"] < c.disk_margin_min:
            expected = "disk margin"
        elif f["overshoot_pct"] >= c.overshoot_max_pct:
            expected = "overshoot"
        else:
            expected = ""
            assert space.rise_time_s[i, j] == pytest.approx(f["rise_time_s"], rel=1e-6)
        assert space.reason[i, j] == expected, (i, j)


def test_best_is_the_fastest_feasible_point(space):
    kp, ki, rise = space.best()
    feasible_rise = space.rise_time_s[space.feasible]
    assert rise == feasible_rise.min()
    i, j = list(space.ki).index(ki), list(space.kp).index(kp)
    assert space.reason[i, j] == ""


def test_plane_widens_to_hold_the_path_and_the_figure_is_written(tmp_path):
    config = example("wt-chp")
    p = 2.31e6
    path = [(8.0 / p, 1e-4 / p, False), (6.0 / p, 2e-4 / p, True), (5.0 / p, 3e-4 / p, True)]
    space = solution_space(config, ["SGen1", "SGen5"], n=8, path=path,
                           table_point=(0.5 / p, 0.3 / p))
    assert space.kp[-1] >= 8.0 / p and space.ki[0] <= 1e-4 / p
    assert space.path == tuple(path) and space.table_point == (0.5 / p, 0.3 / p)
    out = plots.plot_solution_space(space, tmp_path / "ss.png")
    assert out.read_bytes().startswith(b"\x89PNG") and out.stat().st_size > 20_000


def test_paper_path_is_the_tuners_as_plain_numbers(monkeypatch):
    monkeypatch.setattr(solution_space_module, "tuner_path",
                        lambda config, ids: [(np.float64(1e-7), 1e-8, 0), (0.9e-7, 1e-8, 1)])
    path = paper_path(example("wt-chp"), ["SGen1"])
    assert path == [(1e-7, 1e-8, False), (0.9e-7, 1e-8, True)]
    assert all(type(kp) is float and type(ok) is bool for kp, _, ok in path)
