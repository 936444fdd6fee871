"""On-demand tuning of large configs: the per-type design plant and the size limit (fast)."""
from __future__ import annotations

from pathlib import Path

import pytest

from adnmesh.config import load_config
from adnmesh.errors import UsageError
from adnmesh.tuning import TuningProblem
from adnmesh.tuning import ondemand
from adnmesh.tuning.ondemand import OnDemandTuner


@pytest.fixture(scope="module")
def adn100(configs_dir: Path):
    return load_config(configs_dir / "examples" / "adn-100.yaml")


def test_dynamics_spread_per_der_get_one_design_group_per_type(adn100) -> None:
    exact = TuningProblem(adn100)
    design = TuningProblem(adn100, by_type=True)
    assert len(exact.actuators) > ondemand.MAX_EXACT_CLASSES
    assert len(design.actuators) == len({d.type for d in adn100.ders}) == 3
    for act in design.actuators:                    # delays a multiple of 10 ms
        assert abs(act.t_delay_s * 100 - round(act.t_delay_s * 100)) < 1e-9
    wts = [d for d in adn100.ders if d.type == "WT"]
    lag = sum(d.p_inst_w * adn100.t_lag_s(d) for d in wts) / sum(d.p_inst_w for d in wts)
    assert design.actuators[design.group_of[wts[0].id]].t_lag_s == pytest.approx(lag)
    tuner = OnDemandTuner(adn100)
    assert tuner.design.actuators == design.actuators and tuner.problem.actuators == \
        exact.actuators


def test_a_subset_too_large_is_refused_in_one_line(adn100, monkeypatch) -> None:
    monkeypatch.setattr(ondemand, "MAX_DERS", 50)
    with pytest.raises(UsageError, match="too large to tune on demand"):
        OnDemandTuner(adn100).tune(adn100.der_ids())
