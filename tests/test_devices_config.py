"""A DER's ``plant:`` section: read and checked as a user would expect, one line when wrong, and
the commands that refuse what a device cannot do (the sim clock, a bad --fault)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from adnmesh.cli import main
from adnmesh.config import IEC104Plant, SunSpecPlant, load_config
from adnmesh.errors import ConfigError
from up_runs import CASE, write_case


def with_plants(tmp_path: Path, *plants, name: str = "devices", **extra) -> Path:
    """The runtime case (two WTs) with the given ``plant:`` per DER."""
    document = yaml.safe_load(CASE.read_text())
    for der, plant in zip(document["ders"], plants, strict=True):
        der["plant"] = plant
    document.update(extra)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def one_line(capsys, code: int) -> str:
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("adnmesh: error: ") and err.count("\n") == 1, err
    return err


def test_plants_are_read_with_their_defaults(tmp_path: Path) -> None:
    config = load_config(with_plants(
        tmp_path, {"protocol": "sunspec", "port": 1502, "simulator": True},
        {"protocol": "iec104", "host": "rtu-7.example", "port": 2404, "common_address": 7,
         "addresses": {"p_meas": 1200}}))
    sunspec, iec104 = (d.plant for d in config.ders)
    assert isinstance(sunspec, SunSpecPlant) and isinstance(iec104, IEC104Plant)
    assert (sunspec.host, sunspec.unit_id, sunspec.points.p_set, sunspec.points.stamp) == \
        ("127.0.0.1", 1, "704.WSet", "122.Tms")
    assert (iec104.common_address, iec104.addresses.p_set, iec104.addresses.p_meas) == \
        (7, 100, 1200)
    assert load_config(CASE).ders[0].plant  is None


@pytest.mark.parametrize(("plant", "message"), [
    ({"protocol": "modbus", "port": 1502}, "ders[0].plant.protocol: must be sunspec or iec104"),
    ("real", "ders[0].plant: must be simulated or a device"),
    ({"protocol": "sunspec"}, "ders[0].plant.sunspec.port"),
    ({"protocol": "sunspec", "port": 70000}, "port"),
    ({"protocol": "sunspec", "port": 1502, "points": {"p_set": "WSet"}},
     "p_set: must be MODEL.POINT of a SunSpec model (704.WSet), got 'WSet'"),
    ({"protocol": "iec104", "port": 2404, "addresses": {"p_set": 200}},
     "duplicate information object address 200"),
    ({"protocol": "sunspec", "port": 1502, "tls": {"ca": "ca.pem", "cert": "gw.pem"}},
     "cert and key come together"),
    ({"protocol": "sunspec", "port": 1502, "timeout_s": 0}, "timeout_s"),
])
def test_a_bad_plant_is_one_line_naming_its_key(tmp_path: Path, plant, message) -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(with_plants(tmp_path, plant, "simulated"))
    text = str(caught.value)
    assert "\n" not in text and message in text, text


def test_two_simulators_on_one_address_are_refused(tmp_path: Path) -> None:
    plant = {"protocol": "sunspec", "port": 1502, "simulator": True}
    with pytest.raises(ConfigError, match=r"ders\[1\]\.plant\.port: duplicate device simulator "
                                          r"address '127\.0\.0\.1:1502'"):
        load_config(with_plants(tmp_path, plant, plant))


def test_up_refuses_devices_on_the_sim_clock_and_a_speed(tmp_path: Path, capsys) -> None:
    config, table = write_case(tmp_path)
    path = with_plants(tmp_path, {"protocol": "sunspec", "port": 1502}, "simulated")
    for extra in ([], ["--clock", "realtime", "--speed", "2"]):
        err = one_line(capsys, main(["up", str(path), "--table", str(table), *extra]))
        assert "SGen1's plant is a sunspec device, which runs on the wall clock: run with " \
               "--clock realtime (at --speed 1)" in err


def test_check_names_the_devices_and_refuses_a_missing_tls_file(tmp_path: Path,
                                                               capsys) -> None:
    path = with_plants(tmp_path, {"protocol": "sunspec", "port": 1502, "simulator": True},
                       {"protocol": "iec104", "port": 2404})
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "plant devices: 2 of 2 DERs behind a protocol, wall clock only (up --clock " \
           "realtime): SGen1 sunspec 127.0.0.1:1502 (simulated by up), SGen2 iec104 " \
           "127.0.0.1:2404" in out
    path = with_plants(tmp_path, {"protocol": "sunspec", "port": 1502,
                                  "tls": {"ca": "nowhere/ca.pem"}}, "simulated", name="tls")
    err = one_line(capsys, main(["check", str(path)]))
    assert "ders[0].plant.tls.ca: no file" in err and "nowhere/ca.pem" in err


@pytest.mark.parametrize("fault", ["silent", "silent@5", "loud@1+2", "down@3+0", "down@-1+2"])
def test_device_refuses_a_bad_fault_in_one_line(tmp_path: Path, capsys, fault: str) -> None:
    path = with_plants(tmp_path, {"protocol": "sunspec", "port": 1502}, "simulated")
    err = one_line(capsys, main(["device", "sunspec", str(path), "--der", "SGen1",
                                 "--fault", fault]))
    assert "must be KIND@START+DURATION" in err


def test_device_needs_a_port_and_the_plants_protocol(tmp_path: Path, capsys) -> None:
    path = with_plants(tmp_path, {"protocol": "sunspec", "port": 1502}, "simulated")
    err = one_line(capsys, main(["device", "iec104", str(path), "--der", "SGen1"]))
    assert "SGen1's plant speaks sunspec, not iec104" in err
    err = one_line(capsys, main(["device", "iec104", str(path), "--der", "SGen2"]))
    assert "--port: SGen2 has no device port" in err
    err = one_line(capsys, main(["device", "iec104", str(path), "--der", "SGen9"]))
    assert "unknown DER id 'SGen9'" in err
