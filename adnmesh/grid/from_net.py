"""Build :class:`~adnmesh.grid.data.GridData` from a pandapower net (imports pandapower).

:func:`build_grid_data` solves the net with pandapower's ``runpp`` (the reference), converts the
copy :func:`adnmesh.grid.model_net.model_net` makes of it (switches, bus couplers, taps as
``runpp`` reads them) with lightsim2grid's own converter
(``lightsim2grid.network.init_from_pandapower``) and accepts the model only if it reproduces
``runpp`` at that operating point — P and Q at the interconnection point to 1 W / 1 var, every
bus voltage to 1e-7 p.u., the largest line and transformer loading to 1e-5 %.

**Several external grids** (SimBench's 1-HV-mixed: three EHV/HV substations). ``runpp`` holds
each external grid's bus at its voltage magnitude and angle. When they all have the same voltage
(magnitude and angle, as in every SimBench grid), the buses are one node of the upper grid seen
from the ADN: the model moves every element of the other external grids' buses onto the first's
bus (branch data in per unit, so a 220 kV and a 380 kV bus join exactly) and keeps one slack.
The interconnection point is then all the external grids together: ``P_IP``/``Q_IP`` are the sum
of their injections with the sign turned. External grids at different voltages are a
:class:`GridError`.

The converter's transformer formula (``pp_orig_file``) is the first of ``"pandapower_v3"``,
``"pandapower_v2"`` whose model passes the check. With pandapower 3.5.6 and SimBench's
transformers (150° shift) it is ``"pandapower_v2"``, to 1 mW; ``"pandapower_v3"`` is off by 68 W
at lW.

**Names and taps.** Every reported bus, line and transformer keeps its name in the net (else
``bus <index>``, ``line <index>``, ``trafo <index>``), and every transformer its ratio tap
changer (side, neutral, range, % per step) with the position the model is at
(:class:`~adnmesh.grid.data.GridData`), for :meth:`adnmesh.grid.GridSolver.set_tap`.

Supported nets: external grids (at one voltage), lines, two-winding transformers (ratio taps),
switches of every kind, shunts, loads, static generators and storages (constant power). Anything
else in service (gen, ward, trafo3w, ...) is a :class:`GridError`.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np

from adnmesh.grid.data import GridData
from adnmesh.errors import GridError
from adnmesh.grid.model_net import IGNORED_TAP_TYPES, model_net
from adnmesh.grid.solver import GridSolver

__all__ = ["build_grid_data", "UNSUPPORTED", "CONVERTERS"]

UNSUPPORTED = ("gen", "ward", "xward", "impedance", "dcline", "trafo3w", "motor",
               "asymmetric_load", "asymmetric_sgen", "svc", "tcsc", "ssc", "vsc",
               "source_dc", "load_dc")
CONVERTERS = ("pandapower_v3", "pandapower_v2")
_TOL = {"p_w": 1.0, "vm_pu": 1e-7, "loading_pct": 1e-5}


def build_grid_data(net, code: str, case: str, load_model: str) -> GridData:
    """The solver's data of ``net`` (see the module docstring); ``net`` is not changed.

    ``code``, ``case`` and ``load_model`` only label the data; ``net`` must already be at its
    study case with its loads modelled as wanted (:func:`adnmesh.grid.simbench_net.grid_net`).
    """
    import pandapower as pp

    _check_supported(net)
    reference = copy.deepcopy(net)
    _runpp(pp, reference, code)
    if reference._options["trafo_loading"] != "current":
        raise GridError("grid: only pandapower's trafo_loading='current' is supported")
    model, bus_map = model_net(reference)
    _runpp(pp, model, code)                      # its voltages start the model's first solve
    failures = []
    for converter in CONVERTERS:
        data = _convert(model, reference, bus_map, code, case, load_model, converter)
        bad = _differences(data, reference)
        if not bad:
            return data
        failures.append(f"{converter}: {bad}")
    worst = failures[-1] if failures else ""
    raise GridError(f"grid {code}: the solver's model does not reproduce pandapower's runpp; "
                    f"{' '.join(str(worst).split())[:300]}")


def _runpp(pp, net, code: str) -> None:
    try:
        pp.runpp(net)
    except pp.LoadflowNotConverged:
        raise GridError(f"grid {code}: pandapower's runpp does not converge at this operating "
                        f"point") from None


def _check_supported(net) -> None:
    for element in UNSUPPORTED:
        table = net.get(element)
        if table is not None and len(table) and bool(table.in_service.any()):
            raise GridError(f"grid: element type {element!r} is not supported by the solver")
    ext = net.ext_grid[net.ext_grid.in_service.astype(bool)]
    if not len(ext):
        raise GridError("grid: the net has no external grid in service (the interconnection "
                        "point)")
    voltage = ext.vm_pu.astype(float).to_numpy(), ext.va_degree.astype(float).to_numpy()
    if any(np.ptp(v) > 0.0 for v in voltage):
        raise GridError(f"grid: {len(ext)} external grids at different voltages are not "
                        f"supported (vm_pu {sorted(set(voltage[0].tolist()))}, va_degree "
                        f"{sorted(set(voltage[1].tolist()))}); the model joins them into one "
                        f"interconnection point")
    trafo = net.trafo[net.trafo.in_service.astype(bool)]
    if "tap_changer_type" in trafo and (trafo.tap_changer_type == "Ideal").any():
        raise GridError("grid: transformers with an ideal phase-shifting tap changer "
                        "(tap_changer_type 'Ideal') are not supported by the solver")
    if "tap_dependency_table" in trafo and trafo.tap_dependency_table.fillna(False).astype(
            bool).any():
        raise GridError("grid: transformers with tap dependency tables are not supported by "
                        "the solver")


def _convert(model, reference, bus_map, code, case, load_model, converter) -> GridData:
    """The model of ``model`` by lightsim2grid's converter, with the arrays around it."""
    from lightsim2grid.network import init_from_pandapower

    with warnings.catch_warnings():      # NaN limits replaced, slack added, no switches: known
        warnings.simplefilter("ignore")
        grid = init_from_pandapower(model, pp_orig_file=converter)
    slack_gen = len(model.gen)                   # the converter appends one per ext grid
    slack_bus = _one_slack(grid, model, slack_gen)
    vn_hv, vn_lv = _trafo_rated_kv_in_model_base(grid, model, slack_bus)
    res = model.res_bus.sort_index()
    v_init = (res.vm_pu.to_numpy() * np.exp(1j * np.deg2rad(res.va_degree.to_numpy())))
    sgen, line, trafo = model.sgen, model.line, model.trafo
    on = sgen.in_service.to_numpy(dtype=bool) * sgen.scaling.fillna(1.0).to_numpy()
    buses = reference.bus.index[_supplied(reference)]
    report = np.array([bus_map[int(b)] for b in buses], dtype=np.int64)
    taps = _taps(reference.trafo)
    report = np.where(np.isin(report, list(slack_bus)), next(iter(slack_bus.values())),
                      report)
    return GridData(
        code=code, case=case, load_model=load_model, converter=converter, lsgrid=grid,
        v_init=v_init.astype(complex), sgen_names=tuple(str(n) for n in sgen.name),
        sgen_types=tuple("" if t != t or t is None else str(t)
                         for t in (sgen.type if "type" in sgen else [None] * len(sgen))),
        sgen_rating_mw=_ratings(sgen),
        sgen_p_mw=sgen.p_mw.to_numpy(dtype=float) * on,
        sgen_q_mvar=sgen.q_mvar.to_numpy(dtype=float) * on,
        slack_gen=slack_gen, report_bus=report,
        line_i_max_ka=(line.max_i_ka * line.df * line.parallel).to_numpy(dtype=float),
        trafo_vn_hv_kv=vn_hv, trafo_vn_lv_kv=vn_lv,
        trafo_rating_mva=(trafo.sn_mva * trafo.parallel * trafo.df).to_numpy(dtype=float),
        bus_names=_names(reference.bus.loc[buses], "bus"), line_names=_names(line, "line"),
        trafo_names=_names(trafo, "trafo"), **taps)


