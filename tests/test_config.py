"""Tests of adnmesh.config: the reference case, the examples and every class of invalid input.

Invalid inputs go through the command line (``adnmesh check``) so that what is tested is what a
user sees: exit code 2 and one line naming the file and the key path.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from pathlib import Path

import jsonschema
import pytest
import yaml
from pydantic import ValidationError

from adnmesh.cli import main
from adnmesh.config import PT1_RISE_TIME_FACTOR, Config, ConfigFile, load_config, load_hierarchy
from adnmesh.errors import ConfigError

_CONFIGS_DIR = Path(__file__).resolve().parent.parent / "configs"
_ALL = sorted(p for p in _CONFIGS_DIR.rglob("*.yaml")       # not what a run wrote there: the
              if not any(part.endswith("-upper")           # upper level of adnmesh cascade
                         for part in p.relative_to(_CONFIGS_DIR).parts))   # or up (git-ignored)
#: hierarchy files (adnmesh cascade) live in configs/examples/hierarchy/
HIERARCHIES = [p for p in _ALL if p.parent.name == "hierarchy"]
CONFIGS = [p for p in _ALL if p not in HIERARCHIES]

# docs/method.md#reference-case: id -> (type, P_inst [W], T_delay [s], T_rise [s])
REFERENCE_TABLE = {
    "SGen1": ("WT", 2.0e6, 0.01, 0.515),
    "SGen2": ("WT", 2.0e6, 0.01, 0.515),
    "SGen3": ("WT", 1.7e6, 0.01, 0.515),
    "SGen4": ("WT", 1.9e6, 0.01, 0.515),
    "SGen5": ("CHP", 0.31e6, 1.0, 24.57),
    "SGen6": ("CHP", 0.35e6, 1.0, 24.57),
    "SGen7": ("WT", 1.8e6, 0.01, 0.515),
    "SGen8": ("WT", 2.0e6, 0.01, 0.515),
    "SGen9": ("PV", 0.195e6, 0.01, 0.1),
    "SGen10": ("PV", 0.125e6, 0.01, 0.1),
    "SGen11": ("CHP", 0.28e6, 1.0, 24.57),
}


# --- the reference case ----------------------------------------------------------------------


def test_simbench_config_has_the_eleven_ders_of_spec_section_6(simbench_config: Config) -> None:
    assert simbench_config.der_ids() == tuple(REFERENCE_TABLE)
    for der in simbench_config.ders:
        assert (der.type, der.p_inst_w, der.t_delay_s, der.t_rise_s) == REFERENCE_TABLE[der.id]
        # study case lW: the WTs run at half their installed power, CHP and PV at 0 W
        assert der.p_sched_w == (0.5 * der.p_inst_w if der.type == "WT" else 0.0)


def test_simbench_config_delays_constraints_and_grid(simbench_config: Config) -> None:
    assert simbench_config.t_com_s == 0.1
    assert simbench_config.t_meas_s == 0.1
    assert simbench_config.simbench_code == "1-MV-rural--0-no_sw"
    assert simbench_config.grid == "simbench-1-MV-rural"
    c = simbench_config.constraints
    assert (c.disk_margin_min, c.overshoot_max_pct, c.settling_band_pct) == (1.5, 1.0, 5.0)


def test_simbench_scenario_is_the_papers_demonstration(simbench_config: Config) -> None:
    scenario = simbench_config.scenario
    assert scenario.duration_s == 600.0
    assert [(s.t_s, s.delta_w) for s in scenario.p_ref_steps] == [
        (20.0, 1e6),
        (100.0, -1e6),
        (200.0, 1e6),
        (420.0, -1e6),
    ]
    (change,) = scenario.availability
    assert change.t_s == 170.0 and change.available is False
    wind = {der.id for der in simbench_config.ders if der.type == "WT"}
    assert set(change.ders) == wind and len(wind) == 6


def test_t_lag_is_rise_time_over_ln9(simbench_config: Config) -> None:
    wt = simbench_config.ders[0]
    assert PT1_RISE_TIME_FACTOR == pytest.approx(2.197, abs=5e-4)
    assert simbench_config.t_lag_s(wt) == pytest.approx(0.515 / math.log(9.0), rel=1e-15)
    # a PT1 with this time constant reaches 10 % and 90 % exactly t_rise_s apart
    lag = simbench_config.t_lag_s(wt)
    t10, t90 = -lag * math.log(0.9), -lag * math.log(0.1)
    assert t90 - t10 == pytest.approx(wt.t_rise_s, rel=1e-12)


def test_sha256_is_of_the_file_bytes(simbench_config: Config, configs_dir: Path) -> None:
    expected = hashlib.sha256((configs_dir / "simbench.yaml").read_bytes()).hexdigest()
    assert simbench_config.sha256 == expected


def test_config_is_frozen(simbench_config: Config) -> None:
    with pytest.raises(ValidationError, match="frozen"):
        simbench_config.t_com_s = 0.2  # type: ignore[misc]
    with pytest.raises(ValidationError, match="frozen"):
        simbench_config.ders[0].p_inst_w = 1.0  # type: ignore[misc]
    assert isinstance(simbench_config.ders, tuple)
    assert isinstance(simbench_config.scenario.p_ref_steps, tuple)


def test_configs_compare_and_hash_by_value(simbench_config: Config, configs_dir: Path) -> None:
    again = load_config(configs_dir / "simbench.yaml")
    assert again == simbench_config and hash(again) == hash(simbench_config)
    assert len({*simbench_config.ders, *again.ders}) == 11
    changed = again.model_copy(update={"t_com_s": 0.2})
    assert changed != simbench_config and changed.t_com_s == 0.2 and again.t_com_s == 0.1


def test_dump_validates_back_to_the_same_config(simbench_config: Config) -> None:
    content = simbench_config.model_dump(exclude={"path", "sha256", "quantity"})
    assert set(content) == set(ConfigFile.model_fields)
    assert dict(ConfigFile.model_validate(content)) == {
        key: value for key, value in simbench_config if key in ConfigFile.model_fields}


def test_integers_are_read_as_floats(simbench_config: Config) -> None:
    step = simbench_config.scenario.p_ref_steps[0]          # t_s: 20 in the file
    assert type(step.t_s) is float and step.t_s == 20.0
    assert type(simbench_config.runtime.seed) is int


def test_ders_by_id_keeps_the_requested_order(simbench_config: Config) -> None:
    ders = simbench_config.ders_by_id(["SGen9", "SGen1"])
    assert [d.id for d in ders] == ["SGen9", "SGen1"]


def test_ders_by_id_rejects_an_unknown_id(simbench_config: Config) -> None:
    with pytest.raises(ConfigError, match=r"^unknown DER id 'SGen12' \(known: SGen1, SGen2, "):
        simbench_config.ders_by_id(["SGen1", "SGen12"])


def test_simbench_sgen_mapping_matches_the_grid(simbench_config: Config) -> None:
    """Each DER drives an MV static generator of its type whose p_mw equals its P_inst."""
    import simbench
    net = simbench.get_simbench_net(simbench_config.simbench_code)
    sgen = net.sgen.set_index("name")
    simbench_type = {"WT": "Wind_MV", "CHP": "Biomass_MV", "PV": "PV_MV"}
    for der in simbench_config.ders:
        row = sgen.loc[der.sgen]
        assert row["type"] == simbench_type[der.type], der.id
        assert row["p_mw"] * 1e6 == pytest.approx(der.p_inst_w, rel=1e-12), der.id
        assert net.bus.loc[row["bus"], "vn_kv"] == 20.0, der.id


@pytest.mark.parametrize("path", CONFIGS, ids=lambda path: path.name)
def test_every_config_in_configs_loads_and_names_its_schema(path: Path, configs_dir: Path) -> None:
    """Every config is valid for the loader and for its JSON Schema (an independent validator),
    and names the schema on its first line for editors with the YAML language server."""
    config = load_config(path)
    assert config.path == path and config.ders
    names_its_schema(path, configs_dir / "config.schema.json")


@pytest.mark.parametrize("path", HIERARCHIES, ids=lambda path: path.name)
def test_every_hierarchy_file_loads_and_names_its_schema(path: Path, configs_dir: Path) -> None:
    """Every hierarchy file is valid for the loader and its JSON Schema, names the schema on
    its first line, and every ADN's config loads."""
    hierarchy = load_hierarchy(path)
    assert hierarchy.adns
    for adn in hierarchy.adns:
        assert load_config(hierarchy.config_path(adn)).ders
    names_its_schema(path, configs_dir / "hierarchy.schema.json")


