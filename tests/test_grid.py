"""The grid model: study case, fast solver against pandapower's runpp, disk cache.

Fast tests use a small hand-made net (HV slack, transformer, MV feeders, an open loop-line
switch, loads, shunt, generators); the slow ones the SimBench grid of docs/method.md#reference-case.
"""

from __future__ import annotations

import copy
import json
import math
import warnings

import numpy as np
import pandapower as pp
import pytest

from adnmesh.grid import GridError, GridSolver, available_power_w, load_grid
from adnmesh.grid.from_net import build_grid_data
from adnmesh.grid.cache import cache_key, cache_path, cached, default_cache_dir, model_path
from adnmesh.grid.data import from_arrays, to_arrays
from adnmesh.grid.simbench_net import apply_study_case, grid_net, loads_as_impedances

CODE = "1-MV-rural--0-no_sw"
ACTUATORS = ("MV1.101 SGen 1", "MV1.101 MV SGen 2", "MV1.101 MV SGen 3", "MV1.101 MV SGen 4",
             "MV1.101 MV SGen 5", "MV1.101 MV SGen 6", "MV1.101 MV SGen 7",
             "MV1.101 MV SGen 8", "MV1.101 MV SGen 9", "MV1.101 MV SGen 10",
             "MV1.101 MV SGen 12")
SMALL_ACTUATORS = ("WT", "PV")


# ---------------------------------------------------------------------------------------------
# helpers


def small_net():
    """110 kV slack, 110/20 kV transformer, two MV feeders joined by an open loop line."""
    net = pp.create_empty_network()
    hv = pp.create_bus(net, 110.0, name="HV")
    mv = [pp.create_bus(net, 20.0, name=f"MV{i}") for i in range(6)]
    pp.create_ext_grid(net, hv, vm_pu=1.02)
    pp.create_transformer(net, hv, mv[0], std_type="25 MVA 110/20 kV", name="T1")
    cable = "NA2XS2Y 1x185 RM/25 12/20 kV"
    for a, b, km in [(0, 1, 2.0), (1, 2, 3.0), (2, 3, 1.5), (0, 4, 4.0), (4, 5, 2.5)]:
        pp.create_line(net, mv[a], mv[b], km, cable)
    loop = pp.create_line(net, mv[3], mv[5], 1.2, cable, name="loop")
    pp.create_switch(net, mv[5], loop, et="l", closed=False)
    for bus, p, q in [(1, 1.2, 0.4), (3, 0.8, 0.3), (5, 1.5, 0.5)]:
        pp.create_load(net, mv[bus], p_mw=p, q_mvar=q)
    pp.create_shunt(net, mv[3], q_mvar=-0.2)
    pp.create_sgen(net, mv[2], p_mw=4.0, name="WT")
    pp.create_sgen(net, mv[4], p_mw=1.0, name="PV")
    pp.create_sgen(net, mv[0], p_mw=0.5, q_mvar=0.1, name="fixed")
    return net


def small_data(load_model: str = "impedance"):
    net = small_net()
    if load_model == "impedance":
        loads_as_impedances(net)
    return build_grid_data(net, "small", "base", load_model)


def runpp_sample(net, names, p_w):
    """pandapower's own result with the named sgens at ``p_w``: (P_IP, Q_IP, vm min, vm max
    over the buses but the slack's, line loading max, trafo loading max), MV -> HV positive."""
    index = net.sgen.index[net.sgen.name.isin(names)]
    order = {n: i for i, n in enumerate(names)}
    for i in index:
        net.sgen.at[i, "p_mw"] = p_w[order[net.sgen.at[i, "name"]]] / 1e6
    pp.runpp(net)
    ext = net.res_ext_grid.iloc[0]
    adn = net.res_bus.vm_pu[~net.bus.index.isin(net.ext_grid.bus)]   # not the slack's
    return (-ext.p_mw * 1e6, -ext.q_mvar * 1e6, adn.min(), adn.max(),
            net.res_line.loading_percent.max(),
            net.res_trafo.loading_percent.max())


