"""Bad input of any kind is one line and exit code 2 before any work, never a traceback, a hang
or a reader that fills memory (issue 39, input): configs and tables the validator accepts run,
``check`` makes the grid checks ``up`` makes, inputs are regular files of bounded size, outputs
are checked before any work, and every command line of the issue's list is one line."""

from __future__ import annotations

import json
import math
import os
import resource
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from adnmesh.cli import main
from adnmesh.config import MAX_DELAY_PER_LAG, MAX_SPAN_PER_DELAY, PT1_RISE_TIME_FACTOR, load_config
from adnmesh.errors import ConfigError
from adnmesh.sim.faults import FaultError, FaultPlan
from adnmesh.tuning.table import load_table

from synthetic_runs import write_fake_run
from up_runs import CASE, write_case

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def one_line(capsys, code: int, expected: int = 2) -> str:
    """The single stderr line of a command that ended with ``code`` (must be ``expected``)."""
    err = capsys.readouterr().err
    assert code == expected, err
    assert err.startswith("adnmesh: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err and "Warning" not in err
    return err


def case_document(**changes) -> dict:
    """The runtime test case as a document, with top-level keys replaced and ``der_*`` keys
    set on every DER."""
    doc = yaml.safe_load(CASE.read_text())
    for key, value in changes.items():
        if key.startswith("der_"):
            for der in doc["ders"]:
                der[key[4:]] = value
        else:
            doc[key] = value
    return doc


def write_config(tmp_path: Path, name: str = "case", **changes) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(case_document(**changes), sort_keys=False))
    return path


def limited(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """``adnmesh argv`` in its own process with at most 2 GiB of address space and a timeout
    (before the fix, /dev/zero was read until memory ran out and a FIFO blocked forever)."""
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2 * 2**30, 2 * 2**30))

    return subprocess.run([sys.executable, "-m", "adnmesh", *argv], capture_output=True,
                          text=True, timeout=timeout, check=False, preexec_fn=limit)


# --- configs: read as regular files of bounded size ----------------------------------------------


@pytest.mark.parametrize("command", ["check", "up"])
@pytest.mark.parametrize("what", ["/dev/zero", "fifo"])
def test_a_config_that_is_no_regular_file_is_one_line(tmp_path: Path, command: str,
                                                      what: str) -> None:
    path = what
    if what == "fifo":
        path = str(tmp_path / "config.fifo")
        os.mkfifo(path)
    done = limited(command, path)
    assert done.returncode == 2, done.stderr
    kind = "a character device" if what == "/dev/zero" else "a FIFO"
    assert done.stderr == (f"adnmesh: error: {path}: not a regular file ({kind}); a config "
                           "must be a regular file of at most 16 MiB\n")


def test_a_config_larger_than_16_mib_is_one_line(tmp_path: Path, capsys) -> None:
    path = tmp_path / "huge.yaml"
    path.write_bytes(b"#" * (16 * 2**20 + 1))
    err = one_line(capsys, main(["check", str(path)]))
    assert f"{path}: larger than 16 MiB; a config must be a regular file" in err


# --- configs: bounds that follow from the numerics ------------------------------------------------


def test_the_issues_configs_are_refused_naming_the_key(tmp_path: Path) -> None:
    for changes, where, what in [
        ({"der_t_rise_s": 1e-12}, "ders[0].t_rise_s", "too fast for the loop's delays"),
        ({"der_t_delay_s": 3600.0}, "ders[0].t_rise_s", "too fast for the loop's delays"),
        ({"der_t_rise_s": 3600.0}, "ders[0].t_rise_s", "too slow for the shortest forward"),
    ]:
        path = write_config(tmp_path, **changes)
        with pytest.raises(ConfigError) as info:
            load_config(path)
        assert str(info.value).startswith(f"{path}: {where}: {what}"), str(info.value)
        assert "\n" not in str(info.value)