def names_its_schema(path: Path, schema_path: Path) -> None:
    """``path`` names ``schema_path`` on its first line for the YAML language server, and is
    valid for it (an independent validator)."""
    first_line = path.read_text().splitlines()[0]
    prefix = "# yaml-language-server: $schema="
    assert first_line.startswith(prefix)
    assert (path.parent / first_line.removeprefix(prefix)).resolve() == schema_path
    schema = json.loads(schema_path.read_text())
    jsonschema.Draft202012Validator(schema).validate(yaml.safe_load(path.read_text()))


@pytest.mark.parametrize("name", ["two-wt", "wt-chp", "mixed-4", "chp-pv"])
def test_example_configs_load(configs_dir: Path, simbench_config: Config, name: str) -> None:
    config = load_config(configs_dir / "examples" / f"{name}.yaml")
    # the examples' DERs are those of the reference case (their schedules are their own)
    unscheduled = {"p_sched_w": 0.0}
    reference = {der.id: der.model_copy(update=unscheduled) for der in simbench_config.ders}
    assert config.t_com_s == config.t_meas_s == 0.1
    assert config.constraints == simbench_config.constraints
    assert all(der.model_copy(update=unscheduled) == reference[der.id] for der in config.ders)
    assert config.scenario.p_ref_steps


def test_optional_sections_take_their_defaults(tmp_path: Path, simbench_document: dict) -> None:
    document = copy.deepcopy(simbench_document)
    del document["constraints"]
    del document["scenario"]["availability"]
    document["ders"][0]["t_delay_s"] = 0  # a DER without reaction time is allowed
    path = tmp_path / "defaults.yaml"
    path.write_text(yaml.safe_dump(document))
    config = load_config(path)
    assert config.constraints.disk_margin_min == 1.5
    assert config.scenario.availability == ()
    assert config.ders[0].t_delay_s == 0.0


