"""Build :class:`~adnmesh.grid.data.GridData` from a pandapower net (imports pandapower).

:func:`build_grid_data` runs pandapower's ``runpp`` once on the net as it is, takes pandapower's
internal per-unit model of it (``net._ppc["internal"]``: ``Ybus``, ``Yf``, ``Yt``, bus types and
the solved voltages; ``net._pd2ppc_lookups`` for where each element sits), and adds what the
solver needs to put the injections and results together. It then solves the same operating
point with :class:`~adnmesh.grid.solver.GridSolver` and refuses to return data whose solution
differs from ``runpp``'s (P and Q at the slack, every voltage, every loading), so a change of
pandapower's internals cannot pass unnoticed.

Supported nets: one external grid; lines, two-winding transformers, switches, shunts, loads
(constant power) and static generators. Anything else in service (gen, storage, ward, ...) is a
:class:`GridError`.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from adnmesh.grid.data import GridData
from adnmesh.grid.errors import GridError
from adnmesh.grid.solver import GridSolver

__all__ = ["build_grid_data", "UNSUPPORTED"]

UNSUPPORTED = ("gen", "storage", "ward", "xward", "impedance", "dcline", "trafo3w", "motor",
               "asymmetric_load", "asymmetric_sgen", "svc", "tcsc", "ssc", "vsc",
               "source_dc", "load_dc")

_CHECK_TOL = {"p_w": 1.0, "vm_pu": 1e-7, "loading_pct": 1e-5}


def build_grid_data(net, code: str, case: str, load_model: str) -> GridData:
    """Solve ``net`` once with ``runpp`` and return the solver's data of it (see module doc).

    ``code``, ``case`` and ``load_model`` only label the data; ``net`` must already be at its
    study case with its loads modelled as wanted (:func:`adnmesh.grid.simbench_net.grid_net`).
    """
    import pandapower as pp
    from pandapower.pypower.idx_brch import F_BUS, T_BUS

    _check_supported(net)
    pp.runpp(net)
    if net._options["trafo_loading"] != "current":
        raise GridError("grid: only pandapower's trafo_loading='current' is supported")
    internal = net._ppc["internal"]
    if internal["Ybus"].shape[0] != net._ppc["bus"].shape[0] or \
            internal["branch"].shape[0] != net._ppc["branch"].shape[0]:
        raise GridError(f"grid {code}: out-of-service or isolated buses or branches are not "
                        "supported")
    lookup = net._pd2ppc_lookups["bus"]
    base = float(internal["baseMVA"])
    sgen = net.sgen
    on = sgen.in_service.to_numpy(dtype=bool) * sgen.scaling.fillna(1.0).to_numpy()
    loading_f, loading_t = _loading_factors(net, internal, base)
    data = GridData(
        code=code, case=case, load_model=load_model, base_mva=base,
        ybus=sp.csr_matrix(internal["Ybus"]), yf=sp.csr_matrix(internal["Yf"]),
        yt=sp.csr_matrix(internal["Yt"]), v_init=np.asarray(internal["V"], complex).copy(),
        ref=_ints(internal["ref"]), pv=_ints(internal["pv"]), pq=_ints(internal["pq"]),
        s_fixed_pu=_load_injection(net, lookup, internal["Ybus"].shape[0], base),
        sgen_names=tuple(str(n) for n in sgen.name),
        sgen_bus=_ints(lookup[sgen.bus.to_numpy()]),
        sgen_p_mw=sgen.p_mw.to_numpy(dtype=float) * on,
        sgen_q_mvar=sgen.q_mvar.to_numpy(dtype=float) * on,
        report_bus=_ints(lookup[net.bus.index[net.bus.in_service.to_numpy(dtype=bool)]]),
        branch_from=_ints(internal["branch"][:, F_BUS].real),
        branch_to=_ints(internal["branch"][:, T_BUS].real),
        line_rows=_rows(net, "line"), trafo_rows=_rows(net, "trafo"),
        loading_f=loading_f, loading_t=loading_t)
    if data.ref.size != 1:
        raise GridError(f"grid {code}: exactly one slack (external grid) is supported")
    _check_against_runpp(data, net)
    return data


def _check_supported(net) -> None:
    for element in UNSUPPORTED:
        table = net.get(element)
        if table is not None and len(table) and bool(table.in_service.any()):
            raise GridError(f"grid: element type {element!r} is not supported by the solver")
    if int(net.ext_grid.in_service.sum()) != 1:
        raise GridError("grid: exactly one external grid (the slack) is supported")


def _ints(values) -> np.ndarray:
    return np.asarray(values, dtype=np.int64).ravel()


def _rows(net, element: str) -> tuple[int, int]:
    rows = net._pd2ppc_lookups["branch"].get(element)
    return (0, 0) if rows is None else (int(rows[0]), int(rows[1]))


def _load_injection(net, lookup, n_bus: int, base: float) -> np.ndarray:
    """Constant-power loads as (negative) injections per internal bus, p.u."""
    loads = net.load[net.load.in_service.to_numpy(dtype=bool)]
    scaling = loads.scaling.fillna(1.0).to_numpy()
    s = np.zeros(n_bus, complex)
    np.add.at(s, lookup[loads.bus.to_numpy()],
              -(loads.p_mw.to_numpy() + 1j * loads.q_mvar.to_numpy()) * scaling / base)
    return s


def _loading_factors(net, internal, base: float) -> tuple[np.ndarray, np.ndarray]:
    """% loading per p.u. current at each branch end, as pandapower's results define it.

    A p.u. current at a bus of base voltage ``V_b`` kV is ``base / (√3 V_b)`` kA. Lines:
    ``i_ka / (max_i_ka · df · parallel)``; transformers (``trafo_loading="current"``):
    ``i_ka · vn_kv · √3 / sn_mva / (parallel · df)`` at the HV and the LV end.
    """
    from pandapower.pypower.idx_brch import F_BUS, T_BUS
    from pandapower.pypower.idx_bus import BASE_KV

    branch, bus = internal["branch"], internal["bus"]
    kv_f = bus[branch[:, F_BUS].real.astype(np.int64), BASE_KV].real
    kv_t = bus[branch[:, T_BUS].real.astype(np.int64), BASE_KV].real
    ka_f, ka_t = base / (math.sqrt(3) * kv_f), base / (math.sqrt(3) * kv_t)
    f = np.zeros(len(branch))
    t = np.zeros(len(branch))
    a, b = _rows(net, "line")
    line = net.line
    i_max = (line.max_i_ka * line.df * line.parallel).to_numpy(dtype=float)
    f[a:b] = ka_f[a:b] / i_max * 100
    t[a:b] = ka_t[a:b] / i_max * 100
    a, b = _rows(net, "trafo")
    trafo = net.trafo
    rating = (trafo.sn_mva * trafo.parallel * trafo.df).to_numpy(dtype=float)
    f[a:b] = ka_f[a:b] * trafo.vn_hv_kv.to_numpy(dtype=float) * math.sqrt(3) / rating * 100
    t[a:b] = ka_t[a:b] * trafo.vn_lv_kv.to_numpy(dtype=float) * math.sqrt(3) / rating * 100
    return f, t


def _check_against_runpp(data: GridData, net) -> None:
    """Solve ``runpp``'s operating point again with the solver; raise if anything differs."""
    sample = GridSolver(data, actuator_sgens=()).solve(np.zeros(0))
    ext = net.res_ext_grid.loc[net.ext_grid.index[net.ext_grid.in_service]].iloc[0]
    pairs = [("p_w", sample.p_ip_w, -ext.p_mw * 1e6), ("p_w", sample.q_ip_var, -ext.q_mvar * 1e6),
             ("vm_pu", sample.vm_min_pu, net.res_bus.vm_pu.min()),
             ("vm_pu", sample.vm_max_pu, net.res_bus.vm_pu.max())]
    if len(net.line):
        pairs.append(("loading_pct", sample.line_loading_max_pct,
                      net.res_line.loading_percent.max()))
    if len(net.trafo):
        pairs.append(("loading_pct", sample.trafo_loading_max_pct,
                      net.res_trafo.loading_percent.max()))
    bad = [(kind, a, b) for kind, a, b in pairs
           if not (sample.converged and abs(a - b) <= _CHECK_TOL[kind])]
    if bad:
        raise RuntimeError(f"grid {data.code}: the solver does not reproduce runpp: {bad}")
