"""The copy of a pandapower net that lightsim2grid's converter reads as ``runpp`` solves it.

``runpp`` does a few things to a net before it solves it that lightsim2grid's converter
(``lightsim2grid.network.init_from_pandapower``) does not. :func:`model_net` does them on a copy,
with pandapower's own tools where it has them, so that the converted model solves the same
equations; :func:`adnmesh.grid.from_net.build_grid_data` then checks that it does.

- **Open line and transformer switches.** ``runpp`` keeps the branch and puts its open end on an
  auxiliary bus (a line stays energised from its other end, with its charging current); the copy
  does the same. Closed ones are dropped (the converter ignores switches, which would close them
  all — on 1-MV-rural the six open loop lines).
- **Bus-bus switches** (the ``-sw`` SimBench codes: bus couplers, circuit breakers and
  disconnectors of the substations). ``runpp`` merges the buses of every closed one into one node;
  the copy fuses them (``pandapower.toolbox.fuse_buses``) into the lowest-numbered bus of each
  group and drops the others. Branches between two fused buses stay, their charging included, as
  in ``runpp``. Open bus-bus switches are dropped: their buses stay apart.
- **Transformer taps.** pandapower 3 applies a tap only where ``tap_changer_type`` says which kind
  of tap changer it is (``"Ratio"``, ``"Symmetrical"``); where it is empty (SimBench's
  1-MV-urban: both transformers at ``tap_pos`` -1, no type) ``runpp`` ignores the position. The
  copy puts such taps at neutral, and moves every tap's neutral to 0 (``tap_pos - tap_neutral``,
  the converter's convention; the ratio depends only on the difference).
- **Islands.** Buses no external grid supplies (a spare busbar, a feeder cut off by open
  switches) get no power flow in ``runpp`` (NaN results); the copy puts them and what is on them
  out of service (``pandapower.toolbox.set_isolated_areas_out_of_service``). A generator there
  has no power to give.
- **Scaling of storages** is folded into their p and q (the converter ignores it).
- **Column types.** SimBench leaves the generators' optional limit columns as objects, which the
  converter cannot read; they are cast to floats (their NaNs become 0, unused by the power flow).
"""

from __future__ import annotations

import copy

import numpy as np

__all__ = ["model_net", "coupled_buses", "IGNORED_TAP_TYPES"]

IGNORED_TAP_TYPES = (None, "", "None")
_FLOAT_COLUMNS = {"sgen": ("min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar"),
                  "load": ("min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar"),
                  "storage": ("min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar")}


def model_net(net):
    """The copy of ``net`` the converter reads (see the module docstring) and the bus map.

    Returns
    -------
    (pandapowerNet, dict)
        The copy, and for each bus of ``net`` the bus of the copy it is (itself unless fused).
    """
    out = copy.deepcopy(net)
    _open_branch_ends(out)
    bus_map = coupled_buses(out)
    _fuse(out, bus_map)
    out.switch = out.switch.iloc[0:0]
    out.ext_grid = out.ext_grid[out.ext_grid.in_service.astype(bool)]
    _islands_out_of_service(out)
    renumbered = _continuous_bus_index(out)
    _taps_as_runpp_reads_them(out)
    _storage_scaling(out)
    for table, columns in _FLOAT_COLUMNS.items():
        for column in columns:
            if table in out and column in out[table]:
                out[table][column] = out[table][column].astype(float)
    return out, {int(b): renumbered[bus_map[int(b)]] for b in net.bus.index}


def coupled_buses(net) -> dict:
    """Each bus of ``net`` to the lowest-numbered bus it is joined to by closed bus-bus switches
    (itself if none), by pandapower's topology (a graph of those switches only)."""
    from pandapower.topology import connected_components, create_nxgraph

    graph = create_nxgraph(net, respect_switches=True, include_lines=False,
                           include_impedances=False, include_dclines=False,
                           include_trafos=False, include_trafo3ws=False, include_tcsc=False,
                           include_vsc=False, include_line_dc=False,
                           include_out_of_service=True)
    out = {int(b): int(b) for b in net.bus.index}
    for group in connected_components(graph):
        keep = min(int(b) for b in group)
        out.update((int(b), keep) for b in group)
    return out


def _open_branch_ends(net) -> None:
    """Each open line or transformer switch: the branch's end moves to a new auxiliary bus."""
    import pandapower as pp

    switches = net.switch
    is_open = ~switches.closed.astype(bool) & switches.et.isin(("l", "t"))
    for _, sw in switches[is_open].iterrows():
        table, ends = ("line", ("from_bus", "to_bus")) if sw.et == "l" else \
            ("trafo", ("hv_bus", "lv_bus"))
        branch = int(sw.element)
        aux = pp.create_bus(net, net.bus.vn_kv.at[sw.bus], name=f"aux of open switch {sw.name}")
        for end in ends:
            if net[table].at[branch, end] == sw.bus:
                net[table].at[branch, end] = aux
                break


def _fuse(net, bus_map: dict) -> None:
    """Fuse each group of coupled buses into its lowest-numbered bus, in place."""
    from pandapower.toolbox import drop_buses, fuse_buses

    groups: dict = {}
    for bus, keep in bus_map.items():
        if bus != keep:
            groups.setdefault(keep, []).append(bus)
    net.switch = net.switch[net.switch.et != "b"]
    for keep, others in groups.items():
        fuse_buses(net, keep, others, drop=False)       # branches between them stay (runpp too)
    dropped = [b for others in groups.values() for b in others]
    if dropped:
        drop_buses(net, dropped, drop_elements=False)


def _continuous_bus_index(net) -> dict:
    """Number the buses 0, 1, ... in their sorted order (the converter's bus order), in place;
    the old number of each to its new one."""
    from pandapower.toolbox import create_continuous_bus_index

    return {int(old): int(new) for old, new in create_continuous_bus_index(net, start=0).items()}


def _islands_out_of_service(net) -> None:
    """Buses no external grid supplies, and what is on them, out of service (in place): runpp
    leaves them out of its power flow (NaN results), the converter would keep them."""
    import logging

    from pandapower.toolbox import set_isolated_areas_out_of_service

    logger = logging.getLogger("pandapower.toolbox")
    level = logger.level
    logger.setLevel(logging.WARNING)             # it says how many at INFO
    try:
        set_isolated_areas_out_of_service(net, respect_switches=True)
    finally:
        logger.setLevel(level)


def _taps_as_runpp_reads_them(net) -> None:
    """Taps pandapower ignores at neutral; every tap's neutral moved to 0 (in place)."""
    trafo = net.trafo
    if not len(trafo):
        return
    kind = trafo.tap_changer_type if "tap_changer_type" in trafo else \
        np.full(len(trafo), None, dtype=object)
    ignored = np.array([k in IGNORED_TAP_TYPES or k != k for k in kind], dtype=bool)
    neutral = trafo.tap_neutral.astype(float).fillna(0.0).to_numpy()
    pos = trafo.tap_pos.astype(float).to_numpy()
    pos = np.where(ignored | np.isnan(pos), neutral, pos)
    trafo["tap_pos"] = pos - neutral
    trafo["tap_neutral"] = 0.0


def _storage_scaling(net) -> None:
    storage = net.get("storage")
    if storage is None or not len(storage) or "scaling" not in storage:
        return
    scaling = storage.scaling.astype(float).fillna(1.0)
    storage["p_mw"] = storage.p_mw.astype(float) * scaling
    storage["q_mvar"] = storage.q_mvar.astype(float) * scaling
    storage["scaling"] = 1.0
