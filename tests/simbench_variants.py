"""Every SimBench MV and HV code through the grid model, checked against pandapower's runpp.

Shared by ``test_grid_variants*.py`` (split in three files so that xdist's ``loadfile`` runs
them on different workers: reading one SimBench code costs ~3 s).
"""

from __future__ import annotations

import numpy as np
import pandapower as pp
import pytest

from adnmesh.grid import GridSolver
from adnmesh.grid.from_net import build_grid_data
from adnmesh.grid.simbench_net import grid_net


def simbench_codes(level: str, scenarios: tuple[str, ...], one_switch_variant: bool = False
                   ) -> list[str]:
    """The package's codes of one voltage level (``"MV"``, ``"HV"``; not the combined grids)
    whose scenario (``0``, ``1``, ``2``) is in ``scenarios``, both switch variants -- or, with
    ``one_switch_variant``, one per scenario: ``sw`` of scenario 1, ``no_sw`` of the others.
    The two variants of a code are one grid's data, ``no_sw`` made by simbench's
    ``generate_no_sw_variant``; scenario 0 checks both for every grid (``test_grid_variants``),
    so the scenarios' files check each once (half the ~3-8 s reads)."""
    import simbench

    codes = [c for c in simbench.collect_all_simbench_codes()
             if c.startswith(f"1-{level}-") and c.split("--")[1].split("-")[0] in scenarios]
    if not one_switch_variant:
        return codes
    return [c for c in codes if c.endswith("-no_sw") != c.split("--")[1].startswith("1-")]


def upper_grid_buses(net) -> set:
    """The external grids' buses and the buses joined to them by closed bus-bus switches
    (pandapower's topology): the slack's node, whose voltage is the upper grid's."""
    import networkx as nx
    from pandapower.topology import create_nxgraph

    graph = create_nxgraph(net, include_lines=False, include_trafos=False,
                           include_impedances=False, include_trafo3ws=False)
    ext = net.ext_grid.bus[net.ext_grid.in_service.astype(bool)].astype(int)
    return set().union(*(nx.node_connected_component(graph, b) for b in ext))


def runpp_figures(net) -> tuple:
    """P_IP, Q_IP (every external grid, sign turned), voltage extremes but the slack's node,
    largest line and transformer loading, from a fresh ``runpp`` of ``net``."""
    pp.runpp(net)
    adn = net.res_bus.vm_pu[~net.bus.index.isin(upper_grid_buses(net))
                            & net.bus.in_service.astype(bool)]
    return (-net.res_ext_grid.p_mw.sum() * 1e6, -net.res_ext_grid.q_mvar.sum() * 1e6,
            adn.min(), adn.max(), net.res_line.loading_percent.max(),
            net.res_trafo.loading_percent.max())


def check_code(code: str, operating_points: bool) -> None:
    """Build ``code`` at lW (the build itself checks the model against runpp); with
    ``operating_points``, also move its five largest static generators to three other
    powers each and compare a solve with runpp's."""
    net = grid_net(code, "lW")
    data = build_grid_data(net, code, "lW", "impedance")
    if not operating_points:
        return
    sgen = net.sgen[net.sgen.in_service.astype(bool)]
    names = tuple(sgen.sort_values("p_mw", ascending=False).name.iloc[:5])
    solver = GridSolver(data, names)
    rows = net.sgen.index[net.sgen.name.isin(names)]
    p0 = net.sgen.loc[rows].set_index("name").p_mw.loc[list(names)].to_numpy() * 1e6
    for factor in (np.array([0.0, 0.5, 1.0, 1.5, 0.2]), np.full(5, 0.1), np.full(5, 1.8)):
        p = p0 * factor[:len(p0)]
        for name, p_w in zip(names, p):
            net.sgen.loc[net.sgen.name == name, "p_mw"] = p_w / 1e6
        sample = solver.solve(p)
        want = runpp_figures(net)
        assert sample.converged
        assert abs(sample.p_ip_w - want[0]) <= 1.0 and abs(sample.q_ip_var - want[1]) <= 1.0
        assert (sample.vm_min_pu, sample.vm_max_pu) == pytest.approx(want[2:4], abs=1e-7)
        assert (sample.line_loading_max_pct, sample.trafo_loading_max_pct) == pytest.approx(
            want[4:], abs=1e-5)
