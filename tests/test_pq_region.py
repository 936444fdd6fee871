"""The feasible P-Q region at the interconnection point (adnmesh/analysis/pq_region.py) and
``adnmesh analyze CONFIG --pq-region``.

Fast tests use the small hand-made net of tests/test_grid.py (a 4 MW WT and a 1 MW PV as the
DERs); the regions they share are computed once per module. The SimBench reference case is
marked slow.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pandapower as pp
import pandas as pd
import pytest

from adnmesh.analysis.pq_region import (BOUNDARY_TOL_W, DER_CAPABILITY, LOADING_TOL_PCT,
                                        VOLTAGE_TOL_PU, PQRegion, clip_reference, p_range_w,
                                        pq_region, q_range_var)
from adnmesh.cli import main
from adnmesh.config import GridLimits, load_config
from adnmesh.errors import GridError
from adnmesh.grid import GridSolver, available_power_w
from adnmesh.grid.from_net import build_grid_data
from adnmesh.grid.simbench_net import loads_as_impedances
from adnmesh.reactive import capability_of
from test_csv_tidy import numeric
from test_grid import small_net

SGENS = ("WT", "PV")
CONFIG = """\
grid: small
t_com_s: 0.1
t_meas_s: 0.1
ders:
  - {id: WT, type: WT, p_inst_w: 4.0e+6, t_delay_s: 0.01, t_rise_s: 0.5, sgen: WT,
     p_sched_w: 2.0e+6}
  - {id: PV, type: PV, p_inst_w: 1.0e+6, t_delay_s: 0.01, t_rise_s: 0.1, sgen: PV,
     p_sched_w: 0.3e+6}
scenario:
  duration_s: 10
grid_model:
  pandapower_net: small.json
"""
TIGHT = GridLimits(v_max_pu=1.02, loading_max_pct=20.0)
"""Both kinds of limit bind on the small net: bus voltages near the WT, the feeder's lines."""
DIRECTIONS = 12
SLACK_W = 10.0
"""What the optimiser may leave of an optimum on the small net (local optima, stopping), W."""


# ---------------------------------------------------------------------------------------------
# fixtures: the small net, its config and the regions the tests share


@pytest.fixture(scope="module")
def small_files(tmp_path_factory):
    """The small net as a pandapower file beside a config of its two DERs."""
    folder = tmp_path_factory.mktemp("pq")
    pp.to_json(small_net(), str(folder / "small.json"))
    (folder / "small.yaml").write_text(CONFIG)
    return folder


@pytest.fixture(scope="module")
def config(small_files):
    return load_config(small_files / "small.yaml")


@pytest.fixture(scope="module")
def impedance_net():
    """The small net with its loads as constant impedances, as the grid model has them."""
    net = small_net()
    loads_as_impedances(net)
    return net


@pytest.fixture(scope="module")
def data(impedance_net):
    return build_grid_data(copy.deepcopy(impedance_net), "small", "base", "impedance")


@pytest.fixture(scope="module")
def available(data, config):
    return dict(zip(config.der_ids(), available_power_w(data, SGENS).tolist()))


def region_of(data, config, p_avail, limits, **kwargs) -> PQRegion:
    return pq_region(GridSolver(data, SGENS), config.ders, p_avail, limits, config.reactive,
                     directions=DIRECTIONS, **kwargs)


@pytest.fixture(scope="module")
def loose(data, config, available):
    """The region under the config's default limits (0.9-1.1 p.u., 100 %): none binds."""
    return region_of(data, config, available, GridLimits())


@pytest.fixture(scope="module")
def tight(data, config, available):
    return region_of(data, config, available, TIGHT)


# ---------------------------------------------------------------------------------------------
# helpers


def within(sample, limits: GridLimits) -> bool:
    return (limits.v_min_pu <= sample.vm_min_pu and sample.vm_max_pu <= limits.v_max_pu
            and max(sample.line_loading_max_pct, sample.trafo_loading_max_pct)
            <= limits.loading_max_pct)


def random_setpoints(config, available, rng, n: int):
    """``n`` random DER set-points within their capability: uniform in the box (Q cut to the
    circle), every other one at corners of the box or on the circle."""
    caps = [capability_of(d, config.reactive) for d in config.ders]
    p_max = np.array([available[d.id] for d in config.ders])
    s = np.array([c.s_va for c in caps])
    for k in range(n):
        u = rng.uniform(size=(2, len(caps)))
        if k % 2:
            u = np.round(u)
        p = p_max * u[0]
        q = np.array([c.q_min_var + (c.q_max_var - c.q_min_var) * v for c, v in zip(caps, u[1])])
        room = np.sqrt(np.maximum(s ** 2 - p ** 2, 0.0))
        yield p, np.clip(q, -room, room)


