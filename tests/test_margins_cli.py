"""``adnmesh margins``: the JSON object, agreement with the library, one-line errors."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.cli import main
from adnmesh.loopmodel.evaluation import evaluate

from loops import CONFIG, plant

REQUIRED = ("stable", "disk_margin", "disk_gain_margin", "disk_phase_margin_deg", "gain_margin",
            "phase_margin_deg", "delay_margin_s", "overshoot_pct", "rise_time_s",
            "settling_time_s", "settling_time_2pct_s", "peak_time_s")


def _json(capsys, *args):
    code = main(["margins", str(CONFIG.path), *args, "--json"])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.strip().splitlines()
    assert len(lines) == 1
    return json.loads(lines[0])


def test_json_object_matches_library(capsys):
    obj = _json(capsys, "--kp", "4e-8", "--ki", "1.5e-7", "--ders", "SGen1,SGen5")
    assert set(REQUIRED) <= set(obj)
    assert obj["ders"] == ["SGen1", "SGen5"] and obj["stable"] is True
    f = evaluate(plant(["SGen1", "SGen5"]), 4e-8, 1.5e-7).row(0)
    for key in ("disk_margin", "gain_margin", "phase_margin_deg", "delay_margin_s",
                "overshoot_pct", "rise_time_s", "settling_time_s", "settling_time_2pct_s",
                "peak_time_s"):
        assert obj[key] == pytest.approx(f[key], rel=1e-12), key
    assert len(obj["disk_gain_margin"]) == 2
    lo, hi = obj["disk_gain_margin"]
    assert lo < 1 < hi


def test_all_ders_by_default(capsys):
    obj = _json(capsys, "--kp", "1.7e-8", "--ki", "6.8e-8")
    assert obj["ders"] == list(CONFIG.der_ids())
    assert 1.45 < obj["disk_margin"] < 1.55 and obj["stable"]


def test_unstable_loop_has_no_margins(capsys):
    obj = _json(capsys, "--kp", "1.7e-6", "--ki", "6.8e-6")
    assert obj["stable"] is False and obj["unstable_poles"] > 0
    for key in REQUIRED[1:]:
        assert obj[key] is None, key
    assert obj["meets_constraints"] is False


@pytest.mark.parametrize("args, message", [
    (["--kp=-1e-8", "--ki", "1e-8"], "--kp/--ki: K_P must be a finite positive gain"),
    (["--kp", "1e-8", "--ki", "0"], "--kp/--ki: K_I must be a finite positive gain"),
    (["--kp", "1e-8", "--ki", "1e-8", "--ders", "SGen1,SGen99"], "unknown DER id 'SGen99'"),
    (["--kp", "1e-8", "--ki", "1e-8", "--ders", "SGen1,SGen1"], "duplicate DER id"),
])
def test_bad_arguments_one_line_exit_2(capsys, args, message):
    assert main(["margins", str(CONFIG.path), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err


def test_console_script_prints_one_json_object():
    exe = Path(sys.executable).with_name("adnmesh")
    proc = subprocess.run([str(exe), "margins", str(CONFIG.path), "--kp", "1.7e-8", "--ki",
                           "6.8e-8", "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    obj = json.loads(proc.stdout)
    assert obj["stable"] is True and obj["delay_margin_s"] > 0
