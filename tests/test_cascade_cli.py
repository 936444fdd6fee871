"""``adnmesh cascade``: an upper table over two small ADNs, certified as a cascade, its
lower-switch sweep, and the hierarchy file's errors."""
import contextlib
import csv
import io
from pathlib import Path

import control as ct
import numpy as np
import pytest

from adnmesh.cascade.control_models import cascade_models
from adnmesh.cascade.nested_loop import upper_loop
from adnmesh.cascade.upper_table import cascade_of
from adnmesh.cli import main
from adnmesh.commands.cascade import hierarchy_sites
from adnmesh.config import load_config, load_hierarchy
from adnmesh.loopmodel.step_figures import step_figures
from adnmesh.tuning.table import default_table_path, load_table

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"


def hierarchy_file(folder: Path, body: str) -> Path:
    (folder / "chp.yaml").write_text(CHP_ADN)
    path = folder / "h.yaml"
    path.write_text(body)
    return path


GOOD = f"""name: hv-two
t_meas_s: 0.2
constraints: {{disk_margin_min: 1.5, overshoot_max_pct: 1.0}}
adns:
  - {{id: wind, config: {EXAMPLES / 'two-wt.yaml'}, t_com_s: 0.2}}
  - {{id: chp, config: chp.yaml, t_com_s: 0.3}}
"""

#: an ADN of one WT and two CHPs of 1 MW: its closed loop is slow with a long tail, which its
#: equivalent first-order model misses (the upper entries need a back-off on the cascade)
CHP_ADN = f"""extends: {EXAMPLES / 'wt-chp.yaml'}
ders:
  - {{id: SGen1, type: WT,  p_inst_w: 2.0e+6, t_delay_s: 0.01, t_rise_s: 0.515, sgen: "MV1.101 SGen 1"}}
  - {{id: SGen5, type: CHP, p_inst_w: 1.0e+6, t_delay_s: 1.0,  t_rise_s: 24.57, sgen: "MV1.101 MV SGen 5"}}
  - {{id: SGen6, type: CHP, p_inst_w: 1.0e+6, t_delay_s: 1.0,  t_rise_s: 24.57, sgen: "MV1.101 MV SGen 6"}}
scenario: {{duration_s: 100, availability: []}}
"""


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """One run of the command with the sweep, shared by the tests below."""
    folder = tmp_path_factory.mktemp("cascade")
    path = hierarchy_file(folder, GOOD)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["cascade", str(path), "--out", str(folder / "out"), "--switches"]) == 0
    return path, folder / "out", printed.getvalue()


def sites_of(path: Path) -> dict:
    """The sites as the command builds them."""
    return {s.id: s for s in hierarchy_sites(load_hierarchy(path))}