def area(vertices: np.ndarray) -> float:
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def square(side: float = 2.0) -> PQRegion:
    """A region by hand: the square [0, side] x [0, side], counter-clockwise."""
    vertices = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    return PQRegion((), (), (), vertices, 0.0, None, None, (), 0)


# ---------------------------------------------------------------------------------------------
# the region


def test_the_region_contains_every_feasible_point_of_a_brute_force_search(tight, data, config,
                                                                          available):
    solver = GridSolver(data, SGENS)              # independent of the one the region used
    rng = np.random.default_rng(7)
    found = 0
    for p, q in random_setpoints(config, available, rng, 3000):
        sample = solver.solve(p, q)
        if not within(sample, TIGHT):
            continue
        found += 1
        z = np.array([sample.p_ip_w, sample.q_ip_var])
        for s in tight.support:                   # no point beyond any support line
            c = np.array([math.cos(s.direction_rad), math.sin(s.direction_rad)])
            assert c @ z <= s.value + SLACK_W, (z, s)
        assert tight.contains(*z, tol_w=tight.boundary_error_w + SLACK_W)
    assert found > 300


def test_every_vertex_is_feasible_by_pandapower_runpp(tight, impedance_net):
    net = copy.deepcopy(impedance_net)
    rows = [net.sgen.index[net.sgen.name == name][0] for name in SGENS]
    adn = ~net.bus.index.isin(net.ext_grid.bus)
    vertices = {(float(p), float(q)) for p, q in tight.vertices}
    checked = 0
    for s in tight.support:
        if (s.p_ip_w, s.q_ip_var) not in vertices:
            continue
        net.sgen.loc[rows, "p_mw"] = s.der_p_w / 1e6
        net.sgen.loc[rows, "q_mvar"] = s.der_q_var / 1e6
        pp.runpp(net)
        vm = net.res_bus.vm_pu[adn]
        assert TIGHT.v_min_pu - VOLTAGE_TOL_PU - 1e-7 <= vm.min()
        assert vm.max() <= TIGHT.v_max_pu + VOLTAGE_TOL_PU + 1e-7
        loading = max(net.res_line.loading_percent.max(), net.res_trafo.loading_percent.max())
        assert loading <= TIGHT.loading_max_pct + LOADING_TOL_PCT + 1e-5
        assert -net.res_ext_grid.p_mw.sum() * 1e6 == pytest.approx(s.p_ip_w, abs=1.0)
        assert -net.res_ext_grid.q_mvar.sum() * 1e6 == pytest.approx(s.q_ip_var, abs=1.0)
        checked += 1
    assert checked == len(tight.vertices) >= 8


def test_each_der_stays_within_its_capability_at_every_support_point(tight, config, available):
    for s in (*tight.support, *tight.without_limits.support):
        for der, p, q in zip(config.ders, s.der_p_w, s.der_q_var):
            cap = capability_of(der, config.reactive)
            assert 0.0 <= p <= available[der.id]
            assert cap.q_min_var <= q <= cap.q_max_var
            assert p * p + q * q <= cap.s_va ** 2 * (1 + 1e-12)


def test_both_kinds_of_limit_bind_and_are_named(tight, data):
    binding = tight.binding_limits()
    assert set(binding) == {"v_max", "loading"}
    solver = GridSolver(data, SGENS)
    assert binding["v_max"] and set(binding["v_max"]) <= set(solver.bus_names)
    assert binding["loading"] and set(binding["loading"]) <= set(solver.line_names)
    assert all(s.binding == (DER_CAPABILITY,) for s in tight.without_limits.support)
    assert tight.boundary_error_w <= BOUNDARY_TOL_W


def test_a_tightened_voltage_limit_shrinks_the_region(loose, data, config, available):
    lower = region_of(data, config, available, GridLimits(v_max_pu=1.02))
    assert all(loose.contains(p, q, tol_w=loose.boundary_error_w + SLACK_W)
               for p, q in lower.vertices)
    assert area(lower.vertices) < 0.8 * area(loose.vertices)
    assert lower.q_span_var()[1] < loose.q_span_var()[1] - 5e5    # less Q injection
    assert set(lower.binding_limits()) == {"v_max"}


