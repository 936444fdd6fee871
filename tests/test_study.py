"""The year study (adnmesh study): availability rules, ranges, interval results against an
independent pandapower power flow, the command's files, errors and determinism, and the
runtime's check of the study's predictions (--verify)."""

from __future__ import annotations

import copy
import csv
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from adnmesh.config import load_config
from adnmesh.study.availability import (AVAILABLE, ICT, LOW_OUTPUT, MAINTENANCE,
                                        availability)
from adnmesh.study.entries import Figures
from adnmesh.study.ranges import direction, linear_range
from adnmesh.tuning.design_key import design_document
from adnmesh.tuning.table import save_table

REPO = Path(__file__).resolve().parent.parent
CONFIG = REPO / "configs" / "simbench.yaml"
CODE = "1-MV-rural--0-no_sw"


class _Window:
    def __init__(self, ders, start, end):
        self.ders, self.start, self.end = ders, start, end


# -- availability rules -------------------------------------------------------------------------

def test_availability_rules_in_their_order_and_the_draws_do_not_depend_on_the_window():
    times = np.arange(np.datetime64("2016-06-01T00:00"), np.datetime64("2016-06-03T00:00"),
                      np.timedelta64(15, "m"))
    t, n = times.size, 3
    p_inst = np.array([1e6, 2e6, 1e6])
    p_avail = np.full((t, n), 0.5e6)
    p_avail[:10, 0] = 0.009e6                   # below 1 % of 1 MW: low output
    p_avail[10, 0] = 0.011e6                    # above it
    maintenance = [_Window(("D2",), "2016-06-01T06:00", "2016-06-01T07:00")]
    reason = availability(p_avail, p_inst, np.full(n, 0.01), times, maintenance,
                          ("D1", "D2", "D3"), 1.0, 0)
    assert (reason[:10, 0] == LOW_OUTPUT).all() and reason[10, 0] == AVAILABLE
    assert (reason[24:28, 1] == MAINTENANCE).all()          # 06:00, 06:15, 06:30, 06:45
    assert reason[23, 1] == AVAILABLE and reason[28, 1] == AVAILABLE
    assert (reason[:, 2] == AVAILABLE).all()

    p_avail[:, :] = 0.5e6
    ict = availability(p_avail, p_inst, np.full(n, 0.01), times, (), ("D1", "D2", "D3"),
                       0.8, 7)
    share = np.mean(ict == ICT)
    assert 0.12 < share < 0.28                  # 576 draws of p = 0.2
    later = availability(p_avail[50:], p_inst, np.full(n, 0.01), times[50:], (),
                         ("D1", "D2", "D3"), 0.8, 7, first_interval=50)
    assert (later == ict[50:]).all()
    # low output wins over maintenance, maintenance over ICT
    p_avail[24, 1] = 0.0
    mixed = availability(p_avail, p_inst, np.full(n, 0.01), times, maintenance,
                         ("D1", "D2", "D3"), 0.5, 3)
    assert mixed[24, 1] == LOW_OUTPUT and (mixed[25:28, 1] == MAINTENANCE).all()


# -- ranges --------------------------------------------------------------------------------------

def test_linear_range_is_the_first_der_to_saturate_and_the_service_needs_speed_and_range():
    share = np.array([0.5, 0.25, 0.25, 0.0])
    f = Figures(True, 2.0, 3.0, 2.0, 1.6, share)
    head = np.array([[1.0e6, 0.2e6, 0.9e6, 5e6],     # DER 2 saturates first: 0.2 / 0.25
                     [0.4e6, 1.0e6, 1.0e6, 0.0]])    # DER 1: 0.4 / 0.5
    expected = np.array([0.2e6 / 0.25, 0.4e6 / 0.5]) / 1.02
    assert np.allclose(linear_range(head, f), expected)
    mask = np.array([True, True, True, False])
    range_w, linear, ok = direction(head, mask, f, 0.7e6, 3.0)
    assert np.allclose(range_w, [2.1e6, 2.4e6])
    assert ok.tolist() == [True, True]
    assert direction(head, mask, f, 0.7e6, 2.9)[2].tolist() == [False, False]   # too slow
    assert direction(head, mask, f, 0.79e6, 3.0)[2].tolist() == [False, False]  # too big
    empty = Figures(False, np.nan, np.nan, np.nan, np.nan, np.zeros(4))
    assert direction(head, np.zeros(4, bool), empty, 1.0, 10.0)[2].tolist() == [False, False]


