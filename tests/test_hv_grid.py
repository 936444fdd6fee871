"""An HV grid between a hierarchy's ADNs and the level above: the net with the ADNs attached and
the hierarchy file's checks (the two-stage power flow against ``runpp`` of the combined HV+MV
net is in ``test_hierarchy_run``, on the net its shared run wrote)."""
from pathlib import Path

import pandapower as pp
import pytest

from adnmesh.cli import main
from adnmesh.errors import GridError
from adnmesh.grid.hv_attach import (OPERATING_POINT, Attachment, attach_adns, hv_base,
                                    replaced_at, write_net)

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def small_hv_net():
    """Two 110 kV buses and a line; at bus "B": an MV stand-in (load and sgen, SimBench's
    ``mv_`` profile and type) and a wind farm."""
    net = pp.create_empty_network()
    a = pp.create_bus(net, 110.0, name="A")
    b = pp.create_bus(net, 110.0, name="B")
    pp.create_ext_grid(net, a, vm_pu=1.02)
    pp.create_line(net, a, b, 10.0, "149-AL1/24-ST1A 110.0")
    load = pp.create_load(net, b, p_mw=10.0, q_mvar=3.0, name="stand-in load")
    net.load.loc[load, "profile"] = "mv_rural"
    pp.create_sgen(net, b, p_mw=8.0, name="stand-in sgen", type="mv_rural")
    pp.create_sgen(net, b, p_mw=20.0, name="wind farm", type="Wind")
    pp.create_bus(net, 110.0, name="off", in_service=False)
    pp.create_bus(net, 110.0, name="island")          # no line to it
    return net


def test_an_adn_takes_the_place_of_its_buses_mv_stand_ins(tmp_path) -> None:
    path = tmp_path / "hv.json"
    pp.to_json(small_hv_net(), str(path))
    net = hv_base("pandapower", str(path), None)
    replaced = attach_adns(net, [Attachment("adn1", "B", 5e6, 2e6, 0.4e6)])
    assert sorted(replaced["adn1"]) == ["stand-in load", "stand-in sgen"]
    assert not net.load.in_service.any()
    adn = net.sgen[net.sgen.name == "adn1"].iloc[0]
    rest = net.sgen[net.sgen.name == "adn1" + OPERATING_POINT].iloc[0]
    assert (adn.p_mw, adn.sn_mva, rest.p_mw, rest.q_mvar) == (5.0, 5.0, 2.0, 0.4)
    assert bool(net.sgen.in_service[net.sgen.name == "wind farm"].iloc[0])
    # named: only those; an element not at the bus is refused in one line
    net2 = hv_base("pandapower", str(path), None)
    replaced2 = attach_adns(net2, [Attachment("adn1", "B", 5e6, 0.0, 0.0, ("stand-in load",))])
    assert replaced2["adn1"] == ["stand-in load"]
    assert bool(net2.sgen.in_service[net2.sgen.name == "stand-in sgen"].iloc[0])
    with pytest.raises(GridError, match="'wind' is no load or static generator at bus 'B'"):
        replaced_at(small_hv_net(), 1, ("wind",))
    with pytest.raises(GridError, match="no bus named 'C'"):
        attach_adns(small_hv_net(), [Attachment("adn1", "C", 5e6, 0.0, 0.0)])
    write_net(net, tmp_path / "out.json")       # and it reads back as the net it was
    back = pp.from_json(str(tmp_path / "out.json"))
    assert list(back.sgen.name) == list(net.sgen.name)


@pytest.mark.parametrize("adn, extra, said", [
    ("hv_bus: B", "", "hv_bus: needs hv_grid"),
    ("", "hv_grid: {simbench_code: 1-HV-mixed--0-sw}", "hv_bus: is needed with hv_grid"),
    ("hv_bus: B", "hv_grid: {study_case: lW}", "give the HV net as simbench_code or as"),
    ("hv_bus: C", "hv_grid: {pandapower_net: small.json}", "h.yaml: hv_grid: no bus named 'C'"),
    ("hv_bus: B, replaces: [wind]", "hv_grid: {pandapower_net: small.json}",
     "'wind' is no load or static generator at bus 'B'"),
    ("hv_bus: B", "hv_grid: {pandapower_net: small.json, study_case: lW}",
     "hv_grid: unknown study case 'lW' (this grid has: none)"),
    ("hv_bus: 'off'", "hv_grid: {pandapower_net: small.json}", "bus 'off' is out of service"),
    ("hv_bus: island", "hv_grid: {pandapower_net: small.json}",
     "bus 'island' is not connected to an external grid"),
])
def test_hierarchy_files_with_a_bad_hv_grid_are_one_line_errors(tmp_path, capsys, adn, extra,
                                                                said) -> None:
    """Refused in one line, before any tuning (the ADN has no table: it would be tuned)."""
    pp.to_json(small_hv_net(), str(tmp_path / "small.json"))
    config = CONFIGS / "examples" / "wt-chp.yaml"
    (tmp_path / "h.yaml").write_text(
        f"name: hv\nt_meas_s: 0.2\nadns:\n  - {{id: a, config: {config}, t_com_s: 0.2"
        f"{', ' + adn if adn else ''}}}\nscenario: {{duration_s: 10}}\n{extra}\n")
    assert main(["cascade", str(tmp_path / "h.yaml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert said in err[-1] and "Traceback" not in "".join(err)
    assert "tuning it now" not in "".join(err)