def test_limits_that_do_not_bind_leave_the_region_of_der_capability(loose):
    assert loose.binding_limits() == {}
    np.testing.assert_array_equal(loose.vertices, loose.without_limits.vertices)
    assert loose.without_limits.without_limits is None


def test_a_region_lies_inside_its_region_without_grid_limits(tight):
    bare = tight.without_limits
    assert all(bare.contains(p, q, tol_w=bare.boundary_error_w + SLACK_W)
               for p, q in tight.vertices)
    assert set(bare.binding_limits()) == set()


def test_unavailable_ders_stay_at_their_schedules(data, config, available, loose):
    wt_only = region_of(data, config, available, GridLimits(), available=["WT"])
    pv = config.ders[1]
    assert wt_only.moving == ("WT",)
    for s in wt_only.support:
        assert (s.der_p_w[1], s.der_q_var[1]) == (pv.p_sched_w, pv.q_sched_var)
    assert all(loose.contains(p, q, tol_w=loose.boundary_error_w + SLACK_W)
               for p, q in wt_only.vertices)
    assert area(wt_only.vertices) < area(loose.vertices)
    assert any("not available, at their schedules: PV" in n for n in wt_only.notes)


def test_a_config_without_reactive_section_says_the_default_capability(loose):
    assert any("default capability preset cos_phi_0.95" in n for n in loose.notes)


def test_limits_no_set_points_can_keep_are_a_one_line_grid_error(data, config, available):
    with pytest.raises(GridError, match="no DER set-points found that keep the grid") as info:
        region_of(data, config, available, GridLimits(v_max_pu=1.0))   # slack at 1.02 p.u.
    assert "\n" not in str(info.value)


def test_bad_arguments_are_value_errors(data, config, available):
    with pytest.raises(ValueError, match="unknown DER id 'XX'"):
        region_of(data, config, available, GridLimits(), available=["XX"])
    with pytest.raises(ValueError, match="at least 4"):
        pq_region(GridSolver(data, SGENS), config.ders, available, GridLimits(), directions=3)
    with pytest.raises(ValueError, match="actuators"):
        pq_region(GridSolver(data, SGENS[::-1]), config.ders, available, GridLimits())


# ---------------------------------------------------------------------------------------------
# run-time helpers


def test_clipping_leaves_inside_points_and_moves_outside_ones_inside(tight):
    lo, hi = tight.p_span_w()
    qlo, qhi = tight.q_span_var()
    rng = np.random.default_rng(3)
    inside = outside = 0
    for p, q in rng.uniform([lo - 1e6, qlo - 1e6], [hi + 1e6, qhi + 1e6], size=(400, 2)):
        was_inside = tight.contains(p, q)
        for priority in ("p", "q", "nearest"):
            p_out, q_out, clipped = clip_reference(tight, p, q, priority)
            assert clipped is not was_inside
            if was_inside:
                assert (p_out, q_out) == (p, q)
            else:
                assert tight.contains(p_out, q_out)
        inside += was_inside
        outside += not was_inside
        if not was_inside and lo <= p <= hi:          # P kept where the region has it
            assert clip_reference(tight, p, q, "p")[0] == p
        if not was_inside and qlo <= q <= qhi:
            assert clip_reference(tight, p, q, "q")[1] == q
    assert inside > 50 and outside > 50


def test_the_nearest_point_is_nearer_than_every_vertex_and_edge_point(tight):
    z = np.array([tight.p_span_w()[1] + 3e5, tight.q_span_var()[1] + 2e5])
    p, q, clipped = clip_reference(tight, *z, priority="nearest")
    distance = float(np.hypot(p - z[0], q - z[1]))
    assert clipped
    edges = zip(tight.vertices, np.roll(tight.vertices, -1, axis=0))
    for a, b in edges:
        for t in np.linspace(0.0, 1.0, 21):
            assert distance <= float(np.linalg.norm(a + t * (b - a) - z)) + 1e-6


def test_clipping_by_hand_on_a_square():
    region = square()
    assert clip_reference(region, 1.0, 1.0) == (1.0, 1.0, False)
    assert clip_reference(region, 1.0, 3.0, "p") == (1.0, 2.0, True)
    assert clip_reference(region, 3.0, 3.0, "p") == (2.0, 2.0, True)
    assert clip_reference(region, 3.0, 1.0, "q") == (2.0, 1.0, True)
    assert clip_reference(region, 3.0, 1.5, "nearest") == (2.0, 1.5, True)
    with pytest.raises(ValueError, match="priority"):
        clip_reference(region, 3.0, 1.0, "x")


