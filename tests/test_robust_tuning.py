"""Robust tables: the uncertainty set in the config, its box of plants, the certificate (the
worst member it finds against dense sampling of the set), robust entries that hold on every
sampled member where nominal ones do not, the back-off when the searches missed a member, and
the set ``identify`` writes."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import yaml

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.identify.implied_set import implied_set
from adnmesh.identify.model_fit import ModelFit
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.tuning.certify import PlantGroup, certified_entries
from adnmesh.tuning.design_key import design_document
from adnmesh.tuning.ondemand import tune_subset
from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.robust_check import worst_members
from adnmesh.tuning.robust_set import Member

REPO = Path(__file__).resolve().parent.parent
SIMBENCH = REPO / "configs" / "simbench.yaml"
#: a CHP and a PV (two DER types): two coordinates of the CHP's, one PV fixed
SET = {"models": ["pt1", "pt2"],
       "types": {"CHP": {"lag_scale": [1.0, 1.6], "delay_add_s": [0.0, 4.0]}}}


def _config(tmp_path: Path, robust: dict | None = SET, name: str = "two") -> Path:
    doc = {"extends": str(SIMBENCH),
           "ders": [{"id": "SGen5", "type": "CHP", "p_inst_w": 0.31e6, "t_delay_s": 1.0,
                     "t_rise_s": 24.57, "sgen": "MV1.101 MV SGen 5"},
                    {"id": "SGen9", "type": "PV", "p_inst_w": 0.195e6, "t_delay_s": 0.01,
                     "t_rise_s": 0.1, "sgen": "MV1.101 MV SGen 9"}],
           "scenario": {"duration_s": 10, "p_ref_steps": [{"t_s": 1, "delta_w": 1e5}],
                        "availability": []}}
    if robust is not None:
        doc["constraints"] = {"robust": robust}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _dense(problem: TuningProblem, gains, kp: float, ki: float, n: int = 9):
    """(lowest disk margin, highest overshoot %) of one loop over an n-per-coordinate grid of
    the box, every structure: dense sampling, one evaluation per member."""
    low, high = np.inf, -np.inf
    for model in problem.box.models:
        for x in itertools.product(np.linspace(0, 1, n), repeat=problem.box.dimension):
            f = evaluate(problem.member_plant(Member(model, x), gains), np.array([kp]),
                         np.array([ki]), band_pct=problem.band_pct, classical=False)
            low = min(low, float(f.disk_margin[0]) if f.stable[0] else 0.0)
            high = max(high, float(f.overshoot_pct[0]) if f.stable[0] else np.inf)
    return low, high


@pytest.mark.parametrize("robust, said", [
    ({"lag_scale": [1.6, 1.0]}, "constraints.robust.lag_scale: the low end 1.6 is above"),
    ({"models": ["pt1", "pt9"]}, "constraints.robust.models[1]: must be one of"),
    ({"models": ["pt1", "pt1"]}, "constraints.robust.models: name each structure once"),
    ({"types": {"XX": {}}}, "constraints.robust.types.XX"),
    ({"types": {"WT": {}}}, "constraints.robust.types.WT: no DER of this type (the DERs' "
                            "types: CHP, PV)"),
    ({"types": {"CHP": {"delay_add_s": [2, 1]}}}, "delay_add_s: the low end 2 is above"),
    ({"lag_scale": [0, 1]}, "constraints.robust.lag_scale[0]: must be a positive number"),
])
def test_a_bad_set_is_one_line(tmp_path: Path, capsys, robust, said) -> None:
    path = _config(tmp_path, robust)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert said in err and "\n" not in err and "Traceback" not in err


def test_the_set_is_part_of_the_design_and_none_changes_nothing(tmp_path: Path) -> None:
    plain = design_document(load_config(_config(tmp_path, None, "plain")))
    assert "robust" not in plain["constraints"]          # tables tuned before stay bound
    robust = design_document(load_config(_config(tmp_path)))
    assert robust["constraints"]["robust"]["types"]["CHP"]["delay_add_s"] == [0.0, 4.0]
    assert {k: v for k, v in robust["constraints"].items() if k != "robust"} \
        == plain["constraints"]


def test_the_box_maps_points_to_plants(tmp_path: Path) -> None:
    problem = TuningProblem(load_config(_config(tmp_path)))
    box = problem.box
    assert [(c.der_type, c.kind) for c in box.coordinates] == [("CHP", "lag"), ("CHP", "delay")]
    assert len(box.vertices()) == 2 * 4
    chp, pv = problem.group_types.index("CHP"), problem.group_types.index("PV")
    acts = box.actuators_of(Member("pt2", (0.5, 0.25)))
    assert acts[chp].model == acts[pv].model == "pt2"
    assert acts[chp].t_lag_s == pytest.approx(problem.actuators[chp].t_lag_s * 1.6 ** 0.5)
    assert acts[chp].t_delay_s == pytest.approx(2.0)
    assert acts[pv] .t_lag_s == problem.actuators[pv].t_lag_s            # PV as configured
    assert box.describe(Member("pt1", (1.0, 1.0))) == "pt1, CHP b 1.6, CHP dead time +4 s"
    # a dead time never goes below 0
    neg = load_config(_config(tmp_path, {"delay_add_s": [-5.0, 0.0]}, "neg"))
    p = TuningProblem(neg)
    assert all(a.t_delay_s == 0.0 for a in p.box.actuators_of(Member("pt1", (0.0,))))


def test_the_worst_member_is_no_better_than_dense_sampling(tmp_path: Path) -> None:
    """A loop tuned on the reference model alone (near both limits there), judged over the
    set: the certificate's worst disk margin and overshoot are at least as bad as a 9 x 9
    grid's per structure finds, and they are what the member they name gives."""
    config = load_config(_config(tmp_path))
    nominal = tune_subset(load_config(_config(tmp_path, None, "plain")), ("SGen5", "SGen9"))
    problem = TuningProblem(config)
    gains = problem.group_power(("SGen5", "SGen9"), nominal.w)
    wc = worst_members(problem, gains[None], np.array([nominal.kp]), np.array([nominal.ki]))
    low, high = _dense(problem, gains, nominal.kp, nominal.ki)
    assert wc.disk_margin[0] <= low + 1e-6
    assert wc.overshoot_pct[0] >= high - 1e-6
    assert wc.disk_margin[0] < problem.disk_margin_min              # it does not hold ...
    assert low < problem.disk_margin_min                            # ... on the grid either
    again = evaluate(problem.member_plant(wc.disk_margin_at[0], gains),
                     np.array([nominal.kp]), np.array([nominal.ki]), time_domain=False)
    assert again.disk_margin[0] == pytest.approx(wc.disk_margin[0])


