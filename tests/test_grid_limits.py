"""The grid at its limits: names of the elements, where the extremes are, the HV/MV transformer's
tap changer and the limit sensitivities, each against pandapower's ``runpp``.

Fast tests use the small net of ``test_grid``; the slow ones SimBench's 1-MV-rural.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pandapower as pp
import pytest

from adnmesh.errors import GridError
from adnmesh.grid import GridSolver, available_power_w
from adnmesh.grid.data import from_arrays, to_arrays
from adnmesh.grid.from_net import build_grid_data
from adnmesh.grid.sensitivity import limit_sensitivities
from adnmesh.grid.simbench_net import grid_net, loads_as_impedances
from test_grid import ACTUATORS, CODE, SMALL_ACTUATORS, small_net

#: central differences of runpp: half-width, W and var
RUNPP_STEP = 1e3


def tapped_net(side: str = "hv", kind: str | None = "Ratio", pos: float = 1.0):
    """The small net with its transformer's tap changer on ``side``, of type ``kind``, at
    ``pos`` (range -9..9, 1.5 % per step, neutral 0: the standard type's), loads as
    impedances."""
    net = small_net()
    net.trafo["tap_side"] = side
    net.trafo["tap_changer_type"] = kind
    net.trafo["tap_pos"] = pos
    loads_as_impedances(net)
    return net


def runpp_state(net, names, p_w, q_var=None):
    """``runpp`` of ``net`` with the named sgens at ``p_w`` (and ``q_var``): bus voltages by
    bus name (all but the slack's), line and trafo loadings, P_IP and Q_IP (W, var)."""
    rows = [int(net.sgen.index[net.sgen.name == n][0]) for n in names]
    net.sgen.loc[rows, "p_mw"] = np.asarray(p_w, dtype=float) / 1e6
    if q_var is not None:
        net.sgen.loc[rows, "q_mvar"] = np.asarray(q_var, dtype=float) / 1e6
    pp.runpp(net, tolerance_mva=1e-10)
    adn = ~net.bus.index.isin(net.ext_grid.bus)
    vm = dict(zip(net.bus.name[adn], net.res_bus.vm_pu[adn]))
    ext = net.res_ext_grid
    return (vm, net.res_line.loading_percent.to_numpy(), net.res_trafo.loading_percent.to_numpy(),
            -ext.p_mw.sum() * 1e6, -ext.q_mvar.sum() * 1e6)


def assert_state_equals_runpp(solver, sample, state, p_tol_w=1.0, vm_tol_pu=1e-7):
    vm, line, trafo, p_ip, q_ip = state
    assert sample.converged
    assert abs(sample.p_ip_w - p_ip) <= p_tol_w and abs(sample.q_ip_var - q_ip) <= p_tol_w
    want = np.array([vm[name] for name in solver.bus_names])
    np.testing.assert_allclose(solver.bus_vm_pu(), want, rtol=0, atol=vm_tol_pu)
    np.testing.assert_allclose(solver.line_loading_pct(), line, rtol=0, atol=1e-5)
    np.testing.assert_allclose(solver.trafo_loading_pct(), trafo, rtol=0, atol=1e-5)


def runpp_differences(net, names, p_w, q_var, columns):
    """Central differences of ``runpp``: for each (actuator, "p" or "q") of ``columns`` the
    derivative of (voltages by name, line loadings, trafo loadings), per W or per var."""
    out = []
    for d, quantity in columns:
        ends = []
        for sign in (1.0, -1.0):
            p, q = np.array(p_w, dtype=float), np.array(q_var, dtype=float)
            (p if quantity == "p" else q)[d] += sign * RUNPP_STEP
            ends.append(runpp_state(net, names, p, q))
        (vm_hi, line_hi, trafo_hi, *_), (vm_lo, line_lo, trafo_lo, *_) = ends
        out.append(({b: (vm_hi[b] - vm_lo[b]) / (2 * RUNPP_STEP) for b in vm_hi},
                    (line_hi - line_lo) / (2 * RUNPP_STEP),
                    (trafo_hi - trafo_lo) / (2 * RUNPP_STEP)))
    return out


def assert_sensitivities_equal_runpp(solver, sens, reference, columns, rtol):
    """Each column of ``sens`` against ``runpp``'s differences, to ``rtol`` of the column's
    largest entry (per quantity: voltages, lines, trafos)."""
    for (d, quantity), (dv, dline, dtrafo) in zip(columns, reference):
        got = [getattr(sens, f"{x}_d{quantity}")[:, d] for x in ("dv", "dline", "dtrafo")]
        want = [np.array([dv[name] for name in solver.bus_names]), dline, dtrafo]
        for g, w in zip(got, want):
            if w.size:
                np.testing.assert_allclose(g, w, rtol=0, atol=rtol * np.abs(w).max())
                assert np.abs(w).max() > 0


# ---------------------------------------------------------------------------------------------
# names and where the extremes are


def test_names_of_buses_lines_transformers_and_where_the_extremes_are():
    net = small_net()
    net.bus.at[4, "name"] = None                         # MV3: no name, its index stands in
    loads_as_impedances(net)
    solver = GridSolver(build_grid_data(copy.deepcopy(net), "small", "base", "impedance"),
                        SMALL_ACTUATORS)
    assert solver.bus_names == ("MV0", "MV1", "MV2", "bus 4", "MV4", "MV5")   # not the slack
    assert solver.line_names == ("line 0", "line 1", "line 2", "line 3", "line 4", "loop")
    assert solver.trafo_names == ("T1",)
    assert len(solver.bus_names) == solver.bus_vm_pu().size == solver.reported_buses.size
    for p in ([4.0e6, 1.0e6], [0.0, 0.0], [0.5e6, 1.0e6]):
        sample = solver.solve(p)
        runpp_state(net, SMALL_ACTUATORS, p)
        adn = net.res_bus.vm_pu.drop(net.ext_grid.bus)
        name = {b: n if isinstance(n, str) else f"bus {b}" for b, n in net.bus.name.items()}
        assert (sample.vm_min_at, sample.vm_max_at) == (name[adn.idxmin()], name[adn.idxmax()])
        lines = net.res_line.loading_percent
        assert sample.line_max_at == solver.line_names[int(np.argmax(lines.to_numpy()))]
        assert sample.trafo_max_at == "T1"
    assert {solver.solve([4.0e6, 1.0e6]).vm_max_at, solver.solve([0.0, 0.0]).vm_min_at} == \
        {"MV2", "MV5"}                                   # the ends of the two feeders
    failed = solver.solve([5.0e9, 0.0])
    assert not failed.converged
    assert (failed.vm_min_at, failed.vm_max_at, failed.line_max_at, failed.trafo_max_at) == \
        ("", "", "", "")


def test_a_sample_without_the_new_fields_still_builds():
    """Callers that build a GridSample positionally (eight fields) keep working."""
    from adnmesh.grid import GridSample
    sample = GridSample(1.0, 2.0, 0.99, 1.01, 50.0, 40.0, True, 3)
    assert (sample.vm_min_at, sample.trafo_max_at) == ("", "")


def test_names_and_taps_round_trip_and_are_checked():
    data = build_grid_data(tapped_net("lv", pos=-2.0), "small-tap", "base", "impedance")
    back = from_arrays(to_arrays(data), data.lsgrid.copy())
    for field in ("bus_names", "line_names", "trafo_names", "tap_side"):
        assert getattr(back, field) == getattr(data, field)
    for field in ("tap_neutral", "tap_min", "tap_max", "tap_step_percent", "tap_pos"):
        np.testing.assert_array_equal(getattr(back, field), getattr(data, field))
    assert (data.tap_side, data.tap_pos.tolist(), data.tap_min.tolist(), data.tap_max.tolist(),
            data.tap_step_percent.tolist(), data.tap_neutral.tolist()) == \
        (("lv",), [-2.0], [-9.0], [9.0], [1.5], [0.0])
    for change in ({"bus_names": data.bus_names[1:]}, {"trafo_names": ()},
                   {"tap_side": ("middle",)}, {"tap_min": np.array([10.0])},
                   {"tap_pos": np.array([np.nan])}, {"tap_max": np.array([9.0, 9.0])}):
        bad = dataclasses.replace(data, **change)
        with pytest.raises(ValueError, match="do not fit the grid model"):
            from_arrays(to_arrays(bad), data.lsgrid.copy())


# ---------------------------------------------------------------------------------------------
# taps


@pytest.mark.parametrize("side", ["hv", "lv"])
def test_set_tap_equals_runpp_at_every_position_tried(side):
    """The model's ratio (and for an lv tap its impedances) as runpp's at each position;
    back at the first position the results are the first ones again."""
    net = tapped_net(side, pos=1.0)
    solver = GridSolver(build_grid_data(copy.deepcopy(net), "small-tap", "base", "impedance"),
                        SMALL_ACTUATORS)
    assert solver.tap_pos(0) == 1
    p, q = np.array([2.5e6, 0.6e6]), np.array([0.3e6, -0.1e6])
    first = solver.solve(p, q)
    vm_at = {}
    for pos in (-9, -4, 0, 3, 9, 1):
        solver.set_tap(0, pos)
        assert solver.tap_pos(0) == pos
        sample = solver.solve(p, q)
        net.trafo["tap_pos"] = float(pos)
        assert_state_equals_runpp(solver, sample, runpp_state(net, SMALL_ACTUATORS, p, q))
        vm_at[pos] = solver.bus_vm_pu()[0]               # MV0, the MV busbar
    assert sample.p_ip_w == pytest.approx(first.p_ip_w, abs=1e-3)
    raising = vm_at[9] > vm_at[-9]              # up: more turns on the tap's side (pandapower)
    assert raising == (side == "lv") and abs(vm_at[9] - vm_at[-9]) > 0.2


def test_set_tap_without_a_tap_changer_type_moves_as_a_ratio_tap():
    """A net that names no tap changer type (SimBench's under pandapower 3): runpp ignores
    its tap_pos, the model starts at neutral, set_tap moves it as runpp with type 'Ratio'."""
    net = tapped_net("hv", kind=None, pos=-1.0)
    data = build_grid_data(copy.deepcopy(net), "small-tap", "base", "impedance")
    assert data.tap_pos.tolist() == [0.0]              # where runpp (and the model) have it
    solver = GridSolver(data, SMALL_ACTUATORS)
    p = np.array([1.5e6, 0.2e6])
    net.trafo["tap_changer_type"] = "Ratio"
    for pos in (2, -3):
        solver.set_tap(0, pos)
        net.trafo["tap_pos"] = float(pos)
        assert_state_equals_runpp(solver, solver.solve(p), runpp_state(net, SMALL_ACTUATORS, p))


def test_set_tap_rejects_what_it_cannot_do_in_one_line():
    solver = GridSolver(build_grid_data(tapped_net("hv"), "small-tap", "base", "impedance"),
                        SMALL_ACTUATORS)
    cases = [((0, 10), r"tap position 10 of transformer 0 \(T1\) is not an integer in its "
                       r"range \[-9, 9\]"),
             ((0, -10), "not an integer in its range"), ((0, 1.5), "not an integer"),
             ((1, 0), "no transformer 1 \\(the grid has 1\\)")]
    for args, message in cases:
        with pytest.raises(GridError, match=message) as error:
            solver.set_tap(*args)
        assert "\n" not in str(error.value)
    assert solver.tap_pos(0) == 1                      # nothing changed
    none = small_net()
    none.trafo["tap_step_percent"] = np.nan
    data = build_grid_data(none, "small-none", "base", "power")
    assert data.tap_side == ("none",) and np.isnan(data.tap_pos).all()
    for call in (lambda s: s.set_tap(0, 1), lambda s: s.tap_pos(0)):
        with pytest.raises(GridError, match=r"transformer 0 \(T1\) has no ratio tap changer"):
            call(GridSolver(data, SMALL_ACTUATORS))


# ---------------------------------------------------------------------------------------------
# limit sensitivities


@pytest.mark.parametrize("method, rtol", [("jacobian", 1e-5), ("differences", 1e-4)])
@pytest.mark.parametrize("tap", [None, 4])
def test_limit_sensitivities_equal_central_differences_of_runpp(method, rtol, tap):
    """Every voltage and loading derivative by each actuator's P and Q, against runpp's own
    central differences (1 kW / 1 kvar, runpp to 1e-10 MVA: their error ~1e-6), to ``rtol`` of
    each column's largest (the Jacobian's is exact; the solver's differences carry its
    tolerance, 0.01 W, over 2 kW); with an lv tap moved by set_tap too. The solver is left at
    the operating point."""
    net = tapped_net("lv", pos=0.0)
    solver = GridSolver(build_grid_data(copy.deepcopy(net), "small", "base", "impedance"),
                        SMALL_ACTUATORS)
    if tap is not None:
        solver.set_tap(0, tap)
        net.trafo["tap_pos"] = float(tap)
    p, q = np.array([3.0e6, 0.7e6]), np.array([0.4e6, -0.2e6])
    sens = limit_sensitivities(solver, p, q, method=method)
    assert sens.dv_dp.shape == sens.dv_dq.shape == (6, 2)
    assert sens.dline_dp.shape == (6, 2) and sens.dtrafo_dq.shape == (1, 2)
    columns = [(d, x) for d in range(2) for x in ("p", "q")]
    reference = runpp_differences(net, SMALL_ACTUATORS, p, q, columns)
    assert_sensitivities_equal_runpp(solver, sens, reference, columns, rtol=rtol)
    at_point = runpp_state(net, SMALL_ACTUATORS, p, q)
    assert_state_equals_runpp(solver, solver.solve(p, q), at_point)
    np.testing.assert_allclose(sens.vm_pu, solver.bus_vm_pu(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(sens.line_pct, at_point[1], rtol=0, atol=1e-5)
    fresh = GridSolver(solver.data, SMALL_ACTUATORS)
    if tap is not None:
        fresh.set_tap(0, tap)
    fresh.solve(p, q)
    limit_sensitivities(solver, p, q, method=method)
    np.testing.assert_allclose(solver.voltages_pu, fresh.voltages_pu, rtol=0, atol=1e-9)


def test_more_infeed_at_a_feeder_end_raises_its_voltage():
    """The signs a guard relies on: P or Q fed in at a feeder's end raises the voltage there
    (more at the end than at the busbar), and the WT's P export loads the line it flows
    through."""
    net = small_net()
    loads_as_impedances(net)
    solver = GridSolver(build_grid_data(net, "small", "base", "impedance"), SMALL_ACTUATORS)
    sens = limit_sensitivities(solver, [3.0e6, 0.8e6], [0.0, 0.0])
    bus = {name: k for k, name in enumerate(solver.bus_names)}
    for der, end in ((0, "MV2"), (1, "MV4")):            # WT at MV2, PV at MV4
        assert sens.dv_dp[bus[end], der] > 0 and sens.dv_dq[bus[end], der] > 0
        assert sens.dv_dp[bus[end], der] > sens.dv_dp[bus["MV0"], der]
    assert sens.dline_dp[1, 0] > 0                     # MV1-MV2 carries the WT's export
    assert sens.dtrafo_dp[0, 0] > 0                    # 5 MW of sgens, 3.5 MW of load: export


def test_limit_sensitivities_reject_an_unknown_method():
    net = small_net()
    solver = GridSolver(build_grid_data(net, "small", "base", "power"), SMALL_ACTUATORS)
    with pytest.raises(GridError, match="method must be one of jacobian, differences"):
        limit_sensitivities(solver, [1e6, 1e5], [0.0, 0.0], method="secant")


# ---------------------------------------------------------------------------------------------
# slow: SimBench 1-MV-rural


@pytest.fixture(scope="module")
def rural():
    """(net for runpp, its solver data) of 1-MV-rural at lW, loads as impedances."""
    net = grid_net(CODE, "lW", "impedance")
    return net, build_grid_data(copy.deepcopy(net), CODE, "lW", "impedance")


@pytest.mark.slow
def test_simbench_trafo_tap_data_and_set_tap_equal_runpp(rural):
    """SimBench's two parallel HV/MV transformers: a ratio tap on the hv side, -9..9, 1.5 %
    per step, neutral 0, at 0 in lW, no tap changer type. ±2 steps on one and on both equal
    runpp with the type 'Ratio'."""
    net, data = rural
    assert data.trafo_names == ("HV1-MV1.101-Trafo1", "HV1-MV1.101-Trafo2")
    assert data.tap_side == ("hv", "hv")
    for field, value in (("tap_min", -9), ("tap_max", 9), ("tap_step_percent", 1.5),
                         ("tap_neutral", 0), ("tap_pos", 0)):
        assert getattr(data, field).tolist() == [value, value]
    net = copy.deepcopy(net)
    net.trafo["tap_changer_type"] = "Ratio"
    solver = GridSolver(data, ACTUATORS)
    p = 0.7 * available_power_w(data, ACTUATORS)
    for positions in ((2, 0), (-2, 0), (2, 2), (-2, -2)):
        for trafo, pos in enumerate(positions):
            solver.set_tap(trafo, pos)
        net.trafo["tap_pos"] = [float(x) for x in positions]
        assert_state_equals_runpp(solver, solver.solve(p), runpp_state(net, ACTUATORS, p))


@pytest.mark.slow
def test_simbench_limit_sensitivities_of_two_ders_equal_runpp(rural):
    """Two DERs (a wind turbine and a CHP) against runpp's central differences, to 1e-4 of
    each column's largest (runpp's 1 kW differences carry up to ~1.5e-5 here: its loadings'
    rounding). Each DER's Q raises the voltage of its own bus, and so does the P of each on a
    feeder; the wind turbine on the MV busbar (SGen 1) lowers it, by 3e-11 p.u./W: its export
    only adds the transformers' reactive losses."""
    net, data = rural
    net = copy.deepcopy(net)
    solver = GridSolver(data, ACTUATORS)
    p = 0.8 * available_power_w(data, ACTUATORS)
    q = np.zeros(len(ACTUATORS))
    sens = limit_sensitivities(solver, p, q)
    assert sens.dv_dp.shape == (len(solver.bus_names), 11)
    assert sens.dline_dq.shape == (len(data.line_names), 11)
    assert sens.dtrafo_dp.shape == (2, 11)
    columns = [(0, "p"), (0, "q"), (4, "p"), (4, "q")]   # SGen 1 (WT), MV SGen 5 (CHP)
    reference = runpp_differences(net, ACTUATORS, p, q, columns)
    assert_sensitivities_equal_runpp(solver, sens, reference, columns, rtol=1e-4)
    sgen_bus = net.sgen.set_index("name").bus
    bus = {name: k for k, name in enumerate(solver.bus_names)}
    for d in range(len(ACTUATORS)):
        own = bus[net.bus.name[sgen_bus[ACTUATORS[d]]]]
        assert sens.dv_dq[own, d] > 1e-9
        on_busbar = net.bus.name[sgen_bus[ACTUATORS[d]]] == "MV1.101 busbar1.1"
        assert on_busbar == (d == 0)
        assert sens.dv_dp[own, d] > 1e-9 if not on_busbar else abs(sens.dv_dp[own, d]) < 1e-10