def test_exponent_without_sign_is_a_number(tmp_path: Path, configs_dir: Path) -> None:
    """PyYAML alone reads ``2.0e6`` as a string (YAML 1.1); adnmesh reads it as 2e6."""
    text = (configs_dir / "simbench.yaml").read_text().replace("2.0e+6", "2.0e6")
    path = tmp_path / "exponent.yaml"
    path.write_text(text)
    assert load_config(path).ders[0].p_inst_w == 2.0e6


# --- invalid input: exit code 2 and one line naming file and key path ----------------------------


@pytest.fixture(scope="session")
def simbench_document(configs_dir: Path) -> dict:
    """The reference config as plain data, to be broken by the tests below."""
    return yaml.safe_load((configs_dir / "simbench.yaml").read_text())


def _locate(doc, path: str):
    """Return the container and the last key of a dotted key path (``ders.3.p_inst_w``)."""
    *parents, last = [int(k) if k.isdigit() else k for k in path.split(".")]
    for key in parents:
        doc = doc[key]
    return doc, last


def _set(path: str, value):
    """Return a mutation that sets the value at ``path``."""

    def mutate(doc):
        container, last = _locate(doc, path)
        container[last] = value

    return mutate


def _delete(path: str):
    """Return a mutation that removes the key at ``path``."""

    def mutate(doc):
        container, last = _locate(doc, path)
        del container[last]

    return mutate


def _rename(path: str, new_key: str):
    """Return a mutation that renames the key at ``path`` (keeping its value)."""

    def mutate(doc):
        container, last = _locate(doc, path)
        container[new_key] = container.pop(last)

    return mutate