def test_a_robust_entry_holds_on_every_sampled_member(tmp_path: Path) -> None:
    """The entry tuned over the set meets both constraints on the reference model and on
    every member of a 9 x 9 grid per structure; it is slower than the nominal entry, which
    does not hold there (the test can fail)."""
    config = load_config(_config(tmp_path))
    entry = tune_subset(config, ("SGen5", "SGen9"))
    assert entry.feasible, entry.reason
    f = entry.figures
    assert f["robust_disk_margin"] >= 1.5 and f["robust_overshoot_pct"] < 1.0
    assert f["disk_margin"] >= 1.5 and f["overshoot_pct"] < 1.0
    assert "CHP" in f["robust_disk_margin_at"] and "PV" not in f["robust_disk_margin_at"]
    problem = TuningProblem(config)
    gains = problem.group_power(("SGen5", "SGen9"), entry.w)
    low, high = _dense(problem, gains, entry.kp, entry.ki)
    assert low >= 1.5 - 1e-9 and high < 1.0
    assert low >= f["robust_disk_margin"] - 1e-6      # the certificate found the worst
    nominal = tune_subset(load_config(_config(tmp_path, None, "plain")), ("SGen5", "SGen9"))
    assert nominal.figures["rise_time_s"] < f["rise_time_s"]


