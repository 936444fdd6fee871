"""The secure profile's Zenoh configuration: mutual TLS on every link, access control on routers.

A session of the secure profile (:func:`apply_tls`) speaks only TLS (``transport/link/protocols``
is ``["tls"]``), trusts only the run's CA (``root_ca_certificate``), presents its identity's
certificate on every link it opens and, as a router, on every link it accepts, and requires one
from every peer (``enable_mtls``): a session without a certificate, or with one from another
CA, never completes the handshake. Links are cut when a certificate expires
(``close_link_on_expiration``); the server's certificate must name the host a client connects to
(``verify_name_on_connect``). A router adds the access control of :mod:`adnmesh.runtime.acl`
(:func:`apply_access_control`). The whole TLS block is set with one ``insert_json5``, as Zenoh
wants it.

Endpoints of the secure profile are ``tls/HOST:PORT``; :func:`check_endpoints` says so to a user
who mixes them up.
"""

from __future__ import annotations

import json

import zenoh

from adnmesh.errors import UsageError
from adnmesh.runtime.identity import CertFiles

__all__ = ["apply_access_control", "apply_tls", "check_endpoints", "endpoint_address",
           "tls_settings"]


def tls_settings(files: CertFiles, listen: bool = False) -> dict:
    """The ``transport/link/tls`` block of a session of identity ``files.identity`` (a router
    also presents its certificate on the links it accepts: ``listen``)."""
    block = {
        "root_ca_certificate": str(files.ca),
        "enable_mtls": True,
        "connect_certificate": str(files.cert),
        "connect_private_key": str(files.key),
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }
    if listen:
        block["listen_certificate"] = str(files.cert)
        block["listen_private_key"] = str(files.key)
    return block


def apply_tls(config: zenoh.Config, files: CertFiles, listen: bool = False) -> zenoh.Config:
    """Make ``config`` a secure-profile session of ``files.identity`` (see the module
    docstring); return it."""
    config.insert_json5("transport/link/tls", json.dumps(tls_settings(files.check(), listen)))
    config.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    return config


def apply_access_control(config: zenoh.Config, access_control: dict) -> zenoh.Config:
    """Set the router's ``access_control`` section (:func:`adnmesh.runtime.acl.access_control`);
    return ``config``."""
    config.insert_json5("access_control", json.dumps(access_control))
    return config


_HOST_PORT = ("tcp", "tls", "udp", "quic")
"""Protocols whose address is ``HOST:PORT`` (an IPv6 host in brackets)."""


def endpoint_address(endpoint: str) -> tuple[str, str, int] | None:
    """``(protocol, host, port)`` of a ``tcp``/``tls``/``udp``/``quic`` endpoint, None for
    another protocol (Zenoh checks those itself).

    Raises
    ------
    ValueError
        Not of the form ``<protocol>/<address>[?<metadata>][#<config>]``, or a host or port
        that is not one (a port is 0 to 65535).
    """
    protocol, slash, rest = str(endpoint).partition("/")
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if not (slash and protocol and address) or not protocol.replace("-", "").isalnum():
        raise ValueError("not an endpoint (PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447)")
    if protocol not in _HOST_PORT:
        return None
    host, colon, port = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not (colon and host and port.isdigit() and int(port) <= 65535) \
            or any(c.isspace() or c in "[]/" for c in host):
        raise ValueError(f"{protocol} endpoints are {protocol}/HOST:PORT with a port from 0 to "
                         "65535")
    return protocol, host, int(port)


def check_endpoints(endpoints, secure: bool, flag: str = "--connect") -> None:
    """A one-line :class:`UsageError` if an endpoint is not one (:func:`endpoint_address`) or
    does not fit the profile: ``tls/`` with certificates, anything but ``tls/`` without."""
    for endpoint in endpoints or ():
        try:
            endpoint_address(endpoint)
        except ValueError as exc:
            raise UsageError(f"{flag} {endpoint}: {exc}") from None
        tls = str(endpoint).startswith("tls/")
        if secure and not tls:
            raise UsageError(f"{flag} {endpoint}: the secure profile speaks only TLS; use "
                             "tls/HOST:PORT")
        if tls and not secure:
            raise UsageError(f"{flag} {endpoint}: a tls/ endpoint needs certificates "
                             "(--certs DIR)")
