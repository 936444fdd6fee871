"""Tests of adnmesh export: a run's time series as CSV files and a Foxglove layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from adnmesh.cli import main
from adnmesh.results.csv_export import csv_name
from adnmesh.results.foxglove_layout import foxglove_layout, layout_json, message_path
from adnmesh.results.series import read_run
from synthetic_runs import FAKE_DERS, write_fake_run

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("export") / "fake.mcap"
    write_fake_run(path, duration_s=30.0)
    return path


@pytest.fixture(scope="module")
def exported(fake, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("csv") / "run"
    assert main(["export", str(fake), "--csv", str(out)]) == 0
    return out


def test_one_csv_per_key_in_mw_exactly_as_the_series(fake, exported) -> None:
    run = read_run(fake)[0].run
    exact = {"float_precision": "round_trip"}              # the text is exact to the last bit
    p_ip = pd.read_csv(exported / "measurement_p_ip.csv", **exact)
    assert list(p_ip.columns) == ["time_s", "P_IP [MW]"]
    series = run.one("p_ip")
    assert np.array_equal(p_ip["time_s"], run.seconds(series.t_ns))
    assert np.array_equal(p_ip["P_IP [MW]"], series.values * 1e-6)
    assert np.allclose(pd.read_csv(exported / "measurement_p_ip.csv")["P_IP [MW]"],
                       series.values * 1e-6, rtol=1e-15, atol=0)   # pandas' default: close
    p_y = pd.read_csv(exported / "cpfc_p_y.csv", **exact)
    assert list(p_y.columns) == ["time_s", "P_Y", "K_P [1/MW]", "K_I [1/(MW s)]", "table entry"]
    assert np.array_equal(p_y["K_I [1/(MW s)]"], run.one("ki").values * 1e6)
    for der in FAKE_DERS:
        state = pd.read_csv(exported / f"der_{der}_state.csv")
        assert list(state.columns) == ["time_s", f"{der} infeed [MW]", f"{der} setpoint [MW]"]
        assert len(state) == 301 and state.notna().all().all()
    si = pd.read_csv(exported / "availability_si.csv")
    assert list(si.columns) == ["time_s", "DERs available",
                                *(f"{d} available" for d in ("CHP1", "PV1", "WT1", "WT2"))]
    assert si.loc[si.time_s >= 25, "WT1 available"].eq(0).all()


def test_the_index_lists_every_series_and_the_events_file_every_event(fake, exported) -> None:
    run = read_run(fake)[0].run
    index = pd.read_csv(exported / "series.csv", keep_default_na=False)
    assert len(index) == len(run.series)
    assert set(index.series) == {s.name for s in run.series.values()}
    for row in index.itertuples():
        assert row.column in pd.read_csv(exported / row.file, nrows=1).columns
    assert set(index.loc[index.role == "der_infeed", "unit"]) == {"MW"}
    assert set(index.loc[index.role == "der_infeed", "der"]) == set(FAKE_DERS)
    events = pd.read_csv(exported / "events.csv")
    assert list(events.columns) == ["time_s", "kind", "level", "text", "key"]
    assert events.kind.tolist() == [e.kind for e in run.events]
    assert events.time_s.tolist() == [run.seconds(e.t_ns) for e in run.events]


def test_every_csv_is_numeric_but_its_text_columns(exported) -> None:
    from pandas.api.types import is_numeric_dtype

    text = {"series.csv": {"file", "column", "series", "unit", "role", "der", "key", "field"},
            "events.csv": {"kind", "level", "text", "key"}}
    files = sorted(exported.glob("*.csv"))
    assert len(files) == 2 + 4 + 4       # index, events; p_ref, p_ip, p_y, SI; four DERs
    for path in files:
        frame = pd.read_csv(path)
        for column in frame.columns:
            if column not in text.get(path.name, ()):
                assert is_numeric_dtype(frame[column]), (path.name, column)


def test_csv_names_are_the_keys_below_the_grid() -> None:
    assert csv_name("adn/g/der/SGen1/state") == "der_SGen1_state.csv"
    assert csv_name("adn/g/measurement/grid") == "measurement_grid.csv"
    assert csv_name("other topic") == "other_topic.csv"


def test_export_asks_for_something_and_refuses_a_file_as_folder(fake, tmp_path, capsys) -> None:
    assert main(["export", str(fake)]) == 2
    assert "--csv DIR and/or --foxglove-layout FILE" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["export", str(fake), "--csv", str(tmp_path / "file")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def _panels(layout: dict) -> list[str]:
    def walk(node) -> list[str]:
        return [node] if isinstance(node, str) else walk(node["first"]) + walk(node["second"])
    return walk(layout["layout"])


def test_the_foxglove_layout_of_a_run_plots_its_topics(fake, tmp_path) -> None:
    out = tmp_path / "layout.json"
    assert main(["export", str(fake), "--foxglove-layout", str(out)]) == 0
    layout = json.loads(out.read_text())
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig",
                           "layout"}
    assert sorted(_panels(layout)) == sorted(layout["configById"])   # every panel placed
    assert {p.split("!")[0] for p in layout["configById"]} == {"Plot", "RosOut"}
    topics = set(read_run(fake)[0].recording.channels)
    paths = [line["value"] for panel in layout["configById"].values()
             for line in panel.get("paths", ())]
    for path in paths:                       # every plotted topic is one of the recording's
        assert path.rsplit(".", 1)[0] in topics, path
    ders = layout["configById"]["Plot!ders"]["paths"]
    assert [line["label"] for line in ders] == [f"{d} infeed [W]" for d in
                                                ("CHP1", "PV1", "WT1", "WT2")]
    assert len({line["color"] for line in ders}) == len(FAKE_DERS)
    assert "Plot!voltages" not in layout["configById"]          # the fake run has no grid
    assert layout["configById"]["RosOut!events"]["topicToRender"] == "adn/fake/log"


def test_message_paths_are_written_as_foxglove_writes_them() -> None:
    assert message_path("adn/simbench-1-MV-rural/measurement/p_ip", "p_ip_w") == \
        "adn/simbench-1-MV-rural/measurement/p_ip.p_ip_w"
    assert message_path('adn/a b/"x"', "f.g") == '"adn/a b/\\"x\\""."f.g"'


def test_the_shipped_layout_is_the_reference_cases() -> None:
    from adnmesh.config import load_config

    config = load_config(REPO / "configs" / "simbench.yaml")
    shipped = (REPO / "docs" / "foxglove-layout.json").read_text()
    assert shipped == layout_json(foxglove_layout(config.grid, [d.id for d in config.ders]))
    layout = json.loads(shipped)
    assert len(layout["configById"]["Plot!ders"]["paths"]) == len(config.ders)
    assert {"Plot!p_ip", "Plot!p_y", "Plot!gains", "Plot!ders", "Plot!voltages",
            "Plot!loadings", "RosOut!events"} == set(layout["configById"])