# -- the year's intervals against pandapower ------------------------------------------------------

@pytest.fixture(scope="module")
def study_inputs():
    from adnmesh.control.operating_point import available_power_w
    from adnmesh.grid import load_grid
    from adnmesh.grid.profiles import load_profiles

    config = load_config(CONFIG)
    profiles = load_profiles(CODE, "impedance")
    data = load_grid(CODE, "time step 0", "impedance")
    power = available_power_w(config)
    return config, profiles, data, np.array([power[d] for d in config.der_ids()])


def _with_study(config, **study):
    return config.model_copy(update={"study": config.study.model_copy(update=study)})


def test_interval_results_match_pandapower_runpp_at_sample_intervals(study_inputs):
    import pandapower as pp

    from adnmesh.grid.simbench_net import (apply_time_step, load_simbench_net,
                                           loads_as_impedances)
    from adnmesh.study.year import study_year

    config, profiles, data, p_op = study_inputs
    config = _with_study(config, ict_availability=0.6)
    base = load_simbench_net(CODE)
    for k in (100, 12_000, 20_000, 30_000):
        result = study_year(config, profiles.window(k, k + 1), data, p_op, None, k)
        reason, sched, avail = result.reason[0], result.p_sched_w[0], result.p_avail_w[0]
        infeed = np.where((reason == AVAILABLE) | (reason == ICT), sched,
                          np.where(reason == LOW_OUTPUT, avail, 0.0))
        net = copy.deepcopy(base)
        apply_time_step(net, k)
        loads_as_impedances(net)
        for der, p_w in zip(config.ders, infeed):
            net.sgen.loc[net.sgen.name == der.sgen, "p_mw"] = p_w / 1e6
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pp.runpp(net)
        col = result.columns
        assert col["p_ip_w"][0] == pytest.approx(-net.res_ext_grid.p_mw.sum() * 1e6, abs=1.0)
        assert col["q_ip_var"][0] == pytest.approx(-net.res_ext_grid.q_mvar.sum() * 1e6,
                                                   abs=1.0)
        buses = net.res_bus.drop(index=net.ext_grid.bus).vm_pu.dropna()
        assert col["vm_max_pu"][0] == pytest.approx(buses.max(), abs=1e-7)
        assert col["vm_min_pu"][0] == pytest.approx(buses.min(), abs=1e-7)
        assert col["line_max_pct"][0] == pytest.approx(net.res_line.loading_percent.max(),
                                                       abs=1e-5)
        # available power from the profile, availability by the rule
        base_k = copy.deepcopy(base)
        apply_time_step(base_k, k)
        profile = base_k.sgen.set_index("name").p_mw
        for d, der in enumerate(config.ders):
            expected = min(profile[der.sgen] * 1e6, der.p_inst_w)
            assert avail[d] == pytest.approx(expected, abs=1e-6)
            if expected <= 0.01 * der.p_inst_w:
                assert reason[d] == LOW_OUTPUT


def test_the_guard_blocks_directions_where_a_limit_is_near(study_inputs):
    from adnmesh.study.year import study_year

    config, profiles, data, p_op = study_inputs
    loose = study_year(config, profiles.window(0, 96 * 3), data, p_op)
    high = float(np.percentile(loose.columns["vm_max_pu"], 50))
    limits = config.grid_model.limits.model_copy(update={"v_max_pu": high + 0.005})
    tight = config.model_copy(update={"grid_model": config.grid_model.model_copy(
        update={"limits": limits})})
    result = study_year(tight, profiles.window(0, 96 * 3), data, p_op)
    col = result.columns
    limited = col["limited"]
    assert limited.any() and not limited.all()
    assert (limited == (col["vm_max_pu"] > high - 0.005)).all()
    blocked = np.array([bool(b) for b in col["blocked_up"]])
    assert blocked[limited].any() and not blocked[~limited].any()
    # raising P near a high voltage is what is blocked; a blocked DER's headroom is not range
    assert (col["range_up_w"][blocked] < loose.columns["range_up_w"][blocked]).all()
    assert (col["range_down_w"] == loose.columns["range_down_w"]).all()