def as_tuple(sample):
    return (sample.p_ip_w, sample.q_ip_var, sample.vm_min_pu, sample.vm_max_pu,
            sample.line_loading_max_pct, sample.trafo_loading_max_pct)


def assert_agrees(sample, reference, p_tol_w=1.0):
    assert sample.converged
    got = as_tuple(sample)
    assert abs(got[0] - reference[0]) <= p_tol_w
    assert abs(got[1] - reference[1]) <= p_tol_w
    assert got[2:4] == pytest.approx(reference[2:4], abs=1e-7)
    assert got[4:] == pytest.approx(reference[4:], abs=1e-5)


# ---------------------------------------------------------------------------------------------
# fast: the small net


@pytest.mark.parametrize("load_model", ["power", "impedance"])
def test_small_net_solver_equals_runpp_over_random_points(load_model):
    reference_net = small_net()
    if load_model == "impedance":      # pandapower's own ZIP model: no sgen shares a load's bus
        reference_net.load["const_z_p_percent"] = 100.0
        reference_net.load["const_z_q_percent"] = 100.0
    data = small_data(load_model)
    solver = GridSolver(data, SMALL_ACTUATORS)
    available = available_power_w(data, SMALL_ACTUATORS)
    rng = np.random.default_rng(7)
    for _ in range(15):
        p = rng.uniform(0.0, 1.0, 2) * available
        assert_agrees(solver.solve(p), runpp_sample(reference_net, SMALL_ACTUATORS, p))


def test_small_net_actuators_reactive_power_equals_runpp():
    """The actuators' Q set-points enter the power flow (var, sign as pandapower's sgen:
    positive is injected); P and Q together against runpp at random points; without Q the
    last one given stays."""
    net = small_net()
    loads_as_impedances(net)
    solver = GridSolver(build_grid_data(copy.deepcopy(net), "small", "base", "impedance"),
                        SMALL_ACTUATORS)
    rng = np.random.default_rng(11)
    rows = [net.sgen.index[net.sgen.name == n][0] for n in SMALL_ACTUATORS]
    for _ in range(8):
        p = rng.uniform(0.0, 1.0, 2) * np.array([4e6, 1e6])
        q = rng.uniform(-1.0, 1.0, 2) * np.array([1.5e6, 0.4e6])
        net.sgen.loc[rows, "q_mvar"] = q / 1e6
        sample = solver.solve(p, q)
        assert_agrees(sample, runpp_sample(net, SMALL_ACTUATORS, p))
        again = solver.solve(p)                                  # Q as last given
        assert again.q_ip_var == pytest.approx(sample.q_ip_var, abs=1e-3)
    with pytest.raises(GridError, match="expected 2 finite actuator reactive powers"):
        solver.solve([1e6, 1e5], [0.0, math.inf])


def test_small_net_sign_convention_export_positive_import_negative():
    data = small_data()
    solver = GridSolver(data, SMALL_ACTUATORS)
    export = solver.solve([4.0e6, 1.0e6])         # 5.5 MW of generation, 3.5 MW of load
    importing = solver.solve([0.0, 0.0])
    assert export.p_ip_w > 1.0e6
    assert importing.p_ip_w < -2.0e6


def test_small_net_keeps_the_loop_switch_open():
    """The open switch leaves the loop line hanging at one end: closing it changes the flow."""
    data = small_data()
    closed = small_net()
    closed.switch["closed"] = True
    loads_as_impedances(closed)
    closed_data = build_grid_data(closed, "small", "base", "impedance")
    p = [2.0e6, 0.5e6]
    assert data.lsgrid.total_bus() == closed_data.lsgrid.total_bus() + 1   # the open end's bus
    open_, closed_ = (GridSolver(d, SMALL_ACTUATORS).solve(p) for d in (data, closed_data))
    assert closed_.vm_min_pu - open_.vm_min_pu > 1e-3          # the loop supports the far end
    assert abs(closed_.line_loading_max_pct - open_.line_loading_max_pct) > 0.3