def test_the_numerics_bounds_hold_exactly_at_their_limits(tmp_path: Path) -> None:
    """The runtime case: forward delay t_com_s + pi_period_s / 2 + t_delay_s = 0.115 s (the
    longest and the shortest), loop delay 0.215 s with t_meas_s."""
    forward, loop = 0.1 + 0.01 / 2 + 0.01, 0.1 + 0.01 / 2 + 0.01 + 0.1
    fastest = forward / MAX_DELAY_PER_LAG * PT1_RISE_TIME_FACTOR
    slowest = (MAX_SPAN_PER_DELAY * forward - loop) * PT1_RISE_TIME_FACTOR
    for t_rise_s, ok in [(fastest * 1.001, True), (fastest * 0.999, False),
                         (slowest * 0.999, True), (slowest * 1.001, False)]:
        path = write_config(tmp_path, der_t_rise_s=t_rise_s)
        if ok:
            load_config(path)
        else:
            with pytest.raises(ConfigError, match=r"ders\[0\]\.t_rise_s: too"):
                load_config(path)
    # as a time constant: ln 9 times more room at the fast end
    path = write_config(tmp_path, der_t_rise_s=fastest / PT1_RISE_TIME_FACTOR * 1.001,
                        t_rise_is="time_constant")
    load_config(path)


def test_periods_that_would_flood_a_receiver_are_refused(tmp_path: Path) -> None:
    """Before: ``pi_period_s: 1e-6`` put 100,000 P_Y messages on their way to each DER, the
    receivers' gate took 4,096 and the clock stalled for good."""
    with pytest.raises(ConfigError, match=r"runtime\.pi_period_s: too short for cpfc_to_der: "
                                          r"0\.1 s of delay .* at least 0\.0001, got 1e-06"):
        load_config(write_config(tmp_path, runtime={"pi_period_s": 1e-6}))
    load_config(write_config(tmp_path, runtime={"pi_period_s": 1e-4, "watchdog_timeout_s": 1}))
    fault = {"kind": "link_delay", "t_s": 1, "link": "measurement_to_cpfc", "delay_s": 10.0}
    with pytest.raises(ConfigError, match=r"runtime\.measurement_period_s: too short for "
                                          r"measurement_to_cpfc: 10\.1 s of delay \(with its "
                                          r"jitter \+ its largest link_delay fault\)"):
        load_config(write_config(tmp_path, runtime={"faults": [fault]}))


def test_every_shipped_config_keeps_to_the_numerics_bounds() -> None:
    for path in sorted(CONFIGS.glob("*.yaml")) + sorted(CONFIGS.glob("examples/*.yaml")):
        load_config(path)


def test_an_inverted_voltage_band_is_refused(tmp_path: Path, capsys) -> None:
    path = write_config(tmp_path, grid_model={"limits": {"v_min_pu": 1.1, "v_max_pu": 0.9}})
    err = one_line(capsys, main(["check", str(path)]))
    assert err.endswith("grid_model.limits.v_min_pu: must be less than v_max_pu (0.9), got "
                        "1.1\n")