# -- the command ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A copy of the reference config with a maintenance window, and a small gain table
    (the scenario's subsets; the year's others are tuned on demand)."""
    from tuned_tables import tuned_table

    folder = tmp_path_factory.mktemp("study")
    document = yaml.safe_load(CONFIG.read_text())
    document["study"] = {"maintenance": [{"ders": ["SGen5"], "start": "2016-01-02",
                                          "end": "2016-01-03"}]}
    path = folder / "year.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    config = load_config(path)
    table = folder / "year.table.json"
    tuned = tuned_table(config)
    tuned.design = design_document(config)      # bound to the design, as tune's tables are
    save_table(tuned, table)
    return path, table


def _study(path, table, out, *extra, check=True):
    argv = [sys.executable, "-m", "adnmesh", "study", str(path), "--table", str(table),
            "--out", str(out), *extra]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False,
                          cwd=out.parent)
    if check:
        assert done.returncode == 0, done.stderr
    return done


@pytest.fixture(scope="module")
def week(case, tmp_path_factory):
    path, table = case
    out = tmp_path_factory.mktemp("week") / "out"
    done = _study(path, table, out, "--start", "2016-01-01", "--end", "2016-01-08")
    return out, done


def test_study_writes_tidy_files_and_figures_of_the_intervals_asked_for(week):
    out, done = week
    rows = list(csv.DictReader((out / "intervals.csv").open()))
    assert len(rows) == 7 * 96
    assert rows[0]["time"] == "2016-01-01T00:00" and rows[-1]["time"] == "2016-01-07T23:45"
    in_maintenance = [r for r in rows if r["time"].startswith("2016-01-02")]
    assert all("SGen5" not in r["available"].split() for r in in_maintenance)
    assert any("SGen5" in r["available"].split() for r in rows[:96])
    for r in rows:
        assert float(r["linear_up_mw"]) <= float(r["range_up_mw"]) + 1e-9
        assert r["service"] == str(int(r["service_up"] == "1" and r["service_down"] == "1"))
    ders = list(csv.DictReader((out / "ders.csv").open()))
    assert tuple(d["der"] for d in ders) == load_config(CONFIG).der_ids()
    assert float(ders[4]["maintenance_share"]) == pytest.approx(1 / 7)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["intervals"] == 7 * 96
    share = np.mean([r["service"] == "1" for r in rows])
    assert summary["service"]["share"] == pytest.approx(share)
    for name in ("duration", "heatmap_rise", "heatmap_range", "limits", "contribution"):
        assert (out / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "deliverable in" in done.stdout and "intervals" in done.stdout


def test_study_is_deterministic_and_its_service_follows_the_command_line(case, week,
                                                                          tmp_path):
    path, table = case
    out, _ = week
    again = tmp_path / "again"
    _study(path, table, again, "--start", "2016-01-01", "--end", "2016-01-08", "--no-figures")
    assert (again / "intervals.csv").read_bytes() == (out / "intervals.csv").read_bytes()
    smaller = tmp_path / "smaller"
    _study(path, table, smaller, "--start", "2016-01-01", "--end", "2016-01-08",
           "--no-figures", "--service-mw", "0.2", "--service-s", "60")
    a = json.loads((out / "summary.json").read_text())["service"]
    b = json.loads((smaller / "summary.json").read_text())["service"]
    assert b["size_mw"] == 0.2 and b["within_s"] == 60
    assert b["share"] > a["share"]


@pytest.mark.parametrize("extra, words", [
    (("--start", "yesterday"), "--start 'yesterday': not a date"),
    (("--start", ""), "--start '': not a date"),
    (("--start", "20160101"), "--start '20160101': not a date"),
    (("--start", "2016-01-01T12:00+02:00"), "--start '2016-01-01T12:00+02:00': not a date"),
    (("--end", "2016-02-30"), "--end '2016-02-30': not a date"),
    (("--start", "2016-03-02", "--end", "2016-03-01"), "no interval of the profiles"),
    (("--service-mw", "-1"), "--service-mw must be in"),
    (("--verify", "99"), "--verify must be 0 to 20"),
])
def test_bad_command_lines_are_one_line_errors(case, tmp_path, extra, words):
    path, table = case
    done = _study(path, table, tmp_path / "out", *extra, check=False)
    assert done.returncode == 2
    assert words in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_a_config_without_a_grid_model_is_refused_in_one_line(tmp_path):
    document = yaml.safe_load(CONFIG.read_text())
    del document["grid_model"]
    path = tmp_path / "nogrid.yaml"
    path.write_text(yaml.safe_dump(document))
    done = subprocess.run([sys.executable, "-m", "adnmesh", "study", str(path)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "needs a grid model" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.slow
def test_verify_runs_the_runtime_and_measures_what_the_study_predicts(case, tmp_path):
    path, table = case
    out = tmp_path / "verify"
    done = _study(path, table, out, "--start", "2016-01-01", "--end", "2016-01-02",
                  "--no-figures", "--verify", "1")
    rows = json.loads((out / "summary.json").read_text())["verify"]["rows"]
    assert len(rows) == 1
    row = rows[0]
    assert (out / "verify" / f"interval-{row['interval']}.mcap").stat().st_size > 0
    assert row["measured_rise_s"] == pytest.approx(row["predicted_rise_s"], rel=0.1)
    assert row["measured_settling_s"] == pytest.approx(row["predicted_settling_s"], rel=0.15)
    assert row["measured_overshoot_pct"] <= row["predicted_overshoot_pct"] + 0.5
    assert "verify 2016-01-01" in done.stdout


@pytest.mark.slow
def test_the_profile_cache_is_read_back_and_a_damaged_one_is_rebuilt(tmp_path, study_inputs):
    from adnmesh.grid.profiles import load_profiles

    _, year, _, _ = study_inputs
    first = load_profiles(CODE, "power", cache_dir=tmp_path)
    files = list(tmp_path.glob("profiles-*.npz"))
    assert len(files) == 1
    again = load_profiles(CODE, "power", cache_dir=tmp_path)
    assert (again.load_p == first.load_p).all() and (again.times == year.times).all()
    assert again.shunt_p is None and year.load_p is None       # power vs impedance loads
    data = bytearray(files[0].read_bytes())
    data[len(data) // 2] ^= 0xFF
    files[0].write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match="profile cache .* rebuilding it"):
        rebuilt = load_profiles(CODE, "power", cache_dir=tmp_path)
    assert (rebuilt.sgen_p == first.sgen_p).all()


# -- a user's own time series ---------------------------------------------------------------------

def _write_series(path: Path, rows: list[dict]) -> Path:
    with path.open("w", newline="") as fh:
        out = csv.DictWriter(fh, fieldnames=list(rows[0]))
        out.writeheader()
        out.writerows(rows)
    return path


def test_your_own_time_series_match_pandapower_runpp(study_inputs, tmp_path):
    import pandapower as pp
    import pyarrow as pa
    import pyarrow.parquet as pq

    from adnmesh.grid import load_grid
    from adnmesh.grid.profile_file import read_profile_table
    from adnmesh.grid.profiles import profiles_of_table
    from adnmesh.grid.simbench_net import apply_study_case, load_simbench_net, loads_as_impedances
    from adnmesh.study.year import study_year

    config, _, _, p_op = study_inputs
    net = load_simbench_net(CODE)
    apply_study_case(net, "lW")
    wind = "MV1.101 SGen 1"
    load = str(net.load.name.iloc[3])
    rows = [{"time": "2024-03-01T00:00", f"sgen.p_mw:{wind}": 0.4, f"load.p_mw:{load}": 0.9,
             f"load.q_mvar:{load}": 0.2},
            {"time": "2024-03-01 00:15", f"sgen.p_mw:{wind}": 1.6, f"load.p_mw:{load}": 0.1,
             f"load.q_mvar:{load}": -0.05}]
    times, series = read_profile_table(_write_series(tmp_path / "series.csv", rows))
    parquet = tmp_path / "series.parquet"
    pq.write_table(pa.table({"time": pa.array(times.astype("datetime64[ms]")),
                             **{f"sgen.p_mw:{wind}": [0.4, 1.6],
                                f"load.p_mw:{load}": [0.9, 0.1],
                                f"load.q_mvar:{load}": [0.2, -0.05]}}), parquet)
    times_pq, series_pq = read_profile_table(parquet)
    assert (times_pq == times).all() and str(times[1]) == "2024-03-01T00:15"
    profiles = profiles_of_table(net, times, series, "impedance")
    twin = profiles_of_table(net, times_pq, series_pq, "impedance")
    assert (twin.shunt_p == profiles.shunt_p).all() and (twin.sgen_p == profiles.sgen_p).all()
    data = load_grid(CODE, "lW", "impedance")
    result = study_year(config, profiles, data, p_op)
    for k, row in enumerate(rows):
        check = copy.deepcopy(net)
        check.sgen.loc[check.sgen.name == wind, "p_mw"] = row[f"sgen.p_mw:{wind}"]
        check.load.loc[check.load.name == load, ["p_mw", "q_mvar"]] = (
            row[f"load.p_mw:{load}"], row[f"load.q_mvar:{load}"])
        sched = result.p_sched_w[k]
        reason = result.reason[k]
        for der, p_w, why, avail in zip(config.ders, sched, reason, result.p_avail_w[k]):
            check.sgen.loc[check.sgen.name == der.sgen, "p_mw"] = (
                p_w if why == AVAILABLE else avail) / 1e6
        loads_as_impedances(check)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pp.runpp(check)
        assert result.columns["p_ip_w"][k] == pytest.approx(
            -check.res_ext_grid.p_mw.sum() * 1e6, abs=1.0)
        assert result.columns["q_ip_var"][k] == pytest.approx(
            -check.res_ext_grid.q_mvar.sum() * 1e6, abs=1.0)
    assert result.p_avail_w[1, 0] == pytest.approx(1.6e6)


@pytest.mark.parametrize("rows, words", [
    ([{"when": "2024-03-01T00:00", "sgen.p_mw:x": 1}, {"when": "2024-03-01T00:15",
                                                      "sgen.p_mw:x": 1}], "no 'time' column"),
    ([{"time": "01.03.2024 00:00", "sgen.p_mw:x": 1}, {"time": "x", "sgen.p_mw:x": 1}],
     "row 2: time '01.03.2024 00:00' is not"),
    ([{"time": "2024-03-01T00:15", "sgen.p_mw:x": 1}, {"time": "2024-03-01T00:00",
                                                      "sgen.p_mw:x": 1}],
     "times must increase in equal steps"),
    ([{"time": "2024-03-01T00:00", "sgen.q:x": 1}, {"time": "2024-03-01T00:15",
                                                   "sgen.q:x": 1}], "column 'sgen.q:x' is none"),
    ([{"time": "2024-03-01T00:00", "sgen.p_mw:x": 1}, {"time": "2024-03-01T00:15",
                                                      "sgen.p_mw:x": "nan"}],
     "column 'sgen.p_mw:x', row 3: not a number within ±10000 MW or Mvar, got nan"),
    ([{"time": "2024-03-01T00:00", "sgen.p_mw:x": 1}, {"time": "2024-03-01T00:15",
                                                      "sgen.p_mw:x": "a lot"}],
     "holds string, not numbers"),
])
def test_bad_profile_files_are_one_line_errors(tmp_path, capsys, rows, words):
    from adnmesh.cli import main

    path = _write_series(tmp_path / "bad.csv", rows)
    assert main(["study", str(CONFIG), "--profiles", str(path), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1, err


def _study_main(path: Path, tmp_path: Path, capsys) -> str:
    from adnmesh.cli import main

    assert main(["study", str(CONFIG), "--profiles", str(path), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_repeated_columns_an_undecodable_header_and_absurd_values_are_one_line_errors(
        tmp_path, capsys):
    twice = tmp_path / "twice.csv"
    twice.write_text("time,sgen.p_mw:MV1.101 SGen 1,sgen.p_mw:MV1.101 SGen 1\n"
                     "2024-03-01T00:00,1,1\n2024-03-01T00:15,1,1\n")
    assert "column 'sgen.p_mw:MV1.101 SGen 1' is given 2 times" in _study_main(
        twice, tmp_path, capsys)
    latin = tmp_path / "latin.csv"
    latin.write_bytes(b"time,sgen.p_mw:\xdc\x1b[31m\n2024-03-01T00:00,1\n2024-03-01T00:15,1\n")
    assert "the column names are not UTF-8 text" in _study_main(latin, tmp_path, capsys)
    huge = _write_series(tmp_path / "huge.csv", [
        {"time": "2024-03-01T00:00", "load.p_mw:MV1.101 Load 2": 0.1},
        {"time": "2024-03-01T00:15", "load.p_mw:MV1.101 Load 2": 1e300}])
    assert "row 3: not a number within ±10000 MW or Mvar, got 1e+300" in _study_main(
        huge, tmp_path, capsys)


def test_parquet_times_with_a_zone_are_refused(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from adnmesh.errors import GridError
    from adnmesh.grid.profile_file import read_profile_table

    path = tmp_path / "zoned.parquet"
    times = pa.array(np.array(["2024-03-01T00:00", "2024-03-01T00:15"], dtype="datetime64[ms]"),
                     type=pa.timestamp("ms", tz="Europe/Berlin"))
    pq.write_table(pa.table({"time": times, "sgen.p_mw:x": [1.0, 2.0]}), path)
    with pytest.raises(GridError, match="the times carry a time zone"):
        read_profile_table(path)


def test_the_profile_file_is_never_overwritten_by_the_results(tmp_path, capsys):
    from adnmesh.cli import main

    out = tmp_path / "out"
    out.mkdir()
    mine = _write_series(out / "intervals.csv", [
        {"time": "2024-03-01T00:00", "sgen.p_mw:MV1.101 SGen 1": 1},
        {"time": "2024-03-01T00:15", "sgen.p_mw:MV1.101 SGen 1": 1}])
    before = mine.read_bytes()
    assert main(["study", str(CONFIG), "--profiles", str(mine), "--out", str(out)]) == 2
    assert "is one of the files the study writes" in capsys.readouterr().err
    assert mine.read_bytes() == before


def test_verify_without_a_table_fails_before_anything_is_written(tmp_path, capsys):
    from adnmesh.cli import main
    from adnmesh.commands.study import TABLE_DERS

    document = yaml.safe_load(CONFIG.read_text())
    base = document["ders"][0]
    document["ders"] += [dict(base, id=f"Extra{i}", sgen=f"MV1.101 SGen {13 + i}",
                              p_sched_w=0.0) for i in range(TABLE_DERS + 1 - 11)]
    path = tmp_path / "many.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    out = tmp_path / "out"
    assert main(["study", str(path), "--out", str(out), "--verify", "1"]) == 2
    assert "--verify: needs a gain table" in capsys.readouterr().err
    assert not (out / "intervals.csv").exists()


def test_a_series_of_an_element_the_net_lacks_is_a_one_line_error(tmp_path, capsys):
    from adnmesh.cli import main

    path = _write_series(tmp_path / "unknown.csv", [
        {"time": "2024-03-01T00:00", "sgen.p_mw:MV1.101 SGen 99": 1},
        {"time": "2024-03-01T00:15", "sgen.p_mw:MV1.101 SGen 99": 1}])
    assert main(["study", str(CONFIG), "--profiles", str(path), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "the net has no sgen named 'MV1.101 SGen 99'" in err
