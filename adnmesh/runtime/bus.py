"""Zenoh session configuration shared by ``adnmesh up`` and every agent program.

Connection flags are defined once (:func:`add_connection_arguments`), as in the zenoh-python
examples: ``--mode``, ``--connect``, ``--listen``, ``--zenoh-config``. Multicast scouting is always
off; endpoints are explicit. ``adnmesh up`` embeds the router (a session in mode ``router``,
:func:`router_config`) listening on ``tcp/127.0.0.1:<port>`` by default; agents connect to it as
clients. To run an agent on another host, point ``--connect`` at a router reachable from there.

``--certs DIR`` (the ``certs`` and ``identity`` arguments below) selects the secure profile:
mutual TLS with the identity's certificate from DIR, endpoints ``tls/HOST:PORT``, and on a
router the access control of :mod:`adnmesh.runtime.acl` (:mod:`adnmesh.runtime.security`).
"""

from __future__ import annotations

import argparse
import json
import socket

import zenoh

__all__ = ["DEFAULT_ENDPOINT", "DEFAULT_HOST", "add_connection_arguments", "check_listen",
           "client_config", "free_port", "router_config", "session_config"]

DEFAULT_HOST = "127.0.0.1"
"""The only address adnmesh uses unless told otherwise."""

DEFAULT_ENDPOINT = f"tcp/{DEFAULT_HOST}:7447"
"""Where a client connects without ``--connect`` (Zenoh's usual router port on this host)."""

LEASE_MS = 30_000
"""The lease every adnmesh session announces, ms (Zenoh's default: 10 s): a link is closed
when nothing came over it for this long. A realtime run faster than the machine can keep up
with starves processes for seconds at a time (measured at ``--speed 20`` on SimBench: 9 of 14
sessions dropped with 10 s); a process that dies closes its TCP link at once anyway."""

KEEP_ALIVE = 10
"""Keep-alive messages per lease (Zenoh's default: 4): one every 3 s."""

SHARED_MEMORY = False
"""Whether sessions may use Zenoh's shared-memory transport (zenoh 1.x default: on, with a
16 MiB pool per session and only for messages of 3 KiB or more). adnmesh's messages are under a
few hundred bytes and never reach it, but each session would still set the pool up and map its
peers' (docs/performance.md#runtime-memory-and-start-up); a ``--zenoh-config`` file may turn
it on again."""

BLOCK_BEFORE_CLOSE_US = 30_000_000
"""How long a session may wait for room in a link's queue to send a message (congestion
control ``BLOCK``, which adnmesh uses) before Zenoh closes the link, µs (default 5 s)."""