def test_up_refuses_a_config_whose_scenario_it_cannot_tune(tmp_path: Path, monkeypatch,
                                                           capsys) -> None:
    """Constraints no pair meets: before, ``up`` tuned infeasible entries (no gains), started
    the agents, and the CPFC died of them (``ValueError: need kp > 0``)."""
    monkeypatch.chdir(tmp_path)
    path = write_config(tmp_path, constraints={"disk_margin_min": 1.99})
    assert main(["up", str(path), "--out", "run.mcap"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (
        f"adnmesh: error: {path}: constraints: no PI pair meets them for the scenario's DERs "
        "SGen1, SGen2 (no feasible pair on the global grid); relax them or change the DERs")
    assert "Traceback" not in err and not (tmp_path / "run.mcap").exists()


# --- check makes the grid checks up makes ---------------------------------------------------------


def _simbench(tmp_path: Path, name: str, change) -> Path:
    doc = yaml.safe_load((CONFIGS / "simbench.yaml").read_text())
    change(doc)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@pytest.mark.parametrize("name, change, message", [
    ("sgen", lambda d: d["ders"][0].update(sgen="MV1.101 SGen 999"),
     "no static generator named 'MV1.101 SGen 999'"),
    ("load", lambda d: d["ders"][0].update(sgen="MV1.101 Load 1"),
     "no static generator named 'MV1.101 Load 1'"),
    ("code", lambda d: d.update(simbench_code="1-MV-nowhere--0-no_sw"),
     "'1-MV-nowhere--0-no_sw' is not a SimBench code"),
    ("case", lambda d: d["grid_model"].update(study_case="zz"), "unknown study case 'zz'"),
])
def test_check_refuses_what_up_refuses_of_the_grid(tmp_path: Path, monkeypatch, capsys, name,
                                                   change, message) -> None:
    monkeypatch.chdir(tmp_path)
    path = _simbench(tmp_path, name, change)
    checked = one_line(capsys, main(["check", str(path)]))
    assert checked.startswith(f"adnmesh: error: {path}: ") and message in checked
    if name == "case":        # loads the SimBench net itself (no cache for an unknown case)
        return
    assert main(["up", str(path), "--table", "absent.json"]) == 2
    err = capsys.readouterr().err          # up says first that it loads the grid model
    assert err.splitlines()[-1] + "\n" == checked and "Traceback" not in err


def test_check_reports_the_grid_model(configs_dir: Path, capsys) -> None:
    assert main(["check", str(configs_dir / "simbench.yaml")]) == 0
    out = capsys.readouterr().out
    assert ("grid model: study case lW, impedance loads: P_IP 16.5503 MW at the schedules, "
            "the DERs can deliver ") in out


# --- tables ---------------------------------------------------------------------------------------


def _table(tmp_path: Path, change) -> tuple[Path, Path]:
    config, table = write_case(tmp_path)
    doc = json.loads(table.read_text())
    change(doc)
    table.write_text(json.dumps(doc))
    return config, table


def _entry(**values):
    return lambda doc: doc["entries"][-1].update(values)


@pytest.mark.parametrize("change, message", [
    (_entry(kp=math.nan), "entries[1]: K_P must be a finite positive gain (1/W), got nan"),
    (_entry(kp=-1e-8), "entries[1]: K_P must be a finite positive gain (1/W), got -1e-08"),
    (_entry(ki=0.0), "entries[1]: K_I must be a finite positive gain (1/(W s)), got 0.0"),
    (_entry(kp=1e300, ki=1e300), "entries[1]: K_P 1e+300 times the 4e+06 W installed is "
                                 "4e+306, more than the numerics take"),
    (_entry(kp=1e-8, ki=1e-20), "entries[1]: K_P / K_I is 1e+12 s, more than the numerics"),
    (lambda doc: doc["entries"][-1]["w"].update(SGen1=-0.5),
     "entries[1].w.SGen1: must be a weight in [0, 1], got -0.5"),
    (lambda doc: doc["entries"][-1]["w"].update(SGen1=1.5),
     "entries[1].w.SGen1: must be a weight in [0, 1], got 1.5"),
    (_entry(w={"SGen1": 0.0, "SGen2": 0.0}), "entries[1].w: every weight is 0 in a feasible"),
    (_entry(ders=["SGen1", "SGenX"]), "entries[1].ders: unknown DER id 'SGenX'"),
    (_entry(ders=[]), "entries[1].ders: must be a non-empty list of DER ids"),
    (lambda doc: doc.update(der_ids=["SGen1", "SGen1"]), "der_ids: a DER id appears twice"),
    (lambda doc: doc.update(static={"ders": ["SGen1"], "kp": math.inf, "ki": 1.0, "w": {},
                                    "feasible": True}),
     "static: K_P must be a finite positive gain (1/W), got inf"),
])
def test_a_table_the_cpfc_could_not_run_is_refused_when_loaded(tmp_path: Path, change,
                                                                message: str) -> None:
    """Before, these tables passed the loader: a CPFC traceback (kp NaN, kp < 0, ki = 0), a
    KeyError (an unknown DER), a 60 s stall (kp = ki = 1e300, a negative weight)."""
    config, table = _table(tmp_path, change)
    with pytest.raises(ConfigError) as info:
        load_table(table, load_config(config))
    assert str(info.value).startswith(f"{table}: not a valid adnmesh table: "), str(info.value)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_an_infeasible_entry_may_have_no_gains_and_zero_weights(tmp_path: Path) -> None:
    config, table = _table(tmp_path, _entry(kp=None, ki=None, feasible=False,
                                            w={"SGen1": 0.0, "SGen2": 0.0}, reason="none"))
    assert not load_table(table, load_config(config)).lookup(["SGen1", "SGen2"]).feasible


def test_a_deep_or_unreadable_table_is_one_line(tmp_path: Path, capsys) -> None:
    config, table = write_case(tmp_path)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ConfigError, match="JSON nested too deep"):
        load_table(deep)
    fifo = tmp_path / "table.fifo"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match=r"not a regular file \(a FIFO\)"):
        load_table(fifo)
    out = tmp_path / "run.mcap"
    for bad in (deep, tmp_path):
        err = one_line(capsys, main(["up", str(config), "--table", str(bad), "--out", str(out)]))
        assert err.startswith(f"adnmesh: error: {bad}: ")
    assert not out.exists()