# (mutation, expected message after "<file>: ")
INVALID = {
    "missing key": (_delete("ders.3.p_inst_w"), "ders[3].p_inst_w: required key is missing"),
    "missing section": (_delete("scenario"), "scenario: required key is missing"),
    "wrong type": (
        _set("ders.3.p_inst_w", "lots"),
        "ders[3].p_inst_w: must be a number, got 'lots'",
    ),
    "boolean as number": (_set("t_com_s", True), "t_com_s: must be a number, got true"),
    "list as mapping": (_set("constraints", [1.5]), "constraints: must be a mapping, got a list"),
    "negative power": (
        _set("ders.3.p_inst_w", -2),
        "ders[3].p_inst_w: must be a positive number, got -2",
    ),
    "zero rise time": (
        _set("ders.0.t_rise_s", 0),
        "ders[0].t_rise_s: must be a positive number, got 0",
    ),
    "negative delay": (
        _set("ders.5.t_delay_s", -0.5),
        "ders[5].t_delay_s: must be a non-negative number, got -0.5",
    ),
    "zero T_com": (_set("t_com_s", 0), "t_com_s: must be a positive number, got 0"),
    "negative T_meas": (_set("t_meas_s", -0.1), "t_meas_s: must be a positive number, got -0.1"),
    "infinite duration": (
        _set("scenario.duration_s", float("inf")),
        "scenario.duration_s: must be a finite number, got inf",
    ),
    "unknown DER type": (
        _set("ders.2.type", "Wind"),
        "ders[2].type: must be one of 'WT', 'CHP', 'PV', 'HYDRO' or 'GEN', got 'Wind'",
    ),
    "id unusable as a bus key": (
        _set("ders.2.id", "SGen/3"),
        "ders[2].id: must be an identifier (letters, digits, '_', '-'; starting with a letter), "
        "got 'SGen/3'",
    ),
    "no DERs": (_set("ders", []), "ders: must have at least 1 item(s), got 0"),
    "duplicate DER id": (
        _set("ders.4.id", "SGen1"),
        "ders[4].id: duplicate DER id 'SGen1' (also ders[0].id)",
    ),
    "duplicate sgen": (
        _set("ders.1.sgen", "MV1.101 SGen 1"),
        "ders[1].sgen: duplicate sgen 'MV1.101 SGen 1' (also ders[0].sgen)",
    ),
    "schedule above P_inst": (
        _set("ders.8.p_sched_w", 2e5),
        "ders[8].p_sched_w: must not exceed p_inst_w (195000), got 200000",
    ),
    "scenario names an unknown DER": (
        _set("scenario.availability.0.ders.2", "SGen99"),
        "scenario.availability[0].ders[2]: unknown DER id 'SGen99' (known: SGen1, SGen2, SGen3, "
        "SGen4, SGen5, SGen6, SGen7, SGen8, SGen9, SGen10, SGen11)",
    ),
    "scenario names a DER twice": (
        _set("scenario.availability.0.ders.2", "SGen1"),
        "scenario.availability[0].ders[2]: duplicate DER id 'SGen1' "
        "(also scenario.availability[0].ders[0])",
    ),
    "availability not a boolean": (
        _set("scenario.availability.0.available", "no"),
        "scenario.availability[0].available: must be true or false, got 'no'",
    ),
    "zero step": (
        _set("scenario.p_ref_steps.1.delta_w", 0),
        "scenario.p_ref_steps[1].delta_w: must be a non-zero number, got 0",
    ),
    "event after the end": (
        _set("scenario.p_ref_steps.3.t_s", 700),
        "scenario.p_ref_steps[3].t_s: must not exceed scenario.duration_s (600), got 700",
    ),
    "events out of order": (
        _set("scenario.p_ref_steps.2.t_s", 50),
        "scenario.p_ref_steps[2].t_s: must not be earlier than the previous event (100), got 50",
    ),
    "typo in a DER key": (
        _rename("ders.2.p_inst_w", "p_inst"),
        "ders[2].p_inst: unknown key (did you mean 'p_inst_w'?)",
    ),
    "typo in a section name": (
        _rename("scenario", "scenaro"),
        "scenaro: unknown key (did you mean 'scenario'?)",
    ),
    "typo in a constraint": (
        _rename("constraints.overshoot_max_pct", "overshot_max_pct"),
        "constraints.overshot_max_pct: unknown key (did you mean 'overshoot_max_pct'?)",
    ),
    "maintenance of an unknown DER": (
        _set("study", {"maintenance": [{"ders": ["SGen99"], "start": "2016-01-01",
                                        "end": "2016-01-02"}]}),
        "study.maintenance[0].ders[0]: unknown DER id 'SGen99' (known: SGen1, SGen2, SGen3, "
        "SGen4, SGen5, SGen6, SGen7, SGen8, SGen9, SGen10, SGen11)",
    ),
    "maintenance ending before it starts": (
        _set("study", {"maintenance": [{"ders": ["SGen1"], "start": "2016-01-02",
                                        "end": "2016-01-01T12:00"}]}),
        "study.maintenance[0].end: must be after start (2016-01-02), got 2016-01-01T12:00",
    ),
    "maintenance on a day that does not exist": (
        _set("study", {"maintenance": [{"ders": ["SGen1"], "start": "2016-02-30",
                                        "end": "2016-03-02"}]}),
        "study.maintenance[0].start: must be a date or time that exists, got 2016-02-30",
    ),
    "no ICT at all": (
        _set("study", {"ict_availability": 0}),
        "study.ict_availability: must be a positive number, got 0",
    ),
    "unknown section": (
        _set("power_flow", {"solver": "nr"}),
        "power_flow: unknown key (valid keys: grid, simbench_code, t_com_s, t_meas_s, "
        "constraints, ders, scenario, runtime, grid_model, reactive, study, t_rise_is, extends)",
    ),
    "disk margin out of range": (
        _set("constraints.disk_margin_min", 2.5),
        "constraints.disk_margin_min: must be less than 2, got 2.5",
    ),
    "overshoot limit zero": (
        _set("constraints.overshoot_max_pct", 0),
        "constraints.overshoot_max_pct: must be a positive number, got 0",
    ),
    "settling band too wide": (
        _set("constraints.settling_band_pct", 60),
        "constraints.settling_band_pct: must be at most 50, got 60",
    ),
    # values YAML can hold that are not what a key expects
    "null for a name": (_set("grid", None), "grid: must be a string, got nothing (null)"),
    "number for a name": (_set("ders.0.sgen", 5), "ders[0].sgen: must be a string, got 5"),
    "empty name": (_set("ders.0.sgen", ""), "ders[0].sgen: must not be empty"),
    "numeric string": (
        _set("scenario.p_ref_steps.0.t_s", "20"),
        "scenario.p_ref_steps[0].t_s: must be a number, got '20'",
    ),
    "NaN": (_set("t_meas_s", float("nan")), "t_meas_s: must be a finite number, got nan"),
    "minus infinity": (
        _set("ders.0.p_inst_w", float("-inf")),
        "ders[0].p_inst_w: must be a finite number, got -inf",
    ),
    "huge integer": (
        _set("t_com_s", 10**400),
        "t_com_s: must be a number, got 1000000000000000000000000000000000000...",
    ),
    "mapping as list": (_set("ders", {"SGen1": 1}), "ders: must be a list, got a mapping"),
    "string as list": (_set("ders", "SGen1"), "ders: must be a list, got 'SGen1'"),
    "list as section": (_set("scenario", [600]), "scenario: must be a mapping, got a list"),
    "id with a newline": (
        _set("ders.0.id", "SGen1\n"),
        "ders[0].id: must be an identifier (letters, digits, '_', '-'; starting with a letter), "
        "got 'SGen1\\n'",
    ),
    "no DERs in a change": (
        _set("scenario.availability.0.ders", []),
        "scenario.availability[0].ders: must have at least 1 item(s), got 0",
    ),
    "key that is not a string": (
        lambda doc: doc.update({5: 1}),
        "5: unknown key (valid keys: grid, simbench_code, t_com_s, t_meas_s, constraints, ders, "
        "scenario, runtime, grid_model, reactive, study, t_rise_is, extends)",
    ),
    # upper bounds
    "more than 1000 DERs": (
        lambda doc: doc.update(ders=[dict(doc["ders"][0], id=f"D{i}", sgen=f"s{i}")
                                     for i in range(1001)]),
        "ders: must have at most 1000 items, got 1001",
    ),
    "long DER id": (
        _set("ders.0.id", "A" * 65),
        "ders[0].id: must have at most 64 characters, got "
        "'AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA...'",
    ),
    "long sgen": (
        _set("ders.0.sgen", "x" * 201),
        "ders[0].sgen: must have at most 200 characters, got "
        "'xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx...'",
    ),
    "huge P_inst": (
        _set("ders.0.p_inst_w", 2e10),
        "ders[0].p_inst_w: must be at most 1e+10, got 20000000000.0",
    ),
    "huge schedule": (
        _set("ders.0.p_sched_w", 2e10),
        "ders[0].p_sched_w: must be at most 1e+10, got 20000000000.0",
    ),
    "huge step": (
        _set("scenario.p_ref_steps.0.delta_w", -2e10),
        "scenario.p_ref_steps[0].delta_w: must be at least -1e+10, got -20000000000.0",
    ),
    "reaction time over an hour": (
        _set("ders.0.t_delay_s", 3601),
        "ders[0].t_delay_s: must be at most 3600, got 3601",
    ),
    "rise time over an hour": (
        _set("ders.0.t_rise_s", 3601),
        "ders[0].t_rise_s: must be at most 3600, got 3601",
    ),
    "T_com over an hour": (_set("t_com_s", 3601), "t_com_s: must be at most 3600, got 3601"),
    "T_meas over an hour": (_set("t_meas_s", 4e3), "t_meas_s: must be at most 3600, got 4000.0"),
    "scenario too long": (
        _set("scenario.duration_s", 2e6),
        "scenario.duration_s: must be at most 1e+06, got 2000000.0",
    ),
    "too many DERs in a change": (
        _set("scenario.availability.0.ders", ["SGen1"] * 1001),
        "scenario.availability[0].ders: must have at most 1000 items, got 1001",
    ),
}


