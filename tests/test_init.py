"""``adnmesh init``: a config from a SimBench code (issue 32): the rules, the default dynamics,
the scenario sized to the controllable range, the kept grid configs equal to a fresh init, and
a generated file that passes check and up as written."""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path

import pytest

from adnmesh.adn.dynamics import DEFAULT_DYNAMICS, der_type_of
from adnmesh.adn.selection import select_actuators
from adnmesh.adn.survey import Generator
from adnmesh.adn.template import nice_floor, ranges_w, scenario_template, schedule_w
from adnmesh.cli import main
from adnmesh.config import DER_TYPES, load_config
from adnmesh.dermodels import default_params, set_point, infeed_at, steady_state
from adnmesh.errors import UsageError
from adnmesh.control.operating_point import available_power_w, initial_p_ip_w

GRIDS = Path(__file__).resolve().parents[1] / "configs" / "grids"


def _gen(name, kind, p_kw, case_kw=None, kv=20.0, profile=""):
    return Generator(name, 1, kv, kind, profile, p_kw * 1e3,
                     (p_kw if case_kw is None else case_kw) * 1e3)


NET = [_gen("W1", "Wind_MV", 2000), _gen("B1", "Biomass_MV", 300), _gen("P1", "PV_MV", 200, 0),
       _gen("H1", "Hydro_MV", 400), _gen("L1", "lv_RES", 150, 120, profile="lv_rural1"),
       _gen("L2", "lv_RES", 50, 40, kv=0.4), _gen("X1", "something", 80)]


def test_der_types_of_simbench_and_pandapower_generator_types() -> None:
    assert [der_type_of(k, p) for k, p in [("Wind_MV", "WP4"), ("Biomass_MV", "BM1"),
                                           ("PV_MV", "PV3"), ("Hydro_MV", "Hydro2"),
                                           ("lv_RES", "lv_urban6"), ("wye", "WP7"),
                                           ("", ""), ("CHP", "")]] == \
        ["WT", "CHP", "PV", "HYDRO", "PV", "WT", "GEN", "CHP"]
    assert set(DEFAULT_DYNAMICS) == set(DER_TYPES)
    assert DEFAULT_DYNAMICS["WT"][:2] == (0.01, 0.515) and DEFAULT_DYNAMICS["CHP"][:2] == \
        (1.0, 24.57) and DEFAULT_DYNAMICS["PV"][:2] == (0.01, 0.1)     # the paper's


@pytest.mark.parametrize("der_type", ["HYDRO", "GEN"])
def test_the_new_types_have_a_detailed_model_with_the_default_rise(der_type) -> None:
    delay, rise, _ = DEFAULT_DYNAMICS[der_type]
    params = default_params(der_type, 1e6, delay, rise)
    state = steady_state(params, 5e5)
    set_point(params, state, 0, 6e5)
    t = [k * 0.01 for k in range(int((delay + 3 * rise) / 0.01))]
    p = [infeed_at(params, state, int(round(x * 1e9))) for x in t]
    t10 = next(x for x, v in zip(t, p) if v >= 5.1e5)
    t90 = next(x for x, v in zip(t, p) if v >= 5.9e5)
    assert t90 - t10 == pytest.approx(rise, rel=0.02)
    assert p[-1] == pytest.approx(6e5, rel=1e-3)


def test_the_rules_pick_plants_types_sizes_and_names() -> None:
    mv = select_actuators(NET)
    assert [a.generator.name for a in mv.actuators] == ["W1", "B1", "H1", "X1"]
    assert [a.der_type for a in mv.actuators] == ["WT", "CHP", "HYDRO", "GEN"]
    assert [g.name for g in mv.idle] == ["P1"]          # produces nothing at the study case
    every = select_actuators(NET, "all", types=["PV", "WT"], min_size_w=100e3)
    assert [a.generator.name for a in every.actuators] == ["W1", "L1"]
    named = select_actuators(NET, names=["L2", "H1"])
    assert [a.generator.name for a in named.actuators] == ["H1", "L2"]
    with pytest.raises(UsageError, match=r"no static generator named 'H 1'.*closest: 'H1'"):
        select_actuators(NET, names=["H 1"])
    with pytest.raises(UsageError, match=r"no static generator matches the rules \(level mv, "
                                         r"types PV\) of 7 in the net \(1 match but produce"):
        select_actuators(NET, types=["PV"])


