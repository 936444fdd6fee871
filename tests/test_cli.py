"""Tests of adnmesh.cli and the commands in adnmesh.commands."""

from __future__ import annotations

import json
import re
import runpy
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest

from adnmesh import __version__
from adnmesh.cli import COMMANDS, build_parser, main
from adnmesh.commands import check
from adnmesh.commands import schema as schema_command
from adnmesh.errors import UsageError


def test_check_prints_a_summary_of_the_reference_case(configs_dir: Path, capsys) -> None:
    path = configs_dir / "simbench.yaml"
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert f"{path}: valid (sha256 " in out
    assert "simbench-1-MV-rural (SimBench 1-MV-rural--0-no_sw)" in out
    assert "T_com 0.1 s, T_meas 0.1 s" in out
    assert "disk margin >= 1.5, overshoot < 1 %, settling band 5 %" in out
    assert "11 DERs" in out and "12.660" in out  # total P_inst in MW
    for der_type, count, p_mw in [("WT", 6, "11.400"), ("CHP", 3, "0.940"), ("PV", 2, "0.320")]:
        cells = [re.findall(r"[^\s│┃|]+", line) for line in out.splitlines()]
        assert [der_type, str(count), p_mw] in [row[:3] for row in cells], der_type
    assert "T_delay [s]" in out  # units survive rich's markup
    assert "P_ref +1.000 MW" in out and "P_ref -1.000 MW" in out
    assert "unavailable: SGen1, SGen2, SGen3, SGen4, SGen7, SGen8" in out


def test_up_reports_an_invalid_config_first(tmp_path: Path, capsys) -> None:
    assert main(["up", str(tmp_path / "missing.yaml")]) == 2
    assert capsys.readouterr().err == f"adnmesh: error: {tmp_path / 'missing.yaml'}: no such file\n"


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "the following arguments are required: COMMAND"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
        (["check"], "the following arguments are required: CONFIG"),
    ],
)
def test_usage_errors_exit_2(argv: list[str], message: str, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: adnmesh") and message in err


def test_version_and_help_exit_0(capsys) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"adnmesh {__version__}\n"
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ("check", "up"))


def test_every_command_module_has_the_interface() -> None:
    names = build_parser()._subparsers._group_actions[0].choices  # noqa: SLF001
    # one subparser per command module, named after it, in COMMANDS order
    assert list(names) == [m.__name__.rsplit(".", 1)[1] for m in COMMANDS]
    assert {"check", "up", "margins"} <= set(names)
    assert all(callable(m.add_parser) and callable(m.run) for m in COMMANDS)


@pytest.mark.parametrize("name", [m.__name__.rsplit(".", 1)[1] for m in COMMANDS])
def test_every_commands_help_says_its_exit_codes(name: str) -> None:
    parser = build_parser(name)._subparsers._group_actions[0].choices[name]  # noqa: SLF001
    text = " ".join(parser.format_help().split())
    assert re.search(r"[Ee]xit code", text), name
    assert re.search(r"\b0\b", text[text.lower().index("exit code"):]), name


def test_usage_error_is_one_line_and_exit_2(monkeypatch, configs_dir: Path, capsys) -> None:
    def refuse(args):
        raise UsageError("--speed needs --clock realtime")

    monkeypatch.setattr(check, "run", refuse)
    assert main(["check", str(configs_dir / "simbench.yaml")]) == 2
    assert capsys.readouterr().err == "adnmesh: error: --speed needs --clock realtime\n"


def test_ctrl_c_exits_130_with_one_line(monkeypatch, configs_dir: Path, capsys) -> None:
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(check, "run", interrupted)
    assert main(["check", str(configs_dir / "simbench.yaml")]) == 130
    assert capsys.readouterr().err == "adnmesh: interrupted\n"


def test_python_dash_m_adnmesh(monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "argv", ["adnmesh", "--version"])
    with pytest.raises(SystemExit) as info:
        runpy.run_module("adnmesh", run_name="__main__")
    assert info.value.code == 0
    assert capsys.readouterr().out == f"adnmesh {__version__}\n"


def test_installed_console_script_prints_no_traceback(tmp_path: Path) -> None:
    """The real entry point, in its own process: an invalid config is one line, exit code 2."""
    script = Path(sys.executable).with_name("adnmesh")
    assert script.exists(), f"{script} missing: install the project first (pip install -e .)"
    config = tmp_path / "bad.yaml"
    config.write_text("grid: [unclosed\n")
    result = subprocess.run(
        [str(script), "check", str(config)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.startswith(f"adnmesh: error: {config}: line 2, column 1: invalid YAML: ")
    assert result.stderr.count("\n") == 1
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("name", ["config", "hierarchy"])
def test_schema_is_the_committed_file(configs_dir: Path, capsys, name: str) -> None:
    """configs/NAME.schema.json is what 'adnmesh schema NAME' prints: it cannot drift."""
    assert main(["schema", name]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out == (configs_dir / f"{name}.schema.json").read_text(), (
        f"configs/{name}.schema.json is stale: run 'adnmesh schema {name} > "
        f"configs/{name}.schema.json'")


def test_schema_config_is_a_json_schema_with_units(capsys) -> None:
    assert main(["schema", "config"]) == 0
    schema = json.loads(capsys.readouterr().out)
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["additionalProperties"] is False
    assert list(schema["properties"]) == ["grid", "simbench_code", "t_com_s", "t_meas_s",
                                          "constraints", "ders", "scenario", "runtime",
                                          "grid_model", "reactive", "study", "t_rise_is", "extends"]
    der = schema["$defs"]["DER"]["properties"]
    assert der["p_inst_w"]["description"].endswith(", W; the controller's C_d.")
    assert (der["p_inst_w"]["exclusiveMinimum"], der["p_inst_w"]["maximum"]) == (0, 1e10)
    assert der["type"]["enum"] == ["WT", "CHP", "PV", "HYDRO", "GEN"]
    sections = [schema, *schema["$defs"].values()]
    descriptions = [entry["description"] for section in sections
                    for entry in (section, *section["properties"].values())]
    assert len(descriptions) > 60 and not any("\n" in text for text in descriptions)


def test_schema_takes_a_name_from_its_registry(capsys) -> None:
    assert list(schema_command.SCHEMAS) == ["config", "hierarchy", "messages"]
    assert main(["schema", "wire"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'wire' (choose from 'config', 'hierarchy', 'messages')" in err
    assert main(["schema", "messages"]) == 0
    messages = json.loads(capsys.readouterr().out)
    assert messages["p_ip"]["properties"]["p_ip_w"]["maximum"] == 1e15
    assert main(["schema"]) == 2
    assert "the following arguments are required: NAME" in capsys.readouterr().err


@pytest.mark.parametrize("given, expected", [(None, "1"), ("2", "2")])
def test_the_command_line_keeps_openblas_on_one_thread_unless_told(given, expected) -> None:
    """The command line sets OpenBLAS to one thread before numpy loads (its idle threads
    busy-wait and take CPU from the other tuning worker; workers and agents inherit it); a
    value the user set is kept. Importing adnmesh.cli (what the console script does first)
    neither sets it nor loads numpy."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    probe = ("import os, sys; from adnmesh.cli import main; "
             "print(os.environ.get('OPENBLAS_NUM_THREADS'), 'numpy' in sys.modules); "
             "main(['--version']); print(os.environ['OPENBLAS_NUM_THREADS'])")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True, timeout=60, check=True).stdout.splitlines()
    assert out[0] == f"{given} False"
    assert out[-1] == expected
