"""Build :class:`~adnmesh.grid.data.GridData` from a pandapower net (imports pandapower).

:func:`build_grid_data` solves the net with pandapower's ``runpp`` (the reference), converts it
with lightsim2grid's own converter (``lightsim2grid.network.init_from_pandapower``) and accepts
the model only if it reproduces ``runpp`` at that operating point — P and Q at the slack to
1 W / 1 var, every bus voltage to 1e-7 p.u., the largest line and transformer loading to 1e-5 %.

Two things the converter does not do are done before it, on a copy of the net:

- **Switches.** The converter ignores switches, which would close the six open loop lines of
  1-MV-rural. An open line or transformer switch becomes what pandapower makes of it
  internally: an auxiliary bus at that end of the branch (a line stays energised from its other
  end, with its charging current); a closed one is dropped. Bus-bus switches are not supported.
- **Column types.** SimBench leaves the generators' optional limit columns as objects, which the
  converter cannot read; they are cast to floats (their NaNs become 0, unused by the power flow).

The converter's transformer formula (``pp_orig_file``) is the first of ``"pandapower_v3"``,
``"pandapower_v2"`` whose model passes the check. With pandapower 3.5.6 and SimBench's
transformers (taps at neutral, 150° shift) it is ``"pandapower_v2"``, to 1 mW; ``"pandapower_v3"``
is off by 68 W at lW.

Supported nets: one external grid; lines, two-winding transformers, line and transformer
switches, shunts, loads (constant power) and static generators. Anything else in service (gen,
storage, ward, ...) is a :class:`GridError`.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np

from adnmesh.grid.data import GridData
from adnmesh.errors import GridError
from adnmesh.grid.solver import GridSolver

__all__ = ["build_grid_data", "without_switches", "UNSUPPORTED", "CONVERTERS"]

UNSUPPORTED = ("gen", "storage", "ward", "xward", "impedance", "dcline", "trafo3w", "motor",
               "asymmetric_load", "asymmetric_sgen", "svc", "tcsc", "ssc", "vsc",
               "source_dc", "load_dc")
CONVERTERS = ("pandapower_v3", "pandapower_v2")
_TOL = {"p_w": 1.0, "vm_pu": 1e-7, "loading_pct": 1e-5}
_FLOAT_COLUMNS = {"sgen": ("min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar"),
                  "load": ("min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar")}


def build_grid_data(net, code: str, case: str, load_model: str) -> GridData:
    """The solver's data of ``net`` (see the module docstring); ``net`` is not changed.

    ``code``, ``case`` and ``load_model`` only label the data; ``net`` must already be at its
    study case with its loads modelled as wanted (:func:`adnmesh.grid.simbench_net.grid_net`).
    """
    import pandapower as pp

    _check_supported(net)
    reference = copy.deepcopy(net)
    pp.runpp(reference)
    if reference._options["trafo_loading"] != "current":
        raise GridError("grid: only pandapower's trafo_loading='current' is supported")
    model_net = without_switches(reference)
    pp.runpp(model_net)                          # its voltages start the model's first solve
    failures = []
    for converter in CONVERTERS:
        data = _convert(model_net, reference, code, case, load_model, converter)
        bad = _differences(data, reference)
        if not bad:
            return data
        failures.append(f"{converter}: {bad}")
    worst = failures[-1] if failures else ""
    raise GridError(f"grid {code}: the solver's model does not reproduce pandapower's runpp "
                    f"(not supported yet, e.g. an off-neutral transformer tap); "
                    f"{' '.join(str(worst).split())[:300]}")


def without_switches(net):
    """A copy of ``net`` without switches, open line/transformer ends on auxiliary buses."""
    import pandapower as pp

    out = copy.deepcopy(net)
    switches = out.switch
    if (switches.et == "b").any():
        raise GridError("grid: bus-bus switches are not supported by the solver")
    for _, sw in switches[~switches.closed.astype(bool)].iterrows():
        table, ends = ("line", ("from_bus", "to_bus")) if sw.et == "l" else \
            ("trafo", ("hv_bus", "lv_bus"))
        branch = int(sw.element)
        aux = pp.create_bus(out, out.bus.vn_kv.at[sw.bus], name=f"aux of open switch {sw.name}")
        for end in ends:
            if out[table].at[branch, end] == sw.bus:
                out[table].at[branch, end] = aux
                break
    out.switch = out.switch.iloc[0:0]
    for table, columns in _FLOAT_COLUMNS.items():
        for column in columns:
            if column in out[table]:
                out[table][column] = out[table][column].astype(float)
    return out


def _check_supported(net) -> None:
    for element in UNSUPPORTED:
        table = net.get(element)
        if table is not None and len(table) and bool(table.in_service.any()):
            raise GridError(f"grid: element type {element!r} is not supported by the solver")
    if int(net.ext_grid.in_service.sum()) != 1:
        raise GridError("grid: exactly one external grid (the slack) is supported")


def _convert(model_net, reference, code, case, load_model, converter) -> GridData:
    """The model of ``model_net`` by lightsim2grid's converter, with the arrays around it."""
    from lightsim2grid.network import init_from_pandapower

    with warnings.catch_warnings():      # NaN limits replaced, slack added, no switches: known
        warnings.simplefilter("ignore")
        grid = init_from_pandapower(model_net, pp_orig_file=converter)
    order = np.sort(model_net.bus.index.to_numpy())           # the model's bus order
    res = model_net.res_bus.loc[order]
    v_init = (res.vm_pu.to_numpy() * np.exp(1j * np.deg2rad(res.va_degree.to_numpy())))
    sgen, line, trafo = model_net.sgen, model_net.line, model_net.trafo
    on = sgen.in_service.to_numpy(dtype=bool) * sgen.scaling.fillna(1.0).to_numpy()
    buses = reference.bus.index[reference.bus.in_service.to_numpy(dtype=bool)]
    return GridData(
        code=code, case=case, load_model=load_model, converter=converter, lsgrid=grid,
        v_init=v_init.astype(complex), sgen_names=tuple(str(n) for n in sgen.name),
        sgen_types=tuple("" if t != t or t is None else str(t)
                         for t in (sgen.type if "type" in sgen else [None] * len(sgen))),
        sgen_rating_mw=_ratings(sgen),
        sgen_p_mw=sgen.p_mw.to_numpy(dtype=float) * on,
        sgen_q_mvar=sgen.q_mvar.to_numpy(dtype=float) * on,
        slack_gen=len(model_net.gen),            # the converter appends it after the gens
        report_bus=np.searchsorted(order, buses.to_numpy()).astype(np.int64),
        line_i_max_ka=(line.max_i_ka * line.df * line.parallel).to_numpy(dtype=float),
        trafo_vn_hv_kv=trafo.vn_hv_kv.to_numpy(dtype=float),
        trafo_vn_lv_kv=trafo.vn_lv_kv.to_numpy(dtype=float),
        trafo_rating_mva=(trafo.sn_mva * trafo.parallel * trafo.df).to_numpy(dtype=float))