def test_voltage_extremes_leave_out_the_slack():
    """The slack's voltage is the upper grid's, a constant: the extremes are the ADN's buses'
    (with little load and generation at the far end, the slack would be the lowest)."""
    data = small_data()
    solver = GridSolver(data, SMALL_ACTUATORS)
    sample = solver.solve([4.0e6, 1.0e6])
    vm = np.abs(solver.voltages_pu[data.report_bus])       # bus 0 of the net: the HV slack
    assert vm[0] == pytest.approx(1.02)
    assert (sample.vm_min_pu, sample.vm_max_pu) == (vm[1:].min(), vm[1:].max())
    assert sample.vm_max_pu > 1.02


def test_small_net_loads_are_constant_impedances():
    net = small_net()
    data = small_data("impedance")
    solver = GridSolver(data, SMALL_ACTUATORS)
    p = np.array([3.0e6, 0.2e6])
    sample = solver.solve(p)
    v = np.abs(solver.voltages_pu)
    lookup = {name: i for i, name in enumerate(net.bus.name)}
    bus_of = data.report_bus
    s_load = sum((row.p_mw + 1j * row.q_mvar) * v[bus_of[lookup[net.bus.name[row.bus]]]] ** 2
                 for row in net.load.itertuples())
    # the same operating point in pandapower with its ZIP loads at 100 % impedance
    net.load["const_z_p_percent"] = 100.0
    net.load["const_z_q_percent"] = 100.0
    runpp_sample(net, SMALL_ACTUATORS, p)
    assert net.res_load.p_mw.sum() + 1j * net.res_load.q_mvar.sum() == pytest.approx(
        s_load, abs=1e-9)
    assert sample.p_ip_w == pytest.approx(-net.res_ext_grid.p_mw.iloc[0] * 1e6, abs=1.0)


def test_solver_rejects_bad_input():
    data = small_data()
    with pytest.raises(GridError, match="no static generator named 'nope'"):
        GridSolver(data, ["WT", "nope"])
    with pytest.raises(GridError, match="named twice"):
        GridSolver(data, ["WT", "WT"])
    solver = GridSolver(data, SMALL_ACTUATORS)
    with pytest.raises(GridError, match="expected 2 finite actuator active powers"):
        solver.solve([1.0])
    with pytest.raises(GridError, match="expected 2 finite actuator active powers"):
        solver.solve([1.0, math.nan])


def test_build_rejects_unsupported_elements():
    net = small_net()
    pp.create_gen(net, 3, p_mw=1.0)
    with pytest.raises(GridError, match="'gen' is not supported"):
        build_grid_data(net, "small", "base", "power")


def _topology_components(net, ext_bus: int) -> set:
    """Buses joined to ``ext_bus`` by closed bus-bus switches, by pandapower's topology."""
    import networkx as nx
    from pandapower.topology import create_nxgraph

    graph = create_nxgraph(net, include_lines=False, include_trafos=False,
                           include_impedances=False, include_trafo3ws=False)
    return set(nx.node_connected_component(graph, ext_bus))


def test_bus_couplers_are_fused_as_runpp_fuses_them():
    """Closed bus-bus switches join their buses into one node, open ones keep them apart, a
    line between two coupled buses keeps its charging; the solver equals runpp all along."""
    net = small_net()
    cable = "NA2XS2Y 1x185 RM/25 12/20 kV"
    hv2 = pp.create_bus(net, 110.0, name="HV coupled")           # a second busbar at 110 kV
    pp.create_switch(net, 0, hv2, et="b", closed=True)
    net.trafo.at[0, "hv_bus"] = hv2                              # the transformer on it
    mv_b = pp.create_bus(net, 20.0, name="MV busbar 2")
    pp.create_switch(net, 1, mv_b, et="b", closed=True)
    pp.create_line(net, 1, mv_b, 0.3, cable, name="between coupled buses")
    spare = pp.create_bus(net, 20.0, name="spare busbar")       # joined by an open coupler
    pp.create_switch(net, 2, spare, et="b", closed=False)
    pp.create_line(net, spare, 5, 0.8, cable, name="from the spare busbar")
    pp.create_sgen(net, mv_b, p_mw=0.7, name="on busbar 2")
    loads_as_impedances(net)
    data = build_grid_data(net, "small-sw", "base", "impedance")
    assert data.lsgrid.total_bus() == len(net.bus) - 2 + 1      # two fused, one open line end
    names = SMALL_ACTUATORS + ("on busbar 2",)
    solver = GridSolver(data, names)
    rng = np.random.default_rng(3)
    for _ in range(5):
        p = rng.uniform(0.0, 1.0, 3) * np.array([4e6, 1e6, 1e6])
        want = runpp_sample(net, names, p)
        upper = _topology_components(net, int(net.ext_grid.bus.iloc[0]))
        adn = net.res_bus.vm_pu[~net.bus.index.isin(upper)]
        assert_agrees(solver.solve(p), want[:2] + (adn.min(), adn.max()) + want[4:])