def test_the_certificate_backs_off_what_the_searches_missed(tmp_path: Path) -> None:
    """With the searches' members taken away, the pair tuned is the nominal one; the
    certificate finds the members it fails on, adds them and lowers both gains until the
    entry holds over the set (dense sampling agrees)."""
    config = load_config(_config(tmp_path))
    problem = TuningProblem(config)
    problem.members.clear()
    problem._member_actuators.clear()
    nominal = tune_subset(load_config(_config(tmp_path, None, "plain")), ("SGen5", "SGen9"))
    fractions, total = problem.fractions(("SGen5", "SGen9"))
    group = PlantGroup(fractions, (("SGen5", "SGen9"),))
    (entry,) = certified_entries(problem, [group], np.array([nominal.kp * total]),
                                 np.array([nominal.ki * total]), np.array([True]), [None],
                                 np.array([np.nan]), np.array([1.0]), ["test"])
    assert entry.feasible, entry.reason
    assert entry.figures["gain_back_off"] < 1.0
    assert problem.members                                   # the worst ones were added
    gains = problem.group_power(("SGen5", "SGen9"), entry.w)
    low, high = _dense(problem, gains, entry.kp, entry.ki, n=5)
    assert low >= 1.5 - 1e-9 and high < 1.0


def _fit(model, delay, rise, spread=0.01):
    return ModelFit(model, delay, rise, (delay - spread, delay + spread),
                    (rise * (1 - spread), rise * (1 + spread)), 1.0, 0.99, 100)


def test_the_set_identify_implies_covers_the_config_and_every_fit() -> None:
    config = load_config(SIMBENCH)                # CHP 1 s / 24.57 s, WT 0.01 s / 0.515 s
    found = [("SGen5", _fit("pt1", 4.6, 25.4)), ("SGen6", _fit("pt1", 11.2, 40.0)),
             ("SGen1", _fit("pt1", 0.01, 0.3159, spread=0.0)),
             ("SGen9", _fit("pt1", 0.01, 0.1, spread=0.0))]
    robust = implied_set(config, found)
    assert robust["models"] == ["pt1"]
    chp = robust["types"]["CHP"]
    assert chp["lag_scale"][0] == 1.0 and chp["lag_scale"][1] >= 40.0 * 1.01 / 24.57
    assert chp["lag_scale"][1] < 40.0 * 1.01 / 24.57 * 1.001
    assert chp["delay_add_s"] == [0.0, pytest.approx(11.21 - 1.0, abs=1e-3)]
    assert robust["types"]["WT"]["lag_scale"][0] <= 0.3159 / 0.515
    assert robust["types"]["WT"]["lag_scale"][1] == 1.0
    assert robust["types"]["PV"] == {"lag_scale": [1.0, 1.0], "delay_add_s": [0.0, 0.0]}


def test_tune_robust_needs_a_set(tmp_path: Path, capsys) -> None:
    path = _config(tmp_path, None, "plain")
    assert main(["tune", str(path), "--robust", "--out", str(tmp_path / "t.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--robust:" in err and "no uncertainty set" in err and "\n" not in err


def test_a_robust_table_and_its_static_pair_hold_on_every_sampled_member(tmp_path: Path) -> None:
    """Every entry of a whole table tuned over the set, and the static pair on every subset,
    meets both constraints on a 5 x 5 grid of the set per structure."""
    from adnmesh.tuning import tune_table

    config = load_config(_config(tmp_path))
    table = tune_table(config, "paper", 1)
    problem = TuningProblem(config)
    static = table.static
    assert static.feasible, static.reason
    assert static.figures["robust_disk_margin"] >= 1.5
    for s in (("SGen5",), ("SGen9",), ("SGen5", "SGen9")):
        entry = table.lookup(s)
        assert entry.feasible, entry.reason
        for kp, ki, w in ((entry.kp, entry.ki, entry.w), (static.kp, static.ki, None)):
            low, high = _dense(problem, problem.group_power(s, w), kp, ki, n=5)
            assert low >= 1.5 - 1e-9 and high < 1.0, (s, kp, ki)