def add_connection_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--mode``, ``--connect``, ``--listen``, ``--zenoh-config`` and ``--certs`` to
    ``parser``."""
    group = parser.add_argument_group("Zenoh connection")
    group.add_argument("--mode", "-m", choices=["client", "peer"], default="client",
                       help="Zenoh session mode (default: client)")
    group.add_argument("--connect", "-e", metavar="ENDPOINT", action="append",
                       help="endpoint to connect to (repeatable; a client's default: "
                       f"{DEFAULT_ENDPOINT})")
    group.add_argument("--listen", "-l", metavar="ENDPOINT", action="append",
                       help="endpoint to listen on (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE",
                       help="a Zenoh configuration file (JSON5); the flags above override it")
    group.add_argument("--certs", metavar="DIR",
                       help="secure profile: mutual TLS with this program's certificate from "
                       "DIR (made by 'adnmesh certs'); endpoints tls/HOST:PORT")


def session_config(args: argparse.Namespace, identity: str | None = None) -> zenoh.Config:
    """The Zenoh config of a session from the flags of :func:`add_connection_arguments`
    (``identity``: whose certificate ``--certs`` holds)."""
    config = (zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config
              else zenoh.Config())
    config.insert_json5("mode", json.dumps(args.mode))
    connect = args.connect
    if not connect and args.mode == "client" and not args.zenoh_config:
        connect = [DEFAULT_ENDPOINT]
    _check_forms(connect, args.listen)
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    if args.listen:
        config.insert_json5("listen/endpoints", json.dumps(args.listen))
    config.insert_json5("scouting/multicast/enabled", "false")
    if not args.zenoh_config:
        _lease(config)
        _shared_memory(config)
    certs = getattr(args, "certs", None)
    if certs is not None or not args.zenoh_config:   # a config file may bring its own TLS
        _profile(config, connect, args.listen, certs, identity, accepts=bool(args.listen))
    return config


def client_config(connect: list[str], certs=None, identity: str | None = None) -> zenoh.Config:
    """The Zenoh config of a client session connecting to ``connect`` (secure profile: with
    the certificate of ``identity`` from the directory ``certs``)."""
    _check_forms(connect, ())
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps(connect))
    config.insert_json5("scouting/multicast/enabled", "false")
    _lease(config)
    _shared_memory(config)
    _profile(config, connect, (), certs, identity)
    return config


def router_config(listen: list[str], connect=(), certs=None, identity: str | None = None,
                  access_control: dict | None = None) -> zenoh.Config:
    """The Zenoh config of a router listening on ``listen`` and linked to the routers at
    ``connect``; secure profile: with the certificate of ``identity`` from ``certs`` and the
    ``access_control`` section (:func:`adnmesh.runtime.acl.access_control`)."""
    _check_forms(connect, listen)
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    _lease(config)
    _shared_memory(config)
    _profile(config, connect, listen, certs, identity, accepts=True)
    if certs is not None:
        from adnmesh.runtime.security import apply_access_control
        apply_access_control(config, access_control or {"enabled": True})
    return config


def _check_forms(connect, listen) -> None:
    """A one-line UsageError for an endpoint that is not one, before Zenoh reads it (its own
    error is a multi-line exception)."""
    from adnmesh.errors import UsageError
    from adnmesh.runtime.security import endpoint_address

    for flag, endpoints in (("--connect", connect), ("--listen", listen)):
        for endpoint in endpoints or ():
            try:
                endpoint_address(endpoint)
            except ValueError as exc:
                raise UsageError(f"{flag} {endpoint}: {exc}") from None


def check_listen(endpoint: str, flag: str = "--listen") -> None:
    """A one-line UsageError if this host cannot listen on ``endpoint`` now: not an endpoint,
    an address not of this host, a port in use or not allowed (a socket is bound there and
    closed again, as Zenoh's listener will bind it: ``SO_REUSEADDR``)."""
    from adnmesh.errors import UsageError
    from adnmesh.runtime.security import endpoint_address

    try:
        found = endpoint_address(endpoint)
    except ValueError as exc:
        raise UsageError(f"{flag} {endpoint}: {exc}") from None
    if found is None:
        return
    protocol, host, port = found
    kind = socket.SOCK_DGRAM if protocol in ("udp", "quic") else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(host, port, type=kind)
    except (socket.gaierror, UnicodeError) as exc:
        raise UsageError(f"{flag} {endpoint}: unknown host {host!r} "
                         f"({getattr(exc, 'strerror', None) or exc})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            raise UsageError(f"{flag} {endpoint}: cannot listen there: "
                             f"{exc.strerror or exc}") from None


def _lease(config: zenoh.Config) -> None:
    config.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    config.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVE))
    config.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                        str(BLOCK_BEFORE_CLOSE_US))


def _shared_memory(config: zenoh.Config) -> None:
    config.insert_json5("transport/shared_memory/enabled", json.dumps(SHARED_MEMORY))


def _profile(config: zenoh.Config, connect, listen, certs, identity: str | None,
             accepts: bool = False) -> None:
    """Secure profile if ``certs`` is given (TLS with ``identity``'s certificate); else check
    that no endpoint asks for TLS."""
    from adnmesh.errors import UsageError
    from adnmesh.runtime.security import apply_tls, check_endpoints

    secure = certs is not None
    check_endpoints(connect, secure)
    check_endpoints(listen, secure, flag="--listen")
    if secure:
        if identity is None:
            raise UsageError("--certs: this program has no identity of its own")
        from adnmesh.runtime.identity import cert_files
        apply_tls(config, cert_files(certs, identity), listen=accepts)


def free_port(host: str = DEFAULT_HOST) -> int:
    """A TCP port on ``host`` that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]