# cases the JSON Schema cannot state: relations between values and NaN (which compares false
# with every bound); and one that jsonschema misses: its regexes are Python's, whose '$' also
# matches before a final newline (ECMA 262's, which JSON Schema specifies, does not)
NOT_IN_SCHEMA = {"duplicate DER id", "duplicate sgen", "schedule above P_inst", "NaN",
                 "scenario names an unknown DER", "scenario names a DER twice",
                 "event after the end", "events out of order", "id with a newline",
                 "maintenance of an unknown DER", "maintenance ending before it starts",
                 "maintenance on a day that does not exist"}


@pytest.mark.parametrize("case", [case for case in INVALID if case not in NOT_IN_SCHEMA])
def test_the_json_schema_rejects_what_the_loader_rejects(case: str, configs_dir: Path,
                                                         simbench_document: dict) -> None:
    schema = json.loads((configs_dir / "config.schema.json").read_text())
    document = copy.deepcopy(simbench_document)
    INVALID[case][0](document)
    assert not jsonschema.Draft202012Validator(schema).is_valid(document)


def _check(path: Path, capsys) -> tuple[int, str]:
    code = main(["check", str(path)])
    captured = capsys.readouterr()
    return code, captured.err


@pytest.mark.parametrize("case", list(INVALID))
def test_invalid_config_is_one_line_naming_file_and_key(
    case: str, tmp_path: Path, simbench_document: dict, capsys
) -> None:
    mutate, expected = INVALID[case]
    document = copy.deepcopy(simbench_document)
    mutate(document)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    code, err = _check(path, capsys)
    assert code == 2
    assert err == f"adnmesh: error: {path}: {expected}\n"
    assert not any(word in err for word in ("pydantic", "Input should", "http")), err


# (file content or None for a missing file, expected message after "<file>: ")
INVALID_FILES = {
    "missing file": (None, "no such file"),
    "YAML syntax error": (
        "grid: simbench-1-MV-rural\nders: [\n  {id: SGen1\nt_com_s: 0.1\n",
        "line 4, column 8: invalid YAML: ",
    ),
    "YAML indentation error": ("grid: x\n t_com_s: 0.1\n", "line 2, column 9: invalid YAML: "),
    "duplicate YAML key": (
        "grid: x\nt_com_s: 0.1\nt_com_s: 0.2\n",
        "line 3, column 1: invalid YAML: duplicate key 't_com_s'",
    ),
    "empty file": ("# nothing here\n", "empty config (expected a mapping with keys: grid, "),
    "top level is a list": ("- grid\n", "top level: must be a mapping, got a list"),
    "top level is a string": ("hello\n", "top level: must be a mapping, got 'hello'"),
    "only a document marker": ("---\n", "empty config (expected a mapping with keys: grid, "),
    "not UTF-8": (b"grid: \xff\xfe\n", "not UTF-8 text (byte 6)"),
    "Python object tag": (
        "grid: !!python/object/apply:os.system [ls]\n",
        "line 1, column 7: invalid YAML: could not determine a constructor for the tag",
    ),
    "undefined alias": ("grid: *name\n", "line 1, column 7: invalid YAML: found undefined alias"),
    "YAML infinity": (
        "grid: x\nsimbench_code: y\nt_com_s: .inf\n",
        "t_com_s: must be a finite number, got inf",
    ),
    "YAML not-a-number": (
        "grid: x\nsimbench_code: y\nt_com_s: .NaN\n",
        "t_com_s: must be a finite number, got nan",
    ),
}