def _names(table, kind: str) -> tuple[str, ...]:
    """Each row's ``name``, else ``"<kind> <index>"``."""
    names = table.name if "name" in table else [None] * len(table)
    return tuple(f"{kind} {index}" if _missing(name) else str(name)
                 for index, name in zip(table.index, names))


def _missing(value) -> bool:
    return value is None or value != value or str(value).strip() == ""


def _taps(trafo) -> dict:
    """Each transformer's ratio tap changer as :class:`GridData` keeps it (see there): side,
    neutral, range, step and the position the model is at (``trafo`` is the net's table)."""
    n = len(trafo)

    def column(name: str, default) -> np.ndarray:
        if name not in trafo:
            return np.full(n, default, dtype=object)
        return trafo[name].to_numpy(dtype=object)

    side = np.array([str(s) if s in ("hv", "lv") else "none" for s in column("tap_side", None)],
                    dtype=object)
    numbers = {key: np.array(column(key, np.nan), dtype=float)
               for key in ("tap_neutral", "tap_min", "tap_max", "tap_step_percent", "tap_pos")}
    degree = np.nan_to_num(np.array(column("tap_step_degree", np.nan), dtype=float))
    step = numbers["tap_step_percent"]
    has = ((side != "none") & np.isfinite(step) & (step != 0.0) & (degree == 0.0)
           & np.isfinite(numbers["tap_neutral"]) & np.isfinite(numbers["tap_min"])
           & np.isfinite(numbers["tap_max"]) & (numbers["tap_min"] <= numbers["tap_max"]))
    kind = column("tap_changer_type", None)
    applied = np.array([k not in IGNORED_TAP_TYPES and k == k for k in kind], dtype=bool)
    pos = numbers["tap_pos"]
    numbers["tap_pos"] = np.where(applied & np.isfinite(pos), pos, numbers["tap_neutral"])
    out = {key: np.where(has, value, np.nan) for key, value in numbers.items()}
    out["tap_side"] = tuple(str(s) if h else "none" for s, h in zip(side, has))
    return out