# --- command lines --------------------------------------------------------------------------------


@pytest.fixture
def case(tmp_path: Path) -> tuple[Path, Path]:
    return write_case(tmp_path)


@pytest.fixture
def busy_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


@pytest.mark.parametrize("endpoint, message", [
    ("tcp/127.0.0.1:99999", "tcp endpoints are tcp/HOST:PORT with a port from 0 to 65535"),
    ("garbage", "not an endpoint (PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447)"),
    ("tcp/192.0.2.1:7447", "cannot listen there: "),
    ("busy", "cannot listen there: Address already in use"),
])
def test_up_listen_endpoints_are_checked_before_anything_starts(tmp_path: Path, case, busy_port,
                                                                capsys, endpoint, message):
    endpoint = f"tcp/127.0.0.1:{busy_port}" if endpoint == "busy" else endpoint
    config, table = case
    out = tmp_path / "run.mcap"
    err = one_line(capsys, main(["up", str(config), "--table", str(table), "--out", str(out),
                                 "--listen", endpoint]))
    assert err.startswith(f"adnmesh: error: --listen {endpoint}: {message}"), err
    assert not out.exists()


def test_router_connect_garbage_is_one_line(case, capsys) -> None:
    err = one_line(capsys, main(["router", str(case[0]), "--name", "site", "--connect",
                                 "garbage"]))
    assert err == "adnmesh: error: --connect garbage: not an endpoint (PROTOCOL/HOST:PORT, e.g. " \
                  "tcp/127.0.0.1:7447)\n"


@pytest.fixture
def unwritable(tmp_path: Path) -> Path:
    """A place no one can write to, root included: below a regular file."""
    blocker = tmp_path / "a-file"
    blocker.write_text("in the way\n")
    return blocker / "sub"


@pytest.fixture
def truncated(tmp_path: Path) -> Path:
    """A recording cut short (a killed run), so that inspect recovers it."""
    path = tmp_path / "fake.mcap"
    write_fake_run(path, duration_s=20.0)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    return path