@pytest.mark.parametrize("kind, applied", [("Ratio", True), (None, False)])
def test_a_transformer_tap_counts_as_runpp_counts_it(kind, applied):
    """An off-neutral tap with a tap-changer type moves the ratio; without one (SimBench's
    1-MV-urban) pandapower 3 ignores it, and so does the model."""
    net = small_net()
    net.trafo["tap_pos"] = 3.0
    net.trafo["tap_neutral"] = 1.0                              # the ratio: tap_pos - neutral
    net.trafo["tap_changer_type"] = kind
    neutral = small_net()
    for n in (net, neutral):
        loads_as_impedances(n)
    p = np.array([2.5e6, 0.6e6])
    solver = GridSolver(build_grid_data(net, "small-tap", "base", "impedance"), SMALL_ACTUATORS)
    sample = solver.solve(p)
    assert_agrees(sample, runpp_sample(net, SMALL_ACTUATORS, p))
    at_neutral = GridSolver(small_data(), SMALL_ACTUATORS).solve(p)
    moved = abs(sample.vm_max_pu - at_neutral.vm_max_pu) > 1e-3
    assert moved == applied


def _two_feeds(vm_second: float = 1.02, va_second: float = 0.0):
    """The small net fed from two external grids: its own at 110 kV and one at 220 kV through
    a 220/20 kV transformer into the far end of the second feeder."""
    net = small_net()
    ehv = pp.create_bus(net, 220.0, name="EHV")
    pp.create_ext_grid(net, ehv, vm_pu=vm_second, va_degree=va_second)
    pp.create_transformer_from_parameters(
        net, ehv, 5, sn_mva=20.0, vn_hv_kv=220.0, vn_lv_kv=20.0, vkr_percent=0.4,
        vk_percent=12.0, pfe_kw=15.0, i0_percent=0.05, shift_degree=150.0, name="T2")
    return net


def test_several_external_grids_at_one_voltage_are_one_interconnection_point():
    """P_IP and Q_IP are the external grids' injections summed (sign turned); the voltage
    extremes leave out both of their buses."""
    net = _two_feeds()
    loads_as_impedances(net)
    data = build_grid_data(net, "two-feeds", "base", "impedance")
    solver = GridSolver(data, SMALL_ACTUATORS)
    for p in ([4.0e6, 1.0e6], [0.5e6, 0.0], [2.0e6, 0.8e6]):
        sample = solver.solve(p)
        runpp_sample(net, SMALL_ACTUATORS, p)
        ext = net.res_ext_grid
        assert sample.p_ip_w == pytest.approx(-ext.p_mw.sum() * 1e6, abs=1.0)
        assert sample.q_ip_var == pytest.approx(-ext.q_mvar.sum() * 1e6, abs=1.0)
        assert abs(ext.p_mw.iloc[1]) > 0.1                  # the second feed carries power
        adn = net.res_bus.vm_pu[~net.bus.index.isin(net.ext_grid.bus)]
        assert (sample.vm_min_pu, sample.vm_max_pu) == pytest.approx(
            (adn.min(), adn.max()), abs=1e-7)
        assert sample.trafo_loading_max_pct == pytest.approx(
            net.res_trafo.loading_percent.max(), abs=1e-5)