def _ratings(sgen) -> np.ndarray:
    """Each static generator's ``sn_mva`` (the rating; SimBench: its installed power), MW; NaN
    where it is missing or not positive."""
    if "sn_mva" not in sgen:
        return np.full(len(sgen), np.nan)
    rating = sgen.sn_mva.astype(float).to_numpy()
    return np.where(rating > 0, rating, np.nan)


def _differences(data: GridData, reference) -> list:
    """What the model's solution of ``reference``'s operating point gets wrong (empty: none)."""
    solver = GridSolver(data, actuator_sgens=())
    sample = solver.solve(np.zeros(0))
    if not sample.converged:
        return ["no convergence"]
    vm = np.abs(solver.voltages_pu[data.report_bus])
    in_service = reference.bus.in_service.to_numpy(dtype=bool)
    vm_ref = reference.res_bus.vm_pu[in_service].to_numpy()
    slack = reference.ext_grid.index[reference.ext_grid.in_service]
    ext = reference.res_ext_grid.loc[slack]
    adn = reference.res_bus.vm_pu[in_service & ~reference.bus.index.isin(
        reference.ext_grid.bus[slack])]              # the solver's extremes leave out the slack
    adn = adn if len(adn) else reference.res_bus.vm_pu[in_service]
    pairs = [("p_w", sample.p_ip_w, -ext.p_mw.iloc[0] * 1e6),
             ("p_w", sample.q_ip_var, -ext.q_mvar.iloc[0] * 1e6),
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