def _one_slack(grid, model, first: int) -> dict:
    """Join the external grids' buses into the first's (see the module docstring), in place.

    The converter made one slack generator per external grid, ``first`` onwards; all but the
    first are switched off and every element of their buses moves to the first's bus. Returns
    each external grid's model bus before the move to the bus it is now (the first's).
    """
    gens = grid.get_generators()
    slack_buses = [int(gens[first + k].bus_id) for k in range(len(model.ext_grid))]
    keep = slack_buses[0]
    moved = {bus: keep for bus in slack_buses}
    for k, bus in enumerate(slack_buses[1:], start=1):
        grid.deactivate_gen(first + k)
        if bus == keep:
            continue
        for elements, change in ((grid.get_loads(), grid.change_bus_load),
                                 (grid.get_static_generators(), grid.change_bus_sgen),
                                 (grid.get_shunts(), grid.change_bus_shunt),
                                 (grid.get_storages(), grid.change_bus_storage),
                                 (grid.get_generators(), grid.change_bus_gen)):
            for element in elements:
                if element.connected and int(element.bus_id) == bus:
                    change(element.id, keep)
        for branches, change1, change2 in (
                (grid.get_lines(), grid.change_bus1_powerline, grid.change_bus2_powerline),
                (grid.get_trafos(), grid.change_bus1_trafo, grid.change_bus2_trafo)):
            for branch in branches:
                if int(branch.bus1_id) == bus:
                    change1(branch.id, keep)
                if int(branch.bus2_id) == bus:
                    change2(branch.id, keep)
        grid.deactivate_bus(bus)
    return moved