@pytest.mark.parametrize("vm, va", [(1.03, 0.0), (1.02, 2.0)])
def test_external_grids_at_different_voltages_are_a_one_line_error(vm, va):
    net = _two_feeds(vm, va)
    with pytest.raises(GridError, match="2 external grids at different voltages"):
        build_grid_data(net, "two-feeds", "base", "power")


def test_an_island_is_left_out_as_runpp_leaves_it_out():
    """Buses no external grid supplies (here two, with a load, a generator and the line between
    them) have no power flow in runpp; the model leaves them out, the rest equals runpp, and the
    island's generator has no power to give."""
    net = small_net()
    island = [pp.create_bus(net, 20.0, name=f"island {i}") for i in range(2)]
    pp.create_line(net, *island, 1.0, "NA2XS2Y 1x185 RM/25 12/20 kV")
    pp.create_load(net, island[1], p_mw=0.1)
    pp.create_sgen(net, island[0], p_mw=0.2, name="island PV")
    loads_as_impedances(net)
    data = build_grid_data(net, "island", "base", "impedance")
    assert available_power_w(data, ["island PV"]).tolist() == [0.0]
    solver = GridSolver(data, SMALL_ACTUATORS)
    p = np.array([2.0e6, 0.3e6])
    want = runpp_sample(net, SMALL_ACTUATORS, p)
    assert np.isnan(net.res_bus.vm_pu.loc[island]).all()
    adn = net.res_bus.vm_pu[~net.bus.index.isin(net.ext_grid.bus)].dropna()
    assert_agrees(solver.solve(p), want[:2] + (adn.min(), adn.max())
                  + (net.res_line.loading_percent.max(), want[5]))


def test_storage_is_a_constant_power_injection():
    net = small_net()
    pp.create_storage(net, 4, p_mw=-0.8, max_e_mwh=2.0, q_mvar=0.1, scaling=0.5)
    loads_as_impedances(net)
    solver = GridSolver(build_grid_data(net, "small-storage", "base", "impedance"),
                        SMALL_ACTUATORS)
    p = np.array([1.5e6, 0.4e6])
    assert_agrees(solver.solve(p), runpp_sample(net, SMALL_ACTUATORS, p))


def test_not_converged_gives_nan_and_keeps_the_last_solution():
    data = small_data()
    solver = GridSolver(data, SMALL_ACTUATORS)
    good = solver.solve([1.0e6, 0.5e6])
    v = solver.voltages_pu
    bad = solver.solve([5.0e9, 0.0])             # 5 GW into a 20 kV cable: no solution
    assert not bad.converged and math.isnan(bad.p_ip_w) and math.isnan(bad.vm_max_pu)
    assert np.array_equal(solver.voltages_pu, v)
    again = solver.solve([1.0e6, 0.5e6])
    assert again.converged and again.p_ip_w == pytest.approx(good.p_ip_w, abs=1e-3)


def test_warm_start_needs_fewer_iterations_for_a_small_step():
    data = small_data()
    solver = GridSolver(data, SMALL_ACTUATORS)
    solver.solve([0.0, 0.0])
    far = GridSolver(data, SMALL_ACTUATORS).solve([0.0, 0.0])    # from the case: 4 MW, 1 MW
    near = solver.solve([1.0e3, 0.0])
    assert near.iterations < far.iterations


# ---------------------------------------------------------------------------------------------
# fast: the cache


def test_arrays_round_trip_is_exact():
    data = small_data()
    back = from_arrays(to_arrays(data), data.lsgrid.copy())
    p = [2.5e6, 0.7e6]
    assert GridSolver(back, SMALL_ACTUATORS).solve(p) == GridSolver(data, SMALL_ACTUATORS).solve(p)
    assert back.sgen_names == data.sgen_names and back.converter == data.converter