def test_schedules_ranges_and_the_scenario_fit_what_the_actuators_deliver() -> None:
    assert [nice_floor(x) for x in (0.99, 1.0, 2.4, 4.99, 5.0, 7.3e5)] == \
        [0.5, 1.0, 2.0, 2.0, 5.0, 5e5]
    assert schedule_w(1_000_001) == 500_000 or schedule_w(1_000_001) == 500_001
    ders = [("WT1", "WT", 2e6, 2e6, 1e6), ("WT2", "WT", 2e6, 1.6e6, 8e5),
            ("CHP1", "CHP", 5e5, 5e5, 2.5e5)]
    assert ranges_w((c, s) for *_, c, s in ders) == (2.05e6, 2.05e6)
    planned = scenario_template(ders)
    assert planned.steps == ((20.0, 5e5), (120.0, -5e5), (240.0, 1e5), (340.0, -1e5))
    assert planned.unavailable == ((220.0, ("WT1", "WT2")),) and planned.dropped_type == "WT"
    assert planned.duration_s == 440.0
    alone = scenario_template([("H1", "HYDRO", 1e6, 1e6, 5e5)])
    assert alone.steps == ((20.0, 2e5), (120.0, -2e5)) and not alone.unavailable


def _header_command(path: Path) -> list[str]:
    first = path.read_text().splitlines()[1]          # after the schema line
    assert first.startswith("# Written by: adnmesh init ")
    return shlex.split(first[len("# Written by: adnmesh "):])


@pytest.mark.parametrize("grid", ["1-MV-rural", "1-MV-semiurb", "1-MV-urban", "1-MV-comm"])
def test_the_kept_grid_configs_are_what_init_writes_today(grid, tmp_path, capsys) -> None:
    kept = GRIDS / f"{grid}.yaml"
    argv = _header_command(kept)
    (tmp_path / "grids").mkdir()
    (tmp_path / "config.schema.json").write_text("{}")   # as configs/ has it
    out = tmp_path / "grids" / kept.name
    assert argv[-2:] == ["-o", kept.name]
    assert main([*argv[:-1], str(out)]) == 0
    assert out.read_text() == kept.read_text(), (
        f"{kept} is not what init writes now; regenerate it: adnmesh {' '.join(argv)} --force "
        "(from configs/grids)")
    config = load_config(out)
    said = capsys.readouterr().out
    assert f"actuators (" in said and "controllable range at the schedules: +" in said
    steps = config.scenario.p_ref_steps
    assert [s.t_s for s in steps][:2] == [20.0, 120.0] and steps[0].delta_w == -steps[1].delta_w
    assert ("large ADN: " in said) == (len(config.ders) > 16)    # urban: 60 actuators
    for der in config.ders:        # every actuator can move both ways from its schedule
        assert 0 < der.p_sched_w < der.p_inst_w