def test_ranges_by_hand():
    region = square()
    assert q_range_var(region, 0.5) == (0.0, 2.0)
    assert p_range_w(region, 2.0) == (0.0, 2.0)
    assert q_range_var(region, 2.5) is None and p_range_w(region, -0.1) is None
    triangle = PQRegion((), (), (), np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 2.0]]), 0.0, None,
                        None, (), 0)
    assert q_range_var(triangle, 2.0) == (0.0, 1.0)
    assert p_range_w(triangle, 1.0) == (0.0, 2.0)


def test_ranges_agree_with_the_polygon(tight):
    lo, hi = tight.p_span_w()
    for p in np.linspace(lo, hi, 9):
        q_lo, q_hi = q_range_var(tight, p)
        assert tight.contains(p, q_lo) and tight.contains(p, q_hi)
        assert not tight.contains(p, q_hi + 10.0) and not tight.contains(p, q_lo - 10.0)
        p_lo, p_hi = p_range_w(tight, (q_lo + q_hi) / 2)
        assert p_lo <= p <= p_hi


# ---------------------------------------------------------------------------------------------
# the command line


def test_analyze_pq_region_writes_the_figure_and_a_tidy_csv(small_files, tmp_path, capsys,
                                                           monkeypatch):
    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["analyze", str(small_files / "small.yaml"), "--pq-region", "--directions",
                 "8", "--available", "WT", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "P_IP" in said and "Q_IP at the operating point" in said
    assert "binding grid limits: none" in said and "power flows in" in said
    assert (out / "pq-region.png").stat().st_size > 10_000
    assert "pq-region.png" in (out / "index.md").read_text()
    frame = pd.read_csv(out / "pq-region.csv")
    numeric(frame, {"region", "binding"})
    assert set(frame.region) == {"grid_limits", "der_capability"}
    assert (frame.p_PV_w == 3e5).all()                 # PV not available: at its schedule
    assert frame.vertex.isin([0, 1]).all() and frame.vertex.sum() >= 6


@pytest.mark.parametrize("argv, words", [
    (["--pq-region", "--directions", "2"], "--directions must be between 4 and 360"),
    (["--pq-region", "--available", "XX"], "--available: unknown DER id 'XX'"),
    (["--pq-region", "--available", ","], "--available: give at least one DER id"),
    (["--available", "WT", "--only", "der-models"], "--available is an option of --pq-region"),
    (["--pq-region", "--quantity", "q"], "leave out --quantity q"),
])
def test_analyze_pq_region_rejects_bad_options_in_one_line(small_files, tmp_path, capsys,
                                                            monkeypatch, argv, words):
    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    argv = ["analyze", str(small_files / "small.yaml"), *argv, "--out", str(tmp_path / "o")]
    assert words in one_line_error(argv, capsys)


def test_analyze_pq_region_says_it_needs_the_grid(configs_dir, tmp_path, capsys):
    error = one_line_error(["analyze", str(configs_dir / "examples" / "two-wt.yaml"),
                            "--pq-region", "--out", str(tmp_path / "o")], capsys)
    assert "has no grid_model: the P-Q region needs the grid" in error


def one_line_error(argv, capsys) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("adnmesh: error: "), err
    return err[0]


# ---------------------------------------------------------------------------------------------
# slow: the reference case


@pytest.mark.slow
def test_the_reference_case_region(simbench_config):
    from adnmesh.control.operating_point import (available_power_w as study_case_power,
                                                 grid_solver, initial_p_ip_w)

    config = simbench_config
    region = pq_region(grid_solver(config), config.ders, study_case_power(config),
                       config.grid_model.limits, config.reactive, directions=12)
    lo, hi = region.p_span_w()
    assert lo == pytest.approx(10.879e6, abs=5e3) and hi == pytest.approx(23.191e6, abs=5e3)
    assert region.binding_limits() == {}          # 0.9-1.1 p.u. and 100 % hold everywhere
    q_lo, q_hi = q_range_var(region, initial_p_ip_w(config))
    assert q_lo < -3.5e6 and q_hi > 4e6
    assert region.boundary_error_w <= BOUNDARY_TOL_W