def _counting_builder():
    calls = []

    def build():
        calls.append(1)
        return small_data()
    return build, calls


def test_cache_builds_once_then_reads_identical_data(tmp_path):
    key = cache_key("small", "base", "impedance")
    build, calls = _counting_builder()
    first = cached(key, build, tmp_path)
    second = cached(key, build, tmp_path)
    assert len(calls) == 1
    p = [3.0e6, 0.1e6]
    assert GridSolver(second, SMALL_ACTUATORS).solve(p) == \
        GridSolver(first, SMALL_ACTUATORS).solve(p)
    path = cache_path(key, tmp_path)
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted(
        [path.name, model_path(path).name])                    # and no temporary file left


@pytest.mark.parametrize("damage", ["garbage", "truncated", "other key", "model truncated",
                                    "model missing", "other model"])
def test_damaged_cache_file_is_rebuilt_with_a_warning(tmp_path, damage):
    key = cache_key("small", "base", "impedance")
    build, calls = _counting_builder()
    cached(key, build, tmp_path)
    path = cache_path(key, tmp_path)
    model = model_path(path)
    other = dict(key, code="other")
    if damage == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:300])
    elif damage == "other key":
        cached(other, build, tmp_path)
        cache_path(other, tmp_path).replace(path)
    elif damage == "model truncated":
        model.write_bytes(model.read_bytes()[:500])
    elif damage == "model missing":
        model.unlink()
    else:                                      # a valid model, but not the one of the arrays
        closed = small_net()
        closed.switch["closed"] = True
        build_grid_data(closed, "small", "base", "power").lsgrid.save_binary(str(model), True)
    with pytest.warns(RuntimeWarning, match="rebuilding it"):
        data = cached(key, build, tmp_path)
    assert len(calls) == (3 if damage == "other key" else 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = cached(key, build, tmp_path)       # the rebuilt file is good again
    p = [1.0e6, 1.0e6]
    assert GridSolver(again, SMALL_ACTUATORS).solve(p) == \
        GridSolver(data, SMALL_ACTUATORS).solve(p)


def _rewrite_npz(path, change):
    """The cache's ``.npz`` rewritten with ``change(arrays)`` applied, nothing else touched (the
    key, the model's hash and, if present, the digest stay as they were)."""
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    change(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


@pytest.mark.parametrize("edit", ["line ratings / 10", "v_init", "trafo rating", "sgen power",
                                  "meta", "extra entry", "no digest", "digest of other arrays"])
def test_every_file_of_the_cache_is_covered_by_its_hash(tmp_path, edit):
    """Issue 39: a cached ``.npz`` with line ratings divided by 10 was accepted (446 % loading
    instead of 44.6 %): the hash covered the model file, not the arrays beside it."""
    key = cache_key("small", "base", "impedance")
    build, calls = _counting_builder()
    good = cached(key, build, tmp_path)
    path = cache_path(key, tmp_path)

    def change(arrays):
        if edit == "line ratings / 10":
            arrays["line_i_max_ka"] = arrays["line_i_max_ka"] / 10
        elif edit == "v_init":
            arrays["v_init"] = arrays["v_init"] * 1.01
        elif edit == "trafo rating":
            arrays["trafo_rating_mva"] = arrays["trafo_rating_mva"] * 2
        elif edit == "sgen power":
            arrays["sgen_p_mw"] = arrays["sgen_p_mw"] + 0.5
        elif edit == "meta":
            meta = json.loads(str(arrays["meta"]))
            meta["converter"] = "edited"
            arrays["meta"] = np.array(json.dumps(meta, sort_keys=True))
        elif edit == "extra entry":
            arrays["extra"] = np.zeros(3)
        elif edit == "no digest":
            arrays.pop("digest", None)
            arrays["line_i_max_ka"] = arrays["line_i_max_ka"] / 10
        else:                                  # a digest, but of arrays other than these
            from adnmesh.grid.cache import arrays_digest
            arrays["line_i_max_ka"] = arrays["line_i_max_ka"] / 10
            arrays["digest"] = np.array(arrays_digest({"line_i_max_ka": arrays["line_i_max_ka"]}))
    _rewrite_npz(path, change)
    with pytest.warns(RuntimeWarning, match="rebuilding it"):
        data = cached(key, build, tmp_path)
    assert len(calls) == 2
    np.testing.assert_array_equal(data.line_i_max_ka, good.line_i_max_ka)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = cached(key, build, tmp_path)       # the rebuilt file is good again
    assert len(calls) == 2
    np.testing.assert_array_equal(again.line_i_max_ka, good.line_i_max_ka)
    np.testing.assert_array_equal(again.v_init, good.v_init)


def test_unwritable_cache_is_a_warning_not_an_error(tmp_path):
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("x")
    build, calls = _counting_builder()
    with pytest.warns(RuntimeWarning, match="could not be written"):
        data = cached(cache_key("small", "base", "impedance"), build, not_a_dir)
    assert data.code == "small" and len(calls) == 1


def test_cache_dir_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "explicit"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "explicit"
    monkeypatch.delenv("ADNMESH_CACHE_DIR")
    assert default_cache_dir() == tmp_path / "xdg" / "adnmesh"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "adnmesh"


def test_cache_key_holds_the_versions_and_the_format():
    key = cache_key(CODE, "lW", "impedance")
    assert set(key) == {"format", "code", "case", "load_model", "simbench", "pandapower",
                        "lightsim2grid"}
    assert cache_path(key, default_cache_dir()) != cache_path(dict(key, pandapower="0"),
                                                             default_cache_dir())


def test_load_grid_rejects_an_unknown_load_model(tmp_path):
    with pytest.raises(GridError, match="load model must be one of impedance, power"):
        load_grid(CODE, "lW", "zip", cache_dir=tmp_path)


# ---------------------------------------------------------------------------------------------
# slow: the SimBench grid


@pytest.fixture(scope="module")
def simbench_case_net():
    """1-MV-rural at lW with constant-power loads (copy it before changing it)."""
    return grid_net(CODE, "lW", "power")


@pytest.fixture(scope="module")
def simbench_nets(simbench_case_net):
    """{load model: (net for runpp, solver data)}."""
    nets = {}
    for model in ("impedance", "power"):
        net = copy.deepcopy(simbench_case_net)
        if model == "impedance":
            loads_as_impedances(net)
        nets[model] = (net, build_grid_data(copy.deepcopy(net), CODE, "lW", model))
    return nets


@pytest.mark.slow
@pytest.mark.parametrize("load_model", ["impedance", "power"])
def test_simbench_at_the_study_case_equals_runpp(simbench_nets, load_model):
    net, data = simbench_nets[load_model]
    available = available_power_w(data, ACTUATORS)
    sample = GridSolver(data, ACTUATORS).solve(available)
    reference = runpp_sample(net, ACTUATORS, available)
    assert_agrees(sample, reference, p_tol_w=1.0)       # 1 W, far inside 1 kW / 1 kvar
    assert sample.p_ip_w > 1e7                           # lW: MV -> HV, P_IP > 0


@pytest.mark.slow
@pytest.mark.parametrize("load_model", ["impedance", "power"])
def test_simbench_random_operating_points_equal_runpp(simbench_nets, load_model):
    net, data = simbench_nets[load_model]
    solver = GridSolver(data, ACTUATORS)
    available = available_power_w(data, ACTUATORS)
    rng = np.random.default_rng(2024)
    worst = 0.0
    for _ in range(50):
        p = rng.uniform(0.0, 1.0, len(ACTUATORS)) * available
        sample = solver.solve(p)
        reference = runpp_sample(net, ACTUATORS, p)
        assert_agrees(sample, reference, p_tol_w=1.0)
        worst = max(worst, abs(sample.p_ip_w - reference[0]))
    assert worst < 1.0


@pytest.mark.slow
def test_simbench_loads_consume_s0_times_v_squared(simbench_case_net, simbench_nets):
    """Independent of pandapower's load models: the active power balance closes with every
    load taken as P0 |V|² (P0 and the bus from the net, |V| from the solution)."""
    _, data = simbench_nets["impedance"]
    solver = GridSolver(data, ACTUATORS)
    p = 0.5 * available_power_w(data, ACTUATORS)
    sample = solver.solve(p)
    net = simbench_case_net
    vm = dict(zip(net.bus.index, np.abs(solver.voltages_pu[data.report_bus])))
    loads = net.load[net.load.in_service]
    p_load = float(np.sum(loads.p_mw.to_numpy() * np.array([vm[b] for b in loads.bus]) ** 2))
    sgen = data.sgen_p_mw.copy()
    sgen[data.sgen_index(ACTUATORS)] = p / 1e6
    model = solver.model
    losses = sum(float(np.sum(model_res()[0])) for model_res in (
        model.get_line_res1, model.get_line_res2, model.get_trafo_res1, model.get_trafo_res2))
    residual = -sample.p_ip_w / 1e6 + sgen.sum() - p_load - losses
    assert abs(residual) < 1e-6                          # MW: below 1 W
    assert p_load > 1.05 * loads.p_mw.sum()              # and V² matters here (V > 1.02 p.u.)


@pytest.mark.slow
def test_simbench_study_case_values(simbench_case_net):
    net = simbench_case_net
    factors = net.loadcases.loc["lW"]
    data = build_grid_data(copy.deepcopy(net), CODE, "lW", "power")
    # installed power times the case's factor per type (docs/method.md#reference-case table,
    # simbench's loadcases)
    by_type = {"WT": ("MV1.101 SGen 1", 2.0e6, "Wind_p"), "CHP": ("MV1.101 MV SGen 5", 0.31e6,
               "RES_p"), "PV": ("MV1.101 MV SGen 9", 0.195e6, "PV_p")}
    for name, p_inst, column in by_type.values():
        assert available_power_w(data, [name])[0] == pytest.approx(p_inst * factors[column])
    assert net.ext_grid.vm_pu.iloc[0] == factors["Slack_vm"]
    base = grid_net.__globals__["load_simbench_net"](CODE)
    assert net.load.p_mw.to_numpy() == pytest.approx(base.load.p_mw.to_numpy() * factors["pload"])
    assert net.load.q_mvar.to_numpy() == pytest.approx(
        base.load.q_mvar.to_numpy() * factors["qload"])
    with pytest.raises(GridError, match="unknown study case 'xx'.*hL, n1, hW, hPV, lW, lPV"):
        apply_study_case(base, "xx")


@pytest.mark.slow
def test_simbench_cache_round_trip_gives_identical_results(tmp_path):
    cold = load_grid(CODE, "lW", cache_dir=tmp_path)
    warm = load_grid(CODE, "lW", cache_dir=tmp_path)
    rng = np.random.default_rng(5)
    a, b = GridSolver(cold, ACTUATORS), GridSolver(warm, ACTUATORS)
    available = available_power_w(cold, ACTUATORS)
    for _ in range(5):
        p = rng.uniform(0.0, 1.0, len(ACTUATORS)) * available
        assert a.solve(p) == b.solve(p)


def test_unknown_simbench_code_is_a_one_line_error(tmp_path):
    with pytest.raises(GridError, match="'1-MV-nowhere--0-no_sw' is not a SimBench code"):
        load_grid("1-MV-nowhere--0-no_sw", "lW", cache_dir=tmp_path)


def test_is_cached_looks_where_load_grid_stores(tmp_path) -> None:
    # up announces "tens of seconds to build its cache" only when load_grid will build one
    from adnmesh.grid.cache import cache_key, cache_path, is_cached
    args = ("1-MV-rural--0-no_sw", "lW", "impedance")
    assert not is_cached(*args, cache_dir=tmp_path)
    cache_path(cache_key(*args), tmp_path).write_bytes(b"")
    assert is_cached(*args, cache_dir=tmp_path)
    assert not is_cached("1-MV-rural--0-no_sw", "hL", "impedance", cache_dir=tmp_path)