def _trafo_rated_kv_in_model_base(grid, model, moved: dict):
    """Each transformer's rated hv and lv voltage, kV, times its model bus's nominal voltage
    over its net bus's (1 but where :func:`_one_slack` moved a side; see GridData)."""
    vn_bus = model.bus.vn_kv.sort_index().to_numpy(dtype=float)     # the model's bus order
    sides = []
    for column, rated in (("hv_bus", model.trafo.vn_hv_kv), ("lv_bus", model.trafo.vn_lv_kv)):
        old = model.trafo[column].to_numpy(dtype=np.int64)
        new = np.array([moved.get(int(b), int(b)) for b in old], dtype=np.int64)
        sides.append(rated.to_numpy(dtype=float) * vn_bus[new] / vn_bus[old])
    line = model.line
    for column in ("from_bus", "to_bus"):
        old = line[column].to_numpy(dtype=np.int64)
        new = np.array([moved.get(int(b), int(b)) for b in old], dtype=np.int64)
        if np.any(vn_bus[new] != vn_bus[old]):
            raise GridError("grid: a line at an external grid's bus of another nominal voltage "
                            "than the first external grid's is not supported by the solver")
    return sides[0], sides[1]


def _ratings(sgen) -> np.ndarray:
    """Each static generator's ``sn_mva`` (the rating; SimBench: its installed power), MW; NaN
    where it is missing or not positive."""
    if "sn_mva" not in sgen:
        return np.full(len(sgen), np.nan)
    rating = sgen.sn_mva.astype(float).to_numpy()
    return np.where(rating > 0, rating, np.nan)


def _supplied(reference) -> np.ndarray:
    """The buses of ``reference`` (after runpp) in service and supplied (a voltage)."""
    return reference.bus.in_service.to_numpy(dtype=bool) & np.isfinite(
        reference.res_bus.vm_pu.reindex(reference.bus.index).to_numpy(dtype=float))


def _at_slack(data: GridData) -> np.ndarray:
    """Which of ``data.report_bus`` are the slack's model bus (the upper grid's node)."""
    return data.report_bus == int(data.lsgrid.get_generators()[data.slack_gen].bus_id)


def _differences(data: GridData, reference) -> list:
    """What the model's solution of ``reference``'s operating point gets wrong (empty: none)."""
    solver = GridSolver(data, actuator_sgens=())
    sample = solver.solve(np.zeros(0))
    if not sample.converged:
        return ["no convergence"]
    vm = np.abs(solver.voltages_pu[data.report_bus])
    in_service = _supplied(reference)
    vm_ref = reference.res_bus.vm_pu[in_service].to_numpy()
    slack = reference.ext_grid.index[reference.ext_grid.in_service.astype(bool)]
    ext = reference.res_ext_grid.loc[slack]
    adn = reference.res_bus.vm_pu[in_service][~_at_slack(data)]  # extremes leave out the slack
    adn = adn if len(adn) else reference.res_bus.vm_pu[in_service]
    pairs = [("p_w", sample.p_ip_w, -ext.p_mw.sum() * 1e6),
             ("p_w", sample.q_ip_var, -ext.q_mvar.sum() * 1e6),
             ("vm_pu", float(np.max(np.abs(vm - vm_ref))), 0.0),
             ("vm_pu", sample.vm_min_pu, adn.min()),
             ("vm_pu", sample.vm_max_pu, adn.max())]
    if len(reference.line):
        pairs.append(("loading_pct", sample.line_loading_max_pct,
                      reference.res_line.loading_percent.max()))
    if len(reference.trafo):
        pairs.append(("loading_pct", sample.trafo_loading_max_pct,
                      reference.res_trafo.loading_percent.max()))
    return [(kind, got, want) for kind, got, want in pairs if not abs(got - want) <= _TOL[kind]]
