"""``adnmesh analyze``: the output folder, its index, and one-line errors."""
import csv
import json
import re

import pandas as pd
import pytest

from adnmesh.cli import main
from adnmesh.tuning.table import save_table

from coarse_table import EXAMPLES, small_table


@pytest.fixture(scope="module")
def two_wt_table(tmp_path_factory):
    path = tmp_path_factory.mktemp("tables") / "two-wt.json"
    save_table(small_table("two-wt"), path)
    return path


def _error(capsys, *argv):
    code = main(list(argv))
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith("adnmesh: error: "), err
    return err


def test_full_run_writes_every_output_and_an_index_linking_them(tmp_path, two_wt_table, capsys):
    out = tmp_path / "run"
    code = main(["analyze", str(EXAMPLES / "two-wt.yaml"), "--table", str(two_wt_table),
                 "--out", str(out), "--models", "pt1,rhpz", "--solution-space", "SGen2",
                 "--grid", "8"])
    stdout = capsys.readouterr().out
    assert code == 0
    files = {p.name for p in out.iterdir()}
    assert {"index.md", "robustness.png", "robustness.csv", "robustness.md", "uncertainty.png",
            "uncertainty.md", "uncertainty.json", "solution-space-SGen2.png",
            "solution-space-SGen2.csv", "solution-space-SGen2.json"} <= files
    for name in files:
        assert (out / name).stat().st_size > 0, name
    index = (out / "index.md").read_text()
    linked = set(re.findall(r"\]\(([^)]+)\)", index))
    assert files - {"index.md"} <= linked
    rows = list(csv.DictReader((out / "robustness.csv").open()))
    assert [r["subset"] for r in rows] == ["SGen1", "SGen2", "SGen1,SGen2"]
    space = pd.read_csv(out / "solution-space-SGen2.csv")     # tidy: pandas' defaults
    assert len(space) == 64 and (space.columns[space.dtypes == object] == ["class"]).all()
    doc = json.loads((out / "uncertainty.json").read_text())
    assert set(doc["controllers"]) == {"adaptive", "static"}
    assert [m["model"] for m in doc["controllers"]["static"]["models"]] == ["pt1", "rhpz"]
    md = (out / "uncertainty.md").read_text()
    assert "| PT1 |" in md and "| RHPZ |" in md and "nominal value" in md
    assert "Robustness and performance" in stdout and "wrote" in stdout


def test_only_one_part(tmp_path, two_wt_table):
    out = tmp_path / "rob"
    assert main(["analyze", str(EXAMPLES / "two-wt.yaml"), "--table", str(two_wt_table),
                 "--out", str(out), "--only", "robustness", "--outliers"]) == 0
    assert {p.name for p in out.iterdir()} == {"index.md", "robustness.png", "robustness.csv",
                                               "robustness.md"}


def test_missing_default_table_says_to_tune_first(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    err = _error(capsys, "analyze", str(EXAMPLES / "two-wt.yaml"))
    assert "adnmesh tune" in err and "tables/two-wt." in err


@pytest.mark.parametrize("args, message", [
    (["--solution-space", "SGen9"], "unknown DER id 'SGen9'"),
    (["--solution-space", "SGen1,SGen1"], "duplicate DER id"),
    (["--solution-space", ","], "at least one DER id"),
    (["--grid", "2", "--solution-space", "SGen1"], "--grid must be between"),
    (["--models", "pt3"], "--models: unknown value 'pt3'"),
    (["--only", "boxplots"], "--only: unknown value 'boxplots'"),
    (["--only", "solution-space"], "needs --solution-space"),
])
def test_bad_arguments_give_one_line_errors(capsys, two_wt_table, tmp_path, args, message):
    err = _error(capsys, "analyze", str(EXAMPLES / "two-wt.yaml"), "--table",
                 str(two_wt_table), "--out", str(tmp_path / "x"), *args)
    assert message in err
    assert not (tmp_path / "x").exists()


def test_table_of_another_config_is_refused(capsys, two_wt_table, tmp_path):
    err = _error(capsys, "analyze", str(EXAMPLES / "wt-chp.yaml"), "--table", str(two_wt_table),
                 "--out", str(tmp_path / "x"))
    assert "tuned for another design (ders" in err
    err = _error(capsys, "analyze", str(EXAMPLES / "wt-chp.yaml"), "--table",
                 str(tmp_path / "nope.json"))
    assert "nope.json" in err and "adnmesh tune" in err


def test_der_models_alone_need_no_table(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)                      # no tables/ here
    out = tmp_path / "der"
    assert main(["analyze", str(EXAMPLES / "two-wt.yaml"), "--only", "der-models",
                 "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == {"index.md", "der-models.png", "der-models.csv",
                                               "der-models.json", "der-handover.png"}
    rows = list(csv.DictReader((out / "der-models.csv").open()))
    assert {r["der"] for r in rows} == {"SGen1", "SGen2"}
    first = rows[0]
    assert (first["direction"], first["step_pct"]) == ("up", "10")
    assert float(first["rise_time_s"]) == pytest.approx(float(first["pt1_rise_time_s"]),
                                                        rel=1e-6)
    doc = json.loads((out / "der-models.json").read_text())
    assert doc["ders"][0]["model"] == "WT Type 4B-like"
    assert "der-models.png" in (out / "index.md").read_text()
    assert "der-handover.png" in (out / "index.md").read_text()
    assert "DER models" in capsys.readouterr().out


def test_der_models_beside_the_table_parts(tmp_path, two_wt_table):
    out = tmp_path / "both"
    assert main(["analyze", str(EXAMPLES / "two-wt.yaml"), "--table", str(two_wt_table),
                 "--out", str(out), "--only", "robustness", "--der-models"]) == 0
    assert {"robustness.csv", "der-models.png"} <= {p.name for p in out.iterdir()}