def test_bad_input_is_one_line(tmp_path, capsys) -> None:
    def error(*argv: str) -> str:
        assert main(["init", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("adnmesh: error: ") and not any("Traceback" in e for e in err)
        return err[-1]

    out = str(tmp_path / "x.yaml")
    assert "'1-MV-nowhere--0-no_sw' is not a SimBench code" in error(
        "--simbench", "1-MV-nowhere--0-no_sw", "-o", out)
    assert "unknown study case 'lw'" in error("--simbench", "1-MV-comm--0-no_sw",
                                              "--study-case", "lw", "-o", out)
    assert "--types: unknown DER type 'BESS'" in error("--simbench", "1-MV-comm--0-no_sw",
                                                       "--types", "BESS", "-o", out)
    assert "--dynamics 'WT=1': expected KEY=DELAY,RISE" in error(
        "--simbench", "1-MV-comm--0-no_sw", "--dynamics", "WT=1", "-o", out)
    assert "no static generator matches the rules" in error(
        "--simbench", "1-MV-comm--0-no_sw", "--min-size-w", "1e9", "-o", out)
    assert not Path(out).exists()
    Path(out).write_text("mine\n")
    assert "exists; --force overwrites it" in error("--simbench", "1-MV-comm--0-no_sw",
                                                    "-o", out)
    assert Path(out).read_text() == "mine\n"


def test_overrides_of_the_dynamics_per_type_and_per_der(tmp_path, capsys) -> None:
    out = tmp_path / "comm.yaml"
    assert main(["init", "--simbench", "1-MV-comm--0-no_sw", "-o", str(out), "--dynamics",
                 "HYDRO=0.8,15", "--der-dynamics", "WT2=0.02,0.7"]) == 0
    config = load_config(out)
    by_id = {d.id: d for d in config.ders}
    assert (by_id["HYDRO1"].t_delay_s, by_id["HYDRO1"].t_rise_s) == (0.8, 15.0)
    assert (by_id["WT2"].t_delay_s, by_id["WT2"].t_rise_s) == (0.02, 0.7)
    assert (by_id["WT1"].t_delay_s, by_id["WT1"].t_rise_s) == (0.01, 0.515)
    assert "--der-dynamics" in out.read_text().splitlines()[0]      # no schema beside it


def _up_summary(config_path: Path, tmp_path: Path):
    """``up`` on a generated config: its summary JSON and the config, every planned step
    executed with its overshoot below the limit and every power flow converged."""
    summary = tmp_path / "summary.json"
    assert main(["up", str(config_path), "--out", str(tmp_path / "run.mcap"),
                 "--summary-json", str(summary)]) == 0
    data = json.loads(summary.read_text())
    config = load_config(config_path)
    assert [s["t_s"] for s in data["steps"]] == [s.t_s for s in config.scenario.p_ref_steps]
    for step in data["steps"]:
        assert step["figures"]["overshoot_pct"] < config.constraints.overshoot_max_pct, step
    assert data["grid"]["not_converged"] == 0
    return data, config


@pytest.mark.slow
def test_a_generated_config_passes_check_and_up_as_written(tmp_path, capsys) -> None:
    """semiurb as init writes it: check, then up (its own tuning, 14 processes, 440 s of sim
    time): every step compensated within the design constraints, the grid reported."""
    out = tmp_path / "semiurb.yaml"
    assert main(["init", "--simbench", "1-MV-semiurb--0-no_sw", "-o", str(out)]) == 0
    assert main(["check", str(out)]) == 0
    capsys.readouterr()
    data, config = _up_summary(out, tmp_path)
    for step in data["steps"]:
        assert step["figures"]["settling_time_s"] is not None, step
    assert data["grid"]["outside_band"] == 0


def test_tune_chooses_the_scenario_subsets_beyond_16_ders_and_says_so(tmp_path, capsys) -> None:
    """A large ADN needs no flag: 17 DERs have 131,071 subsets, more than a table holds."""
    import yaml

    document = yaml.safe_load((GRIDS.parent / "examples" / "two-wt.yaml").read_text())
    first = document["ders"][0]
    document["ders"] = [{**first, "id": f"WT{i}", "sgen": f"sgen {i}"} for i in range(1, 18)]
    document["scenario"]["availability"] = [{"t_s": 20, "available": False, "ders": ["WT17"]}]
    document.pop("grid_model", None)
    path = tmp_path / "seventeen.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    out = tmp_path / "t.json"
    assert main(["tune", str(path), "--out", str(out), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "17 DERs: 2^17 - 1 subsets are more than a table holds" in err
    assert "tuning the 2 subset(s) the scenario meets" in err
    entries = json.loads(out.read_text())["entries"]
    assert sorted(len(e["ders"]) for e in entries) == [16, 17]
    assert main(["tune", str(path), "--out", str(out), "--subsets", "all"]) == 2
    assert "more than a table can hold" in capsys.readouterr().err


# --- a pandapower net file ------------------------------------------------------------------


@pytest.fixture(scope="module")
def cigre_file(tmp_path_factory) -> Path:
    """CIGRE's MV benchmark with its PV and wind DERs, written by pandapower.to_json."""
    import pandapower as pp
    import pandapower.networks as pn

    path = tmp_path_factory.mktemp("net") / "cigre-mv.json"
    pp.to_json(pn.create_cigre_network_mv(with_der="pv_wind"), str(path))
    return path


def test_init_from_a_pandapower_file_checks_and_solves_it(cigre_file, tmp_path, capsys,
                                                          monkeypatch) -> None:
    import pandapower as pp

    from adnmesh.control.operating_point import initial_p_ip_w

    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "site" / "cigre.yaml"
    out.parent.mkdir()
    assert main(["init", "--pandapower", str(cigre_file), "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "pandapower net" in said and "9 (8 PV, 1 WT)" in said
    config = load_config(out)
    assert config.simbench_code is None and config.grid_model.pandapower_net == \
        os.path.relpath(cigre_file, out.parent)           # relative to the config
    assert config.pandapower_net_path() == cigre_file.resolve()
    assert main(["check", str(out)]) == 0
    assert "pandapower net" in capsys.readouterr().out
    # the grid model's P_IP at the schedules is runpp's of the same net with the DERs there
    net = pp.from_json(str(cigre_file))
    for der in config.ders:
        net.sgen.loc[net.sgen.name == der.sgen, "p_mw"] = der.p_sched_w / 1e6
    loads = net.load[net.load.in_service]
    for _, load in loads.iterrows():           # constant impedance at 1 p.u., as the model
        pp.create_shunt(net, int(load.bus), q_mvar=float(load.q_mvar * load.scaling),
                        p_mw=float(load.p_mw * load.scaling))
    net.load.in_service = False
    pp.runpp(net)
    assert initial_p_ip_w(config) == pytest.approx(-net.res_ext_grid.p_mw.sum() * 1e6, abs=1.0)


def test_bad_pandapower_input_is_one_line(cigre_file, tmp_path, capsys, monkeypatch) -> None:
    import pandapower as pp
    import yaml

    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))

    def error(*argv: str) -> str:
        assert main(list(argv)) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("adnmesh: error: ") and not any("Traceback" in e for e in err)
        return err[-1]

    junk = tmp_path / "junk.json"
    junk.write_text('{"not": "a net"}')
    out = str(tmp_path / "x.yaml")
    assert "is not a pandapower net file" in error("init", "--pandapower", str(junk), "-o", out)
    assert "no.json: no such file" in error("init", "--pandapower", str(tmp_path / "no.json"),
                                             "-o", out)
    net = pp.from_json(str(cigre_file))
    net.ext_grid.in_service = False
    island = tmp_path / "island.json"
    pp.to_json(net, str(island))
    assert "no external grid in service" in error("init", "--pandapower", str(island), "-o", out)
    assert "the net has no study cases" in error("init", "--pandapower", str(cigre_file),
                                                 "--study-case", "hL", "-o", out)
    # a config whose sgen is not in the net: check says so, with the closest names
    good = tmp_path / "good.yaml"
    assert main(["init", "--pandapower", str(cigre_file), "-o", str(good)]) == 0
    capsys.readouterr()
    document = yaml.safe_load(good.read_text())
    document["ders"][0]["sgen"] = "PV 99"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(document, sort_keys=False))
    assert "no static generator named 'PV 99'" in error("check", str(bad))
    document["grid_model"]["pandapower_net"] = "junk.json"
    bad.write_text(yaml.safe_dump(document, sort_keys=False))
    assert "is not a pandapower net file" in error("check", str(bad))
    document["simbench_code"] = "1-MV-rural--0-no_sw"
    bad.write_text(yaml.safe_dump(document, sort_keys=False))
    assert "grid_model.pandapower_net: names a net beside simbench_code" in error("check",
                                                                                   str(bad))


@pytest.mark.slow
def test_a_pandapower_config_runs_with_up(cigre_file, tmp_path, capsys) -> None:
    out = tmp_path / "cigre.yaml"
    assert main(["init", "--pandapower", str(cigre_file), "-o", str(out)]) == 0
    data, _ = _up_summary(out, tmp_path)
    assert data["grid"]["samples"] > 0


def test_several_external_grids_of_a_pandapower_net(cigre_file, tmp_path, capsys,
                                                    monkeypatch) -> None:
    """A second feed at the first's voltage: init says P_IP is their sum and check accepts it;
    at another voltage check refuses it in one line (as up would)."""
    import pandapower as pp

    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    net = pp.from_json(str(cigre_file))
    first = net.ext_grid.iloc[0]
    hv = pp.create_bus(net, 110.0, name="second feed")
    pp.create_ext_grid(net, hv, vm_pu=float(first.vm_pu), va_degree=float(first.va_degree))
    pp.create_transformer(net, hv, 12, std_type="25 MVA 110/20 kV", name="second feed")
    two = tmp_path / "two-feeds.json"
    pp.to_json(net, str(two))
    out = tmp_path / "two.yaml"
    assert main(["init", "--pandapower", str(two), "-o", str(out)]) == 0
    text = out.read_text()
    assert "2 external grid(s)" in text and "P_IP is their exchange summed" in text
    assert main(["check", str(out)]) == 0
    capsys.readouterr()
    net.ext_grid.at[net.ext_grid.index[-1], "vm_pu"] = float(first.vm_pu) + 0.01
    pp.to_json(net, str(two))
    assert main(["check", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2 external grids at different voltages" in err[0]


def test_a_time_step_of_the_profiles_gives_the_operating_point(tmp_path, capsys,
                                                               monkeypatch) -> None:
    """init --time-step: the config holds grid_model.time_step; check and the grid model put
    the net at that quarter hour, each sgen at its installed power times its profile there
    (computed here from the net's profiles, not through simbench's own function)."""
    import simbench

    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    step = 20_000                                              # 31 July 2016, 08:00
    out = tmp_path / "comm-t.yaml"
    assert main(["init", "--simbench", "1-MV-comm--0-no_sw", "--time-step", str(step),
                 "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"time step {step} (" in said
    config = load_config(out)
    assert config.grid_model.time_step == step and "--time-step 20000" in out.read_text()
    net = simbench.get_simbench_net("1-MV-comm--0-no_sw")
    renewables = net.profiles["renewables"].loc[step]
    for der in config.ders:
        row = net.sgen[net.sgen.name == der.sgen].iloc[0]
        want = row.p_mw * renewables[row.profile] * row.scaling * 1e6
        assert available_power_w(config)[der.id] == pytest.approx(want, rel=1e-9)
    assert main(["check", str(out)]) == 0
    assert f"grid model: time step {step}," in capsys.readouterr().out


def test_bad_time_steps_are_one_line(cigre_file, tmp_path, capsys) -> None:
    def error(*argv: str) -> str:
        assert main(list(argv)) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("adnmesh") and "error: " in err[-1]
        assert not any("Traceback" in e for e in err)
        return err[-1]

    out = str(tmp_path / "x.yaml")
    assert "time step 35136 is not in the net's profiles (0 to 35135" in error(
        "init", "--simbench", "1-MV-comm--0-no_sw", "--time-step", "35136", "-o", out)
    assert "a whole number >= 0, got '-1'" in error(
        "init", "--simbench", "1-MV-comm--0-no_sw", "--time-step", "-1", "-o", out)
    assert "not allowed with argument" in error(
        "init", "--simbench", "1-MV-comm--0-no_sw", "--time-step", "3", "--study-case", "hL",
        "-o", out)
    assert "the net has no profiles" in error(
        "init", "--pandapower", str(cigre_file), "--time-step", "3", "-o", out)
    assert main(["init", "--simbench", "1-MV-comm--0-no_sw", "-o", out]) == 0
    text = Path(out).read_text().replace("  study_case: lW", "  study_case: lW\n  time_step: 7")
    Path(out).write_text(text)
    assert "give a study_case or a time_step, not both" in error("check", out)


def test_a_pandapower_sqlite_file(cigre_file, tmp_path, capsys, monkeypatch) -> None:
    """A net saved with pandapower.to_sqlite is read as the JSON one (same P_IP); a file named
    .sqlite that is no database is one line."""
    import pandapower as pp

    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    db = tmp_path / "cigre.sqlite"
    pp.to_sqlite(pp.from_json(str(cigre_file)), str(db))
    configs = []
    for source in (cigre_file, db):
        out = tmp_path / f"{source.suffix[1:]}.yaml"
        assert main(["init", "--pandapower", str(source), "-o", str(out)]) == 0
        assert main(["check", str(out)]) == 0
        configs.append(load_config(out))
    capsys.readouterr()
    assert initial_p_ip_w(configs[1]) == pytest.approx(initial_p_ip_w(configs[0]), abs=1e-6)
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    assert main(["init", "--pandapower", str(junk), "-o", str(tmp_path / "j.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("adnmesh: error: ") and "junk.db is not a pandapower net file" in \
        err[-1] and not any("Traceback" in e for e in err)