def test_every_upper_entry_is_certified_on_the_exact_cascade(written) -> None:
    path, out, _ = written
    upper = load_config(out / "hv-two.upper.yaml")
    assert (out / "hv-two.cascade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [d.id for d in upper.ders] == ["wind", "chp"]
    table = load_table(default_table_path(upper), upper)
    assert len(table.entries) == 3
    sites = sites_of(path)
    for entry in table.entries.values():
        assert entry.feasible and entry.figures["certified_on"] == "cascade"
        cascade = cascade_of(sites, entry, 0.2)
        # the verdict of the independent model: python-control with Padé delays
        loop, closed = cascade_models(cascade, entry.kp, entry.ki, order=12)
        assert np.max(closed.poles().real) < 0
        ours = upper_loop(cascade, entry.kp, entry.ki)
        near = np.geomspace(ours.disk_omega / 1.5, ours.disk_omega * 1.5, 2001)
        dm, _, _ = ct.disk_margins(loop, near)
        assert float(dm) == pytest.approx(entry.figures["disk_margin"], rel=1e-5)
        assert float(dm) >= 1.5 * (1 - 1e-6)
        t = np.arange(0.0, 8 * entry.figures["settling_time_s"], 0.01)
        y = np.squeeze(ct.step_response(closed, T=t).outputs)
        assert step_figures(t, y).overshoot_pct < 1.0 + 0.02
    rows = list(csv.DictReader((out / "hv-two.cascade.csv").open()))
    assert sorted(r["adns"] for r in rows) == ["chp", "wind", "wind chp"]
    assert all(float(r["back_off"]) <= 1.0 for r in rows)
    # the equivalent models were optimistic for the entries with the CHP ADN
    factor = {r["adns"]: float(r["back_off"]) for r in rows}
    assert factor["wind"] == 1.0 and factor["chp"] < 0.5 and factor["wind chp"] < 1.0
    assert all(float(r["equivalent_disk_margin"]) >= 1.5 for r in rows)
    # where a back-off was needed the entry is tuned on the cascade: never slower than backed off
    for r in rows:
        assert float(r["rise_time_s"]) <= float(r["backed_off_rise_time_s"])
    chp = next(r for r in rows if r["adns"] == "chp")
    assert float(chp["rise_time_s"]) < 0.9 * float(chp["backed_off_rise_time_s"])
    assert table.lookup(["chp"]).figures["refined_on_cascade"] is True


def test_the_switch_sweep_covers_every_lower_entry(written) -> None:
    _, out, printed = written
    rows = list(csv.DictReader((out / "hv-two.switches.csv").open()))
    assert sorted((r["adn"], r["ders"]) for r in rows) == sorted(
        [("wind", "SGen1"), ("wind", "SGen2"), ("wind", "SGen1 SGen2")]
        + [("chp", " ".join(s)) for s in (("SGen1",), ("SGen5",), ("SGen6",), ("SGen1", "SGen5"),
                                          ("SGen1", "SGen6"), ("SGen5", "SGen6"),
                                          ("SGen1", "SGen5", "SGen6"))])
    for r in rows:
        assert r["back_off"] and 0 < float(r["back_off"]) <= 1.0
        assert float(r["disk_margin"]) >= 1.5 and float(r["overshoot_pct"]) < 1.0
    # at its own full entry an ADN gives back the upper entry's certificate, unchanged
    full = [r for r in rows if r["ders"] in ("SGen1 SGen2", "SGen1 SGen5 SGen6")]
    assert [float(r["back_off"]) for r in full] == [1.0, 1.0]
    assert full[0]["disk_margin"] == full[1]["disk_margin"]
    # losing a plant changes the upper loop enough to need the rule somewhere
    backed = [r for r in rows if float(r["back_off"]) < 1.0]
    assert backed
    for adn in ("wind", "chp"):
        mine = [r for r in rows if r["adn"] == adn]
        held = sum(float(r["back_off"]) == 1.0 for r in mine)
        assert (f"switches of {adn}: {len(mine)} entries; the upper gains hold for {held}, "
                f"back off for {len(mine) - held}") in printed


@pytest.mark.parametrize("body, message", [
    ("name: h\nt_meas_s: 0.2\nadns: []\n", "adns: "),
    (GOOD.replace("id: chp", "id: wind"), "duplicate ADN id 'wind'"),
    (GOOD.replace("t_meas_s", "t_mes_s"), "did you mean 't_meas_s'"),
    (GOOD.replace("two-wt.yaml", "missing.yaml"), "adns wind: "),
    (GOOD.replace("t_com_s: 0.3", "t_com_s: -1"), "adns[1].t_com_s"),
    (GOOD.replace("t_com_s: 0.3", "t_com_s: 0.3004"),
     "adns[1].t_com_s: must be a whole number of milliseconds"),
    (GOOD.replace("t_meas_s: 0.2", "t_meas_s: 0"), "t_meas_s: "),
])
def test_a_bad_hierarchy_file_is_one_line_and_exit_2(tmp_path, capsys, body, message) -> None:
    path = hierarchy_file(tmp_path, body)
    assert main(["cascade", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("adnmesh: error: ")]
    assert len(errors) == 1 and message in errors[0] and "Traceback" not in err


def test_an_adn_whose_delays_share_no_millisecond_is_one_line(tmp_path, capsys) -> None:
    path = hierarchy_file(tmp_path, GOOD)
    (tmp_path / "chp.yaml").write_text(CHP_ADN.replace("t_delay_s: 0.01", "t_delay_s: 0.01037"))
    assert main(["cascade", str(path), "--out", str(tmp_path / "out")]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines()
              if line.startswith("adnmesh: error: ")]
    assert len(errors) == 1 and "adns chp: the cascade's delays share no unit" in errors[0]


@pytest.mark.parametrize("argv, said", [
    (["check", str(EXAMPLES / "hierarchy" / "hv.yaml")],
     "a hierarchy file (it names adns), not an ADN's config: 'adnmesh cascade FILE' tunes and "
     "certifies it, 'adnmesh up FILE' runs it"),
    (["cascade", str(EXAMPLES.parent / "simbench.yaml")],
     "an ADN's config (it names ders), not a hierarchy file"),
])
def test_a_hierarchy_file_and_a_config_given_for_each_other_are_said_as_such(argv, said,
                                                                            capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0]