def test_outputs_into_an_unwritable_place_are_one_line_before_any_work(
        tmp_path: Path, case, unwritable: Path, truncated: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    config, table = case
    for argv, flag, target in [
        (["up", str(config), "--table", str(table), "--out"], "--out", "run.mcap"),
        (["up", str(config), "--table", str(table), "--summary-json"], "--summary-json",
         "s.json"),
        (["tune", str(config), "--method", "global", "--out"], "--out", "t.json"),
        (["analyze", str(config), "--table", str(table), "--only", "robustness", "--out"],
         "--out", "analysis"),
        (["inspect", str(truncated), "--recover-to"], "--recover-to", "r.mcap"),
        (["plot", str(truncated), "-o"], "-o", "p.png"),
        (["replay", str(truncated), "--rrd"], "--rrd", "r.rrd"),
        (["certs"], "DIR", "certs"),
    ]:
        err = one_line(capsys, main([*argv, str(unwritable / target)]))
        assert err.startswith(f"adnmesh: error: {flag} {unwritable / target}: cannot write the "), \
            err
        assert "Not a directory" in err
    assert not any((tmp_path / "logs").glob("*.mcap")) and not Path("tables").exists()


def test_outputs_naming_a_directory_are_one_line(tmp_path: Path, case, capsys) -> None:
    config, table = case
    for argv in (["up", str(config), "--table", str(table), "--out", str(tmp_path)],
                 ["tune", str(config), "--out", str(tmp_path)]):
        err = one_line(capsys, main(argv))
        assert err == f"adnmesh: error: --out {tmp_path}: cannot write the file there: Is a " \
                      "directory\n"


def test_certs_into_proc_is_one_line(capsys) -> None:
    err = one_line(capsys, main(["certs", "/proc/adnmesh-certs"]))
    assert err.startswith("adnmesh: error: DIR /proc/adnmesh-certs: cannot write the folder")


@pytest.mark.parametrize("kp, ki, message", [
    ("1e400", "1e-7", "K_P must be a finite positive gain (1/W), got inf"),
    ("1e300", "1e-7", "K_P / K_I is 1e+307 s, more than the numerics take"),
    ("1e300", "1e300", "K_P 1e+300 times the 4e+06 W installed is 4e+306"),
    ("nan", "1e-7", "K_P must be a finite positive gain (1/W), got nan"),
    ("5e-8", "-1", "K_I must be a finite positive gain (1/(W s)), got -1.0"),
])
def test_margins_gains_outside_the_numerics_are_one_line(case, capsys, kp, ki, message) -> None:
    """Before: ``--kp 1e400`` and ``--kp 1e300 --ki 1e-7`` were tracebacks of the stability
    certificate, ``--kp 1e300 --ki 1e300`` leaked a NumPy overflow warning."""
    err = one_line(capsys, main(["margins", str(case[0]), "--kp", kp, "--ki", ki]))
    assert err.startswith(f"adnmesh: error: --kp/--ki: {message}"), err


def test_a_binary_or_endless_subsets_file_is_one_line(tmp_path: Path, case, capsys) -> None:
    binary = tmp_path / "subsets.bin"
    binary.write_bytes(bytes(range(256)) * 4)
    err = one_line(capsys, main(["tune", str(case[0]), "--subsets", str(binary), "--out",
                                 str(tmp_path / "t.json")]))
    assert "not UTF-8 text (byte 128)" in err
    err = one_line(capsys, main(["tune", str(case[0]), "--subsets", "/dev/zero", "--out",
                                 str(tmp_path / "t.json")]))
    assert "/dev/zero: cannot read (not a regular file (a character device))" in err
    err = one_line(capsys, main(["tune", str(case[0]), "--subsets", "random:99999999999",
                                 "--out", str(tmp_path / "t.json")]))
    assert "N must be a positive integer, at most 65,535" in err


def test_up_speed_outside_its_range_is_one_line(case, capsys) -> None:
    """Before: ``--speed 1e-300`` killed an agent with an overflow, the run never progressed
    and its summary claimed real time."""
    for speed in ("1e-300", "0.0009", "2e6"):
        err = one_line(capsys, main(["up", str(case[0]), "--table", str(case[1]), "--clock",
                                     "realtime", "--speed", speed]))
        assert err.startswith("adnmesh: error: --speed must be in [0.001, 1e+06], got "), err


def test_a_fault_after_the_scenario_is_refused(case) -> None:
    config = load_config(case[0])
    plan = FaultPlan(config, ["cpfc", "der/SGen1"])
    plan.add("kill", 12 * 10**9, None, agent="cpfc")             # at the end: still acts
    with pytest.raises(FaultError, match=r"kill at 12\.5 s: after the end of the scenario "
                                         r"\(12 s\)"):
        plan.add("kill", int(12.5e9), None, agent="cpfc")
    with pytest.raises(FaultError, match="at the earliest at 13 s: after the end"):
        plan.add("ict_outage", 0, None, earliest_ns=13 * 10**9)
    assert len(plan.faults) == 1


@pytest.mark.slow
def test_adnmesh_fault_beyond_the_scenario_is_refused_by_the_run(tmp_path: Path) -> None:
    """Against a running ``up``: one line and exit 2 (refused), and the run lists no fault
    (before: accepted and listed as a fault that was never detected)."""
    from up_runs import finish, start_long_run

    proc, agents, config = start_long_run(tmp_path, "late", "--summary-json",
                                          str(tmp_path / "late.summary.json"),
                                          scenario={"duration_s": 400})
    refused = subprocess.run([sys.executable, "-m", "adnmesh", "fault",
                              str(tmp_path / "late.mcap"), "kill", "cpfc", "--at", "500"],
                             capture_output=True, text=True, timeout=60, check=False)
    returncode, err = finish(proc, agents, config)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert refused.stderr == ("adnmesh fault: fault request refused: kill at 500 s: after the "
                              "end of the scenario (400 s)\n") and refused.stdout == ""
    assert returncode == 0, err
    summary = json.loads((tmp_path / "late.summary.json").read_text())
    assert summary["faults"] == []


# --- more of the probe's command lines (benchmarks/probe.py, its full sweep) ---------------------


def test_more_bad_command_lines_are_one_line(tmp_path: Path, case, unwritable: Path, capsys,
                                             monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    config, table = case
    up = ["up", str(config), "--table", str(table)]
    fifo = tmp_path / "run.fifo"
    os.mkfifo(fifo)
    for argv, message in [
        ([*up, "--listen", ""], "--listen : not an endpoint"),
        ([*up, "--external", ",,,"], "--external ',,,': names no agent"),
        ([*up, "--view", str(unwritable / "v.rrd")], f"--view {unwritable / 'v.rrd'}: cannot"),
        (["tune", str(config), "--workers", "1000000"], "--workers must be 1 to 1024"),
        (["tune", str(config), "--overshoot-max-pct", "1e400"], "--overshoot-max-pct must be"),
        (["analyze", str(config), "--table", str(table), "--solution-space", ""],
         "--solution-space: give at least one DER id"),
        (["fault", "tcp/127.0.0.1:1", "ict_outage", "--timeout", "-1"], "--timeout must be"),
        (["fault", "tcp/127.0.0.1:1", "ict_outage", "--timeout", "nan"], "--timeout must be"),
        (["agent", "der", str(config), "--id", "SGen1", "--connect", "tcp/127.0.0.1:1",
          "--resume-at-ns", "-1"], "--resume-at-ns must be in [0, 2**63) ns"),
        (["agent", "der", str(config), "--id", "SGen1", "--connect", "tcp/127.0.0.1:1",
          "--connect-timeout", "nan"], "--connect-timeout must be in [0, 86400] s"),
        (["replay", str(fifo)], f"{fifo}: not a regular file (a FIFO)"),
        (["plot", str(fifo)], f"{fifo}: not a regular file (a FIFO)"),
        (["inspect", str(fifo)], f"{fifo}: not a regular file (a FIFO)"),
    ]:
        err = one_line(capsys, main(argv))
        assert err.startswith(f"adnmesh: error: {message}"), (argv, err)


@pytest.mark.parametrize("change, message", [
    (lambda doc: doc["entries"][-1]["w"].pop("SGen2"),
     "entries[1].w: no weight for 'SGen2' (one per DER of the entry)"),
    (_entry(kp=10**400), "entries[1]: K_P must be a finite positive gain (1/W), got 1000000"),
])
def test_more_bad_tables_are_refused(tmp_path: Path, change, message: str) -> None:
    config, table = _table(tmp_path, change)
    with pytest.raises(ConfigError) as info:
        load_table(table, load_config(config))
    assert message in str(info.value)


def test_a_zero_weight_of_find_w_is_a_valid_table(tmp_path: Path) -> None:
    """Find W gives a DER that can take no share the weight 0 (adnmesh/tuning/weights.py),
    in a feasible entry: the table the tuning writes must load."""
    config, table = _table(tmp_path, lambda doc: doc["entries"][-1]["w"].update(SGen2=0.0))
    assert load_table(table, load_config(config)).lookup(["SGen1", "SGen2"]).w["SGen2"] == 0.0
