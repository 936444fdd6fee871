"""Certificates of the secure profile (adnmesh/runtime/certificates.py, identity.py, ``adnmesh certs``):
what is created, with which permissions, and what a second run keeps or replaces."""

from __future__ import annotations

import ipaddress
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.errors import UsageError
from adnmesh.runtime.certificates import issue
from adnmesh.runtime.identity import cert_files, check_identity, identities

REPO = Path(__file__).resolve().parent.parent
CASE = REPO / "configs" / "examples" / "runtime-step.yaml"


def load_cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_identities_of_a_config_are_its_agents_up_and_the_operator() -> None:
    assert identities(load_config(CASE)) == ("cpfc", "measurement", "availability",
                                             "der/SGen1", "der/SGen2", "up", "operator")


@pytest.mark.parametrize("bad", ["", "der/", "der/1x", "router/", "root", "der/a/b", "../ca",
                                 "cpfc/../up", "der/" + "x" * 80])
def test_what_is_not_an_identity_is_refused(bad: str) -> None:
    with pytest.raises(UsageError, match="not an identity"):
        check_identity(bad)


def test_every_identity_gets_a_key_only_its_owner_reads_and_a_cert_signed_by_the_ca(
        tmp_path: Path) -> None:
    names = [*identities(load_config(CASE)), "router/site"]
    result = issue(tmp_path / "certs", names, hosts=["127.0.0.1", "scada.example"])
    assert result.ca_created and result.created == names and result.kept == []
    ca = load_cert(tmp_path / "certs" / "ca.pem")
    assert mode(tmp_path / "certs" / "ca.key") == 0o600
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name in names:
        files = cert_files(tmp_path / "certs", name)
        assert mode(files.key) == 0o600 and mode(files.key.parent) == 0o700
        cert = load_cert(files.cert)
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
        assert san.get_values_for_type(x509.DNSName) == ["scada.example"]
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert (tmp_path / "certs" / "der" / "SGen1.pem").is_file()   # the identity is the path


def test_a_second_run_keeps_every_key_and_signs_new_identities_with_the_same_ca(
        tmp_path: Path) -> None:
    directory = tmp_path / "certs"
    issue(directory, ["cpfc", "up"])
    before = {p: p.read_bytes() for p in directory.rglob("*") if p.is_file()}
    result = issue(directory, ["cpfc", "up", "der/New"])
    assert (result.ca_created, result.created, result.kept) == (False, ["der/New"],
                                                                 ["cpfc", "up"])
    assert {p: p.read_bytes() for p in before} == before
    load_cert(directory / "der" / "New.pem").verify_directly_issued_by(
        load_cert(directory / "ca.pem"))


def test_renew_replaces_one_identitys_key_and_force_replaces_everything(tmp_path: Path) -> None:
    directory = tmp_path / "certs"
    issue(directory, ["cpfc", "up"])
    ca, cpfc_key, up_key = ((directory / n).read_bytes() for n in ("ca.pem", "cpfc.key",
                                                                    "up.key"))
    renewed = issue(directory, ["cpfc", "up"], renew=["cpfc"])
    assert renewed.created == ["cpfc"] and renewed.kept == ["up"]
    assert (directory / "cpfc.key").read_bytes() != cpfc_key
    assert (directory / "up.key").read_bytes() == up_key
    assert (directory / "ca.pem").read_bytes() == ca
    load_cert(directory / "cpfc.pem").verify_directly_issued_by(load_cert(directory / "ca.pem"))
    forced = issue(directory, ["cpfc", "up"], force=True)
    assert forced.ca_created and forced.created == ["cpfc", "up"]
    assert (directory / "ca.pem").read_bytes() != ca
    assert mode(directory / "cpfc.key") == 0o600


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "ca.pem").unlink() or (d / "ca.key").unlink(), "keys without a CA"),
    (lambda d: (d / "cpfc.pem").unlink(), "exists without its pair"),
    (lambda d: (d / "ca.key").write_text("not a key"), "not a usable CA"),
])
def test_a_damaged_directory_is_a_one_line_error_and_nothing_is_overwritten(
        tmp_path: Path, damage, message: str) -> None:
    directory = tmp_path / "certs"
    issue(directory, ["cpfc", "up"])
    damage(directory)
    before = {p: p.read_bytes() for p in directory.rglob("*") if p.is_file()}
    with pytest.raises(UsageError, match=message):
        issue(directory, ["cpfc", "up"])
    assert {p: p.read_bytes() for p in directory.rglob("*") if p.is_file()} == before


def test_bad_hosts_days_and_renewals_are_refused(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="not a host name"):
        issue(tmp_path / "a", ["up"], hosts=["bad host"])
    with pytest.raises(UsageError, match="--days"):
        issue(tmp_path / "b", ["up"], days=0)
    with pytest.raises(UsageError, match="cannot renew der/X"):
        issue(tmp_path / "c", ["up"], renew=["der/X"])


def test_adnmesh_certs_reports_what_it_created_and_kept(tmp_path: Path, capsys) -> None:
    argv = ["certs", str(tmp_path / "certs"), "--config", str(CASE), "--router", "site"]
    assert main(argv) == 0
    assert "CA created; 8 certificate(s) created, 0 kept" in capsys.readouterr().out
    assert main(argv) == 0
    assert "CA kept; 0 certificate(s) created, 8 kept" in capsys.readouterr().out
    assert main([*argv, "--renew", "der/Nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot renew der/Nope" in err
