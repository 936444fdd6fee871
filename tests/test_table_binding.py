"""A gain table is bound to what its gains depend on (issue 40.5): the design's DERs, delays,
constraints and conventions, not the config file's bytes; found next to the config whatever the
working directory; ``up`` keeps the table it tunes for itself and finds it again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from adnmesh.commands import up_tables
from adnmesh.config import load_config
from adnmesh.errors import ConfigError
from adnmesh.tuning.design_key import design_sha256
from adnmesh.tuning.table import (SchedulingTable, TableEntry, default_table_path, load_table,
                                  new_table, save_table)

EXAMPLE = Path(__file__).resolve().parents[1] / "configs" / "examples" / "two-wt.yaml"


def _variant(tmp_path: Path, name: str, edit=None, comment: str = "") -> Path:
    document = yaml.safe_load(EXAMPLE.read_text())
    if edit is not None:
        edit(document)
    path = tmp_path / f"{name}.yaml"
    path.write_text(comment + yaml.safe_dump(document, sort_keys=False))
    return path


def _table(config) -> SchedulingTable:
    table = new_table(config, config.constraints.model_dump(), "test")
    for ders in (("SGen1", "SGen2"), ("SGen1",)):
        table.add(TableEntry(ders, 2e-8, 1e-8, {d: 1.0 for d in ders}))
    return table


def test_edits_outside_the_design_keep_the_table(tmp_path: Path) -> None:
    base = load_config(_variant(tmp_path, "base"))
    path = tmp_path / "table.json"
    save_table(_table(base), path)

    def scenario(d):
        d["scenario"]["duration_s"] = 90
        d["scenario"]["p_ref_steps"].append({"t_s": 70, "delta_w": 5e5})

    def runtime(d):
        d["runtime"] = {"seed": 7, "links": {"cpfc_to_der": {"jitter_s": 0.01}}}

    def grid(d):
        d["grid_model"] = {"study_case": "hL", "limits": {"v_min_pu": 0.95}}

    def same_number(d):                      # 2.0e6 written as an integer: the same design
        d["ders"][0]["p_inst_w"] = 2000000

    for name, edit in [("scenario", scenario), ("runtime", runtime), ("grid", grid),
                       ("number", same_number), ("comment", None)]:
        config = load_config(_variant(tmp_path, name, edit, comment="# a note\n"))
        assert config.sha256 != base.sha256 and design_sha256(config) == design_sha256(base)
        assert load_table(path, config).lookup(["SGen1"]) is not None, name


@pytest.mark.parametrize("edit, difference", [
    (lambda d: d["ders"][1].update(t_delay_s=0.5), "ders[1].t_delay_s: 0.01 in the table, 0.5"),
    (lambda d: d["ders"][0].update(p_inst_w=1.5e6), "ders[0].p_inst_w: 2000000 in the table, "
                                                    "1500000 in the config"),
    (lambda d: d.update(t_meas_s=0.2), "t_meas_s: 0.1 in the table, 0.2 in the config"),
    (lambda d: d["constraints"].update(overshoot_max_pct=2.0),
     "constraints.overshoot_max_pct: 1 in the table, 2 in the config"),
    (lambda d: d.update(runtime={"pi_period_s": 0.1}), "design_t_com_s: 0.105 in the table"),
    (lambda d: d.update(t_rise_is="time_constant"), "t_rise_is: 'rise_time' in the table"),
])
def test_a_design_change_refuses_the_table_naming_the_difference(tmp_path, edit, difference):
    base = load_config(_variant(tmp_path, "base"))
    path = tmp_path / "table.json"
    save_table(_table(base), path)
    changed = load_config(_variant(tmp_path, "changed", edit))
    assert design_sha256(changed) != design_sha256(base)
    with pytest.raises(ConfigError, match="tuned for another design") as refused:
        load_table(path, changed)
    assert difference in str(refused.value) and "\n" not in str(refused.value)


def test_an_edited_design_or_an_old_table_without_one(tmp_path: Path) -> None:
    config = load_config(_variant(tmp_path, "base"))
    path = tmp_path / "table.json"
    document = _table(config).to_json()
    document["design"]["t_com_s"] = 0.2           # made to match another config by hand
    path.write_text(json.dumps(document))
    with pytest.raises(ConfigError, match="design_sha256: .* is not the design's"):
        load_table(path, config)
    old = _table(config)
    old.design = None                             # a table written before designs were kept
    save_table(old, path)
    assert "design" not in json.loads(path.read_text())
    assert load_table(path, config).design is None
    other = load_config(_variant(tmp_path, "other", comment="# only a comment\n"))
    with pytest.raises(ConfigError, match="bound to the file"):
        load_table(path, other)


def test_the_default_table_is_next_to_the_config(tmp_path: Path, monkeypatch) -> None:
    config = load_config(_variant(tmp_path, "site"))
    monkeypatch.chdir("/")
    expected = tmp_path / "tables" / f"site.{design_sha256(config)[:12]}.json"
    assert default_table_path(config) == expected


def test_up_keeps_the_table_it_tuned_and_finds_it_again(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ADNMESH_CACHE_DIR", str(tmp_path / "cache"))
    said: list[str] = []
    config = load_config(_variant(tmp_path, "kept"))
    first = up_tables.table_for(None, config, tmp_path, "run1", said.append)
    assert first.parent == tmp_path / "cache" / "tables" and "tuning the 2 subset" in said[0]
    said.clear()
    # the scenario's steps and a comment change, not its subsets: the same table, not tuned
    moved = load_config(_variant(tmp_path, "kept", lambda d: d["scenario"]["p_ref_steps"][0]
                                 .update(delta_w=5e5), comment="# moved step\n"))
    assert up_tables.table_for(None, moved, tmp_path, "run2", said.append) == first
    assert said == [f"gain table {first}: tuned by an earlier run for this design and scenario"]
    # another subset in the scenario: tuned again, kept apart
    said.clear()
    more = load_config(_variant(tmp_path, "kept", lambda d: d["scenario"]["availability"]
                                .__setitem__(0, {"t_s": 20, "available": False,
                                                 "ders": ["SGen1"]})))
    other = up_tables.table_for(None, more, tmp_path, "run3", said.append)
    assert other != first and other.exists() and "tuning the 2 subset" in said[0]
    # a damaged kept table is said and tuned again, never used
    first.write_text("{")
    said.clear()
    assert up_tables.table_for(None, moved, tmp_path, "run4", said.append) == first
    assert said[0].startswith("not using the tuned gain table an earlier run kept: ")
    assert load_table(first, moved).lookup(["SGen1", "SGen2"]) is not None
