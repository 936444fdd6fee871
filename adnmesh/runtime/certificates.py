"""Certificates of the secure profile: one CA, one certificate per identity.

The identities and where their files are: :mod:`adnmesh.runtime.identity`. Keys are ECDSA
P-256 (PKCS#8 PEM, unencrypted, mode 0600 in directories of mode 0700); certificates carry the
identity as CN, the hosts as subject alternative names (a router's listening certificate is
checked against the address a client connects to) and are valid for server and client
authentication. :func:`issue` never overwrites an existing key unless told to
(``force`` for everything, ``renew`` for some identities: the rotation of a certificate).
Creating them is done by the ``cryptography`` library; nothing here talks to Zenoh.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from adnmesh.errors import UsageError
from adnmesh.runtime.identity import CA, cert_files, check_identity

__all__ = ["DEFAULT_HOSTS", "IssueResult", "issue"]

DEFAULT_HOSTS = ("127.0.0.1", "localhost")
"""Subject alternative names of every certificate unless told otherwise."""

_VALID_FROM = datetime.timedelta(minutes=5)   # tolerance for clocks slightly behind


@dataclass
class IssueResult:
    """What :func:`issue` did: identities whose key and certificate it created, those it kept."""

    ca_created: bool = False
    created: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)


def issue(directory: str | os.PathLike, names, hosts=DEFAULT_HOSTS, days: int = 365,
          force: bool = False, renew=()) -> IssueResult:
    """Create the CA (unless there is one) and a key and certificate for every identity.

    Parameters
    ----------
    directory : path
        The certificate directory (created, mode 0700).
    names : iterable of str
        Identities (see the module docstring).
    hosts : iterable of str
        Host names and IP addresses of every certificate (subject alternative names).
    days : int
        Validity, days from now.
    force : bool
        Replace everything, the CA included (every old certificate stops working).
    renew : iterable of str
        Identities to issue again with a new key, signed by the existing CA (rotation).

    Raises
    ------
    UsageError
        For an invalid identity or host, a half-present key pair, an unusable CA.
    """
    if not 1 <= days <= 36500:
        raise UsageError(f"--days must be in [1, 36500], got {days}")
    root = Path(directory)
    names = [check_identity(n) for n in dict.fromkeys(names)]
    renew = {check_identity(n) for n in renew}
    unknown = sorted(renew - set(names))
    if unknown:
        raise UsageError(f"cannot renew {', '.join(unknown)}: not an identity of this config")
    san = x509.SubjectAlternativeName([_general_name(h) for h in dict.fromkeys(hosts)])
    result = IssueResult()
    _mkdir(root)
    ca_cert_path, ca_key_path = root / f"{CA}.pem", root / f"{CA}.key"
    if force or not (ca_cert_path.exists() or ca_key_path.exists()):
        existing = [n for n in names if cert_files(root, n).key.exists()]
        if existing and not force:
            raise UsageError(f"{root}: keys without a CA ({', '.join(existing[:3])}); "
                             "--force makes a new CA and replaces every key")
        ca_key, ca_cert = _new_ca(root.resolve().name, days)
        _write_pair(ca_cert_path, ca_key_path, ca_key, ca_cert, replace=force)
        result.ca_created = True
    else:
        ca_key, ca_cert = _load_ca(ca_cert_path, ca_key_path)
    for name in names:
        files = cert_files(root, name)
        present = files.cert.exists(), files.key.exists()
        if any(present) and not (force or name in renew):
            if not all(present):
                raise UsageError(f"{files.cert if present[0] else files.key} exists without "
                                 f"its pair; remove it or renew {name}")
            result.kept.append(name)
            continue
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _sign(ca_key, ca_cert, name, key, san, days)
        _write_pair(files.cert, files.key, key, cert, replace=True)
        result.created.append(name)
    return result


# -- internals -----------------------------------------------------------------------------------


def _general_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?", host):
        raise UsageError(f"--host: not a host name or IP address: {host!r}")
    return x509.DNSName(host)


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "adnmesh"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _validity(builder: x509.CertificateBuilder, days: int) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.timezone.utc)
    return builder.not_valid_before(now - _VALID_FROM).not_valid_after(
        now + datetime.timedelta(days=days))


def _new_ca(label: str, days: int):
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(f"adnmesh CA {label}"[:64])
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                          content_commitment=False, key_encipherment=False,
                          data_encipherment=False, key_agreement=False, encipher_only=False,
                          decipher_only=False)
    cert = (_validity(x509.CertificateBuilder(), days).subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(usage, critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))
    return key, cert


def _load_ca(cert_path: Path, key_path: Path):
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        cert.verify_directly_issued_by(cert)
    except FileNotFoundError as exc:
        raise UsageError(f"{exc.filename}: missing (the CA needs both {cert_path.name} and "
                         f"{key_path.name}; --force makes a new CA)") from None
    except (ValueError, TypeError, InvalidSignature) as exc:
        raise UsageError(f"{cert_path.parent}: not a usable CA ({exc})") from None
    if key.public_key().public_numbers() != cert.public_key().public_numbers():
        raise UsageError(f"{key_path}: not the key of {cert_path}")
    return key, cert


def _sign(ca_key, ca_cert, identity: str, key, san, days: int) -> x509.Certificate:
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                          content_commitment=False, key_encipherment=False,
                          data_encipherment=False, key_agreement=True, encipher_only=False,
                          decipher_only=False)
    return (_validity(x509.CertificateBuilder(), days).subject_name(_name(identity))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(usage, critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(san, critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))


def _mkdir(path: Path) -> None:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)


def _write_pair(cert_path: Path, key_path: Path, key, cert, replace: bool) -> None:
    """Write the key (0600, never over an existing file unless ``replace``), then the cert."""
    _mkdir(key_path.parent)
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if replace else os.O_EXCL)
    try:
        fd = os.open(key_path, flags, 0o600)
    except FileExistsError:
        raise UsageError(f"{key_path} exists; not overwritten") from None
    with os.fdopen(fd, "wb") as out:
        os.fchmod(out.fileno(), 0o600)
        out.write(pem)
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
