"""Robustness analysis: as-deployed loops (weights applied), summaries, CSV, box plots."""
from dataclasses import replace

import numpy as np
import pytest

from adnmesh.analysis import plots
from adnmesh.analysis.robustness import ALL_EQUAL, METRICS, analyze_robustness, table_batches
from adnmesh.analysis.subset_loops import deployed_batch
from adnmesh.analysis.uncertainty import analyze_uncertainty
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.tuning.problem import all_subsets
from adnmesh.tuning.table import SchedulingTable

from coarse_table import example, small_table

PNG = b"\x89PNG\r\n\x1a\n"


def _weighted_table(name: str) -> SchedulingTable:
    """The small table with one weight lowered, so that W visibly matters."""
    base = small_table(name)
    table = SchedulingTable(base.config_sha256, base.constraints, base.method, base.der_ids,
                            static=base.static, complete=base.complete)
    for entry in base.entries.values():
        w = dict(entry.w)
        if "SGen5" in w and len(w) > 1:
            w["SGen5"] = 0.5
        table.add(replace(entry, w=w))
    return table


def test_all_subsets_in_size_then_config_order():
    assert all_subsets(["a", "b", "c"]) == [("a",), ("b",), ("c",), ("a", "b"), ("a", "c"),
                                            ("b", "c"), ("a", "b", "c")]


def test_figures_are_those_of_the_deployed_loop_with_weights():
    config = example("wt-chp")
    table = _weighted_table("wt-chp")
    result = analyze_robustness(config, table)
    assert result.names == ["SGen1", "SGen5", "SGen1,SGen5"]
    i = result.names.index("SGen1,SGen5")
    entry = table.lookup(["SGen1", "SGen5"])
    assert entry.w["SGen5"] == 0.5
    plant = plant_from_ders(config.ders_by_id(["SGen1", "SGen5"]), config.design_t_com_s,
                            config.t_meas_s, weights=entry.w)
    direct = evaluate(plant, entry.kp, entry.ki).row(0)
    # step figures may differ within the simulation's error bound: in a batch, the step
    # size is coarsened when every response of the batch is smooth
    for m in METRICS:
        assert result.adaptive[m.key][i] == pytest.approx(direct[m.key], rel=1e-6), m.key
    # the group gains carry w_d P_inst,d
    assert sorted(result.adaptive_batch.gains_w[i]) == pytest.approx([0.155e6, 2.0e6])
    # the static controller: its one pair and weights 1 for every subset
    st = table.static
    plant = plant_from_ders(config.ders_by_id(["SGen5"]), config.design_t_com_s, config.t_meas_s)
    direct = evaluate(plant, st.kp, st.ki).row(0)
    j = result.names.index("SGen5")
    assert result.static["rise_time_s"][j] == pytest.approx(direct["rise_time_s"], rel=1e-6)
    assert np.all(result.static_batch.kp == st.kp)


def test_summary_names_the_worst_subsets():
    result = analyze_robustness(example("mixed-4"), small_table("mixed-4"))
    for ctrl in result.controllers:
        summary = result.summary(ctrl)
        values = getattr(result, ctrl)
        for m in METRICS:
            v = np.asarray(values[m.key], float)
            s = summary[m.key]
            fin = np.isfinite(v)
            assert s.median == pytest.approx(np.median(v[fin]))
            worst = np.max(v[fin]) if m.worse == "high" else np.min(v[fin])
            assert s.worst_value == worst
            if s.worst_subset == ALL_EQUAL:
                assert np.all(v[fin] == worst)
            else:
                assert v[result.names.index(s.worst_subset)] == worst
    # the adaptive controller is faster than the static one for the median subset
    assert (result.summary("adaptive")["rise_time_s"].median
            < result.summary("static")["rise_time_s"].median)


def test_a_figure_equal_for_all_subsets_names_no_worst_subset():
    result = analyze_robustness(example("two-wt"), small_table("two-wt"))
    # the adaptive table gives every subset of identical WTs the same normalised loop
    assert result.summary("adaptive")["rise_time_s"].worst_subset == ALL_EQUAL


def test_csv_has_one_row_per_subset_and_a_column_per_figure():
    result = analyze_robustness(example("wt-chp"), _weighted_table("wt-chp"))
    header, rows = result.csv_rows()
    assert len(rows) == 3 and all(len(r) == len(header) for r in rows)
    assert {"adaptive_rise_time_s", "static_delay_margin_s", "w_SGen1", "in_SGen5"} <= set(header)
    row = rows[result.names.index("SGen1,SGen5")]
    assert [row[header.index(c)] for c in ("in_SGen1", "in_SGen5", "w_SGen1", "w_SGen5")] == \
        [1, 1, "1", "0.5"]
    alone = rows[result.names.index("SGen1")]
    assert alone[header.index("in_SGen5")] == 0 and alone[header.index("w_SGen5")] == ""


def test_entries_without_a_pi_pair_are_left_out_of_the_adaptive_analysis():
    base = small_table("wt-chp")
    table = SchedulingTable(base.config_sha256, base.constraints, base.method, base.der_ids,
                            dict(base.entries), base.static)
    table.add(replace(table.lookup(["SGen1", "SGen5"]), kp=float("nan"), ki=float("nan"),
                      feasible=False, reason="no feasible pair"))
    result = analyze_robustness(example("wt-chp"), table)
    i = result.names.index("SGen1,SGen5")
    assert result.without_gains() == ["SGen1,SGen5"] and result.unstable("adaptive") == []
    assert np.isnan(result.adaptive["rise_time_s"][i]) and not result.adaptive["stable"][i]
    assert np.isfinite(result.static["rise_time_s"][i])         # the static pair still applies
    assert result.summary("adaptive")["disk_margin"].finite == 2
    res = analyze_uncertainty(result.adaptive_batch, 5.0, models=("pt1",),
                              quantities=("stability",))
    assert res.without_gains == ("SGen1,SGen5",) and res.excluded == ()


def test_table_without_static_controller_analyses_the_adaptive_one():
    base = small_table("two-wt")
    table = SchedulingTable(base.config_sha256, base.constraints, base.method, base.der_ids,
                            dict(base.entries))
    adaptive, static, feasible, _ = table_batches(example("two-wt"), table)
    assert static is None and feasible.all()
    result = analyze_robustness(example("two-wt"), table)
    assert result.controllers == ("adaptive",) and result.static is None
    header, _ = result.csv_rows()
    assert not any(h.startswith("static_") for h in header)


def test_identical_loops_form_one_class():
    config = example("two-wt")
    # SGen1 and SGen2 are identical; with gains scaled by 1/P_inst the pair is the same loop too
    batch = deployed_batch(config, [("SGen1",), ("SGen2",), ("SGen1", "SGen2")],
                           [1e-7, 1e-7, 0.5e-7], [3e-7, 3e-7, 1.5e-7])
    first, cls = batch.loop_classes()
    assert list(first) == [0] and list(cls) == [0, 0, 0]
    batch = deployed_batch(config, [("SGen1",), ("SGen2",), ("SGen1", "SGen2")], 1e-7, 3e-7)
    first, cls = batch.loop_classes()
    assert list(first) == [0, 2] and list(cls) == [0, 0, 1]


@pytest.mark.parametrize("outliers", [False, True])
def test_box_plot_is_written(tmp_path, outliers):
    result = analyze_robustness(example("wt-chp"), small_table("wt-chp"))
    path = plots.plot_robustness(result, tmp_path / "box.png", outliers=outliers)
    data = path.read_bytes()
    assert data.startswith(PNG) and len(data) > 20_000