@pytest.mark.parametrize("case", list(INVALID_FILES))
def test_unreadable_config_is_one_line_naming_the_file(case: str, tmp_path: Path, capsys) -> None:
    content, expected = INVALID_FILES[case]
    path = tmp_path / "bad.yaml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    code, err = _check(path, capsys)
    assert code == 2
    assert err.startswith(f"adnmesh: error: {path}: {expected}")
    assert err.count("\n") == 1 and err.endswith("\n")


def test_a_directory_is_not_a_config(tmp_path: Path, capsys) -> None:
    code, err = _check(tmp_path, capsys)
    assert (code, err) == (2, f"adnmesh: error: {tmp_path}: is a directory, not a config file\n")


def test_load_config_raises_config_error_with_the_same_message(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("grid: x\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: t_com_s: required key is missing"


# --- the optional runtime section (adnmesh up) ---------------------------------------------------


def test_runtime_section_is_optional_with_defaults(simbench_config: Config) -> None:
    from adnmesh.config import Runtime

    runtime = simbench_config.runtime
    assert runtime == Runtime(der_models="detailed")          # the only key simbench.yaml sets
    assert (runtime.seed, runtime.pi_period_s, runtime.measurement_period_s) == (0, 0.01, 0.01)
    assert runtime.links.cpfc_to_der.delay_s is None          # the config's t_com_s
    assert runtime.links.der_to_availability.delay_s == 0.1
    assert runtime.faults == () and runtime.measurement_timeout_s == 0.25


def test_runtime_section_is_read(tmp_path: Path, simbench_document: dict) -> None:
    document = copy.deepcopy(simbench_document)
    document["runtime"] = {
        "seed": 42, "pi_period_s": 0.02, "rest_of_grid_w": -1.5e6,
        "links": {"cpfc_to_der": {"jitter_s": 0.01, "loss": 0.1,
                                  "outages": [{"t_s": 5, "duration_s": 2}]},
                  "der_to_availability": {"jitter_s": 0.05}},
        "faults": [{"kind": "der_offline", "der": "SGen3", "t_s": 10, "duration_s": 4},
                   {"kind": "kill", "agent": "der/SGen4", "t_s": 30, "restart_after_s": 2},
                   {"kind": "link_loss", "link": "cpfc_to_der", "probability": 0.3, "t_s": 40},
                   {"kind": "link_delay", "link": "measurement_to_cpfc", "delay_s": 0.5,
                    "t_s": 50, "duration_s": 1},
                   {"kind": "ict_outage", "t_s": 60, "duration_s": 2},
                   {"kind": "link_outage", "link": "der_to_availability", "t_s": 70}],
    }
    path = tmp_path / "runtime.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    runtime = load_config(path).runtime
    assert (runtime.seed, runtime.pi_period_s, runtime.rest_of_grid_w) == (42, 0.02, -1.5e6)
    link = runtime.links.cpfc_to_der
    assert (link.delay_s, link.jitter_s, link.loss, link.fifo) == (None, 0.01, 0.1, True)
    assert (link.outages[0].t_s, link.outages[0].duration_s) == (5.0, 2.0)
    heartbeat = runtime.links.der_to_availability
    assert (heartbeat.delay_s, heartbeat.jitter_s) == (0.1, 0.05)   # default delay kept
    offline, kill, loss, delay, ict, outage = runtime.faults
    assert (offline.kind, offline.der, offline.duration_s) == ("der_offline", "SGen3", 4.0)
    assert (kill.agent, kill.restart_after_s, kill.duration_s) == ("der/SGen4", 2.0, None)
    assert (loss.probability, loss.duration_s, delay.delay_s) == (0.3, None, 0.5)
    assert (ict.kind, outage.link) == ("ict_outage", "der_to_availability")


def test_at_most_100000_events_per_list(tmp_path: Path, simbench_document: dict, capsys) -> None:
    document = copy.deepcopy(simbench_document)
    document["scenario"]["p_ref_steps"] = "STEPS"
    steps = "[&step {t_s: 1, delta_w: 1.0e+5}" + ", *step" * 100_000 + "]"   # 100,001 steps
    path = tmp_path / "many.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False).replace("STEPS", steps))
    code, err = _check(path, capsys)
    assert code == 2
    assert err == (f"adnmesh: error: {path}: scenario.p_ref_steps: must have at most 100000 "
                   "items, got 100001\n")


def test_runtime_example_config_loads(configs_dir: Path) -> None:
    config = load_config(configs_dir / "examples" / "runtime-step.yaml")
    assert (config.runtime.seed, config.runtime.rest_of_grid_w) == (7, -3e6)
    assert config.ders[1].p_sched_w == 0.5e6


RUNTIME_INVALID = {
    "unknown runtime key": ({"clock": "sim"}, "runtime.clock: unknown key (valid keys: seed, "),
    "negative seed": ({"seed": -1}, "runtime.seed: must be a non-negative number, got -1"),
    "fractional seed": ({"seed": 1.5}, "runtime.seed: must be an integer, got 1.5"),
    "boolean seed": ({"seed": True}, "runtime.seed: must be an integer, got true"),
    "string seed": ({"seed": "7"}, "runtime.seed: must be an integer, got '7'"),
    "seed beyond int64": ({"seed": 2**63},
                          "runtime.seed: must be at most 9223372036854775807, got "
                          "9223372036854775808"),
    "zero period": ({"pi_period_s": 0}, "runtime.pi_period_s: must be at least 1e-06, got 0"),
    "period over an hour": ({"heartbeat_period_s": 3601},
                            "runtime.heartbeat_period_s: must be at most 3600, got 3601"),
    "huge rest of the grid": ({"rest_of_grid_w": -1e11},
                              "runtime.rest_of_grid_w: must be at least -1e+10, got "
                              "-100000000000.0"),
    "loss of one": ({"links": {"measurement_to_cpfc": {"loss": 1.0}}},
                    "runtime.links.measurement_to_cpfc.loss: must be less than 1, got 1.0"),
    "negative loss": ({"links": {"der_to_availability": {"loss": -0.1}}},
                      "runtime.links.der_to_availability.loss: must be a non-negative number, "
                      "got -0.1"),
    "fifo not a boolean": ({"links": {"der_to_availability": {"fifo": "yes"}}},
                           "runtime.links.der_to_availability.fifo: must be true or false, "
                           "got 'yes'"),
    "typo in a link key": ({"links": {"cpfc_to_der": {"jiter_s": 0.1}}},
                           "runtime.links.cpfc_to_der.jiter_s: unknown key (did you mean "
                           "'jitter_s'?)"),
    "jitter over an hour": ({"links": {"cpfc_to_der": {"jitter_s": 4000}}},
                            "runtime.links.cpfc_to_der.jitter_s: must be at most 3600, got 4000"),
    "delay over an hour": ({"links": {"der_to_availability": {"delay_s": 4000}}},
                           "runtime.links.der_to_availability.delay_s: must be at most 3600, "
                           "got 4000"),
    "null delay": ({"links": {"availability_to_cpfc": {"delay_s": None}}},
                   "runtime.links.availability_to_cpfc.delay_s: must be a number, "
                   "got nothing (null)"),
    "delay of a fixed link": ({"links": {"cpfc_to_der": {"delay_s": 0.2}}},
                              "runtime.links.cpfc_to_der.delay_s: unknown key (this link's delay "
                              "is t_com_s)"),
    "delay of the measurement link": ({"links": {"measurement_to_cpfc": {"delay_s": 0}}},
                                      "runtime.links.measurement_to_cpfc.delay_s: unknown key "
                                      "(this link's delay is t_meas_s)"),
    "outage longer than any scenario": (
        {"links": {"der_to_availability": {"outages": [{"t_s": 0, "duration_s": 2e6}]}}},
        "runtime.links.der_to_availability.outages[0].duration_s: must be at most 1e+06, "
        "got 2000000.0"),
    "offline longer than any scenario": (
        {"faults": [{"kind": "der_offline", "der": "SGen1", "t_s": 1, "duration_s": 2e6}]},
        "runtime.faults[0].duration_s: must be at most 1e+06, got 2000000.0"),
    "kill of a DER without id": (
        {"faults": [{"kind": "kill", "agent": "der/", "t_s": 1}]},
        "runtime.faults[0].agent: must be cpfc, measurement, availability or der/<id>, "
        "got 'der/'"),
    "fault of an unknown kind": (
        {"faults": [{"kind": "meteor", "t_s": 1}]},
        "runtime.faults[0].kind: must be one of 'link_outage', 'link_loss', 'link_delay', "
        "'der_offline', 'ict_outage' or 'kill', got 'meteor'"),
    "link fault without its link": (
        {"faults": [{"kind": "link_outage", "t_s": 1, "duration_s": 1}]},
        "runtime.faults[0].link: required for a link_outage fault"),
    "loss without probability": (
        {"faults": [{"kind": "link_loss", "link": "cpfc_to_der", "t_s": 1}]},
        "runtime.faults[0].probability: required for a link_loss fault"),
    "duration of a kill": (
        {"faults": [{"kind": "kill", "agent": "cpfc", "t_s": 1, "duration_s": 3}]},
        "runtime.faults[0].duration_s: not a key of a kill fault"),
    "a DER for an ICT outage": (
        {"faults": [{"kind": "ict_outage", "der": "SGen1", "t_s": 1}]},
        "runtime.faults[0].der: not a key of a ict_outage fault"),
    "an unknown link": (
        {"faults": [{"kind": "link_outage", "link": "pigeon", "t_s": 1}]},
        "runtime.faults[0].link: must be one of 'cpfc_to_der', 'measurement_to_cpfc', "
        "'der_to_availability' or 'availability_to_cpfc', got 'pigeon'"),
    "measurement timeout too short": (
        {"measurement_timeout_s": 0.01},
        "runtime.measurement_timeout_s: must exceed measurement_period_s + "
        "measurement_to_cpfc.jitter_s (0.01), got 0.01"),
    "empty outage": ({"links": {"cpfc_to_der": {"outages": [{"t_s": 1, "duration_s": 0}]}}},
                     "runtime.links.cpfc_to_der.outages[0].duration_s: must be a positive "
                     "number, got 0"),
    "heartbeat timeout within the jitter": (
        {"heartbeat_timeout_s": 1.2, "links": {"der_to_availability": {"jitter_s": 0.3}}},
        "runtime.heartbeat_timeout_s: must exceed heartbeat_period_s + "
        "der_to_availability.jitter_s (1.3), got 1.2"),
    "heartbeat timeout too short": (
        {"heartbeat_period_s": 1.0, "heartbeat_timeout_s": 1.0},
        "runtime.heartbeat_timeout_s: must exceed heartbeat_period_s + "
        "der_to_availability.jitter_s (1), got 1"),
    "watchdog too short": (
        {"watchdog_timeout_s": 0.05, "links": {"cpfc_to_der": {"jitter_s": 0.05}}},
        "runtime.watchdog_timeout_s: must exceed pi_period_s + cpfc_to_der.jitter_s (0.06), "
        "got 0.05"),
    "offline fault of an unknown DER": (
        {"faults": [{"kind": "der_offline", "der": "SGen12", "t_s": 1, "duration_s": 1}]},
        "runtime.faults[0].der: unknown DER id 'SGen12' (known: SGen1, "),
    "kill of an unknown agent": (
        {"faults": [{"kind": "kill", "agent": "grid", "t_s": 1}]},
        "runtime.faults[0].agent: must be cpfc, measurement, availability or der/<id>, "
        "got 'grid'"),
    "kill of an unknown DER": (
        {"faults": [{"kind": "kill", "agent": "der/SGen0", "t_s": 1}]},
        "runtime.faults[0].agent: unknown DER id 'SGen0' (known: "),
    "kill after the end": (
        {"faults": [{"kind": "kill", "agent": "cpfc", "t_s": 601}]},
        "runtime.faults[0].t_s: must not exceed scenario.duration_s (600), got 601"),
}


@pytest.mark.parametrize("case", list(RUNTIME_INVALID))
def test_invalid_runtime_section_is_one_line(case: str, tmp_path: Path, simbench_document: dict,
                                             capsys) -> None:
    runtime, expected = RUNTIME_INVALID[case]
    document = copy.deepcopy(simbench_document)
    document["runtime"] = runtime
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    code, err = _check(path, capsys)
    assert code == 2
    assert err.startswith(f"adnmesh: error: {path}: {expected}"), err
    assert err.count("\n") == 1
    assert not any(word in err for word in ("pydantic", "Input should", "http")), err


def test_a_config_extends_another_key_by_key(tmp_path, configs_dir) -> None:
    """extends: the base's keys, this file's replacing them (mappings merged, lists replaced);
    a circle, a chain too long and a bad value are one-line errors."""
    import shutil

    base = tmp_path / "base.yaml"
    shutil.copy(configs_dir / "examples" / "runtime-step.yaml", base)
    variant = tmp_path / "sub" / "variant.yaml"
    variant.parent.mkdir()
    variant.write_text("extends: ../base.yaml\nruntime: {seed: 11}\n"
                       "scenario: {p_ref_steps: [{t_s: 2, delta_w: -1.0e+5}]}\n")
    original, config = load_config(base), load_config(variant)
    assert config.runtime.seed == 11
    assert config.runtime.pi_period_s == original.runtime.pi_period_s     # merged
    assert [(s.t_s, s.delta_w) for s in config.scenario.p_ref_steps] == [(2.0, -1e5)]
    assert config.scenario.availability == original.scenario.availability
    assert config.ders == original.ders and config.extends is None
    assert config.sha256 != original.sha256
    variant.write_text("extends: variant.yaml\n")
    with pytest.raises(ConfigError, match="leads back to this file"):
        load_config(variant)
    variant.write_text("extends: [a]\n")
    with pytest.raises(ConfigError, match="extends: must be the file name of a config"):
        load_config(variant)
    variant.write_text("extends: nothing.yaml\n")
    with pytest.raises(ConfigError, match="nothing.yaml"):
        load_config(variant)


def test_extends_errors_name_the_files(tmp_path) -> None:
    """A missing base names the file that extends it; a bad value from a base says the
    config extends one; a control character in a file name is a one-line error."""
    child = tmp_path / "child.yaml"
    child.write_text("extends: nothere.yaml\n")
    with pytest.raises(ConfigError, match=r"child.yaml: extends nothere.yaml: .*nothere.yaml"):
        load_config(child)
    (tmp_path / "base.yaml").write_text("grid: g\nt_com_s: -1\n")
    child.write_text("extends: base.yaml\n")
    with pytest.raises(ConfigError, match=r"child.yaml \(with what it extends\): t_com_s"):
        load_config(child)
    child.write_text('extends: "a\\0b"\n')
    with pytest.raises(ConfigError, match="extends: must be the file name"):
        load_config(child)


def test_guard_and_tap_changer_levels_that_cannot_work_are_refused(tmp_path, configs_dir) -> None:
    base = configs_dir / "simbench.yaml"
    for extra, words in (("{guard: {v_margin_pu: 0.2}}", "too narrow"),
                         ("{guard: {loading_margin_pct: 60, loading_release_pct: 40}}",
                          "no loading below"),
                         ("{tap_changer: {regulates: extremes, extremes_margin_pu: 0.11}}",
                          "leaves no band")):
        variant = tmp_path / "v.yaml"
        variant.write_text(f"extends: {base}\ngrid_model: {extra}\n")
        with pytest.raises(ConfigError, match=words):
            load_config(variant)
