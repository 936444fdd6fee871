"""``adnmesh router CONFIG --name NAME --connect ENDPOINT [--listen ENDPOINT] [--certs DIR]
[--levels FILE [--record FILE --run-id ID]]``.

A site router: a Zenoh router session (no daemon) on another host, linked to ``adnmesh up``'s
router; the agents of that site (``adnmesh agent ... --connect`` this router's endpoint) reach
the run through it. In the secure profile it presents the certificate ``router/NAME``, accepts
only clients with certificates of the run's CA and enforces the same access control as
``up``'s router on them (:mod:`adnmesh.runtime.acl`; ``up`` is its peer); ``up`` must be told
of it (``adnmesh up --routers NAME``). Runs until SIGINT/SIGTERM, or with ``--until-run-ends``
until ``up``'s liveliness, once seen, is withdrawn.

As the site of ADN NAME in a hierarchy's run (``--levels``, set by ``adnmesh up``): only that
site's agents may be its clients, and ``--record`` also records what they publish
(:mod:`adnmesh.runtime.site_recorder`).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from adnmesh.commands import add_config_argument

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``router`` subparser."""
    parser = subparsers.add_parser(
        "router", help="run a site router linked to the router of 'adnmesh up'",
        description="Run a Zenoh router for the agents of one site, linked to the router of "
        "'adnmesh up' (--connect). With --certs: mutual TLS with the certificate router/NAME "
        "and the run's access control on its own clients. Exit code 0 after SIGINT/SIGTERM or "
        "the end of the run (--until-run-ends), 1 if the router cannot start.")
    add_config_argument(parser)
    parser.add_argument("--name", required=True, help="the site's name (identity router/NAME)")
    parser.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", required=True,
                        help="the router of adnmesh up (tcp/HOST:PORT, tls/ with --certs)")
    parser.add_argument("--listen", "-l", metavar="ENDPOINT", action="append",
                        help="where this router listens (default: 127.0.0.1, a free port)")
    parser.add_argument("--certs", metavar="DIR", help="secure profile: certificate directory")
    parser.add_argument("--until-run-ends", action="store_true",
                        help="exit when the run ends (up's liveliness is withdrawn)")
    parser.add_argument("--levels", metavar="FILE",
                        help="as the site of ADN NAME in a hierarchy's run: the levels file "
                        "adnmesh up wrote (only the site's agents may be clients; set by "
                        "adnmesh up)")
    parser.add_argument("--record", metavar="FILE",
                        help="with --levels and --run-id: also record what the site's agents "
                        "(ADN NAME's and the upper level's der/NAME) publish, to FILE (MCAP)")
    parser.add_argument("--run-id", metavar="ID", help="with --record: the run's id")
    return parser


def _access_control(args: argparse.Namespace):
    """``(topology, access control)`` of the router: the config's run, or with ``--levels`` a
    site of the hierarchy's (its agents ``<grid>:<agent id>``; only the site's own may be its
    clients)."""
    from adnmesh.config import load_config
    from adnmesh.errors import UsageError
    from adnmesh.names import LAUNCHER
    from adnmesh.runtime import acl
    from adnmesh.sim.topology import Topology

    if args.levels is None:
        topology = Topology.from_config(load_config(args.config))
        return topology, acl.access_control(topology, [LAUNCHER])
    from adnmesh.sim.hierarchy_levels import load_levels
    levels = load_levels(args.levels)
    if args.name not in levels.adns:
        raise UsageError(f"--levels: {args.name} is no ADN of {args.levels} (known: "
                         f"{', '.join(levels.adns)})")
    return levels.topology, acl.access_control(levels.topology, [LAUNCHER],
                                               clients=levels.site_members(args.name))


def _site_recorder(args: argparse.Namespace):
    """The site's recorder of ``--record`` (:mod:`adnmesh.runtime.site_recorder`), or None."""
    from adnmesh.errors import UsageError

    if args.record is None:
        if args.run_id is not None:
            raise UsageError("--run-id is for --record")
        return None
    if args.levels is None or args.run_id is None:
        raise UsageError("--record needs --levels and --run-id (a site of a hierarchy's run)")
    from adnmesh.commands import output_path
    from adnmesh.runtime.site_recorder import SiteRecorder
    from adnmesh.sim.hierarchy_levels import load_levels

    if not args.run_id.strip():
        raise UsageError("--run-id must name the run")
    path = output_path(args.record, "--record")
    try:
        return SiteRecorder(path, load_levels(args.levels), args.name, args.run_id)
    except OSError as exc:        # a full disk: the site runs on, unrecorded here (up records)
        print(f"adnmesh router router/{args.name}: not recording to {path}: "
              f"{exc.strerror or exc}", file=sys.stderr, flush=True)
        return None


def run(args: argparse.Namespace) -> int:
    """Run the router until told to stop."""
    import zenoh

    from adnmesh.runtime.bus import DEFAULT_HOST, free_port, router_config
    from adnmesh.runtime.identity import router_identity
    from adnmesh.runtime.process import die_with_parent
    from adnmesh.names import LAUNCHER

    topology, access = _access_control(args)
    identity = router_identity(args.name)
    scheme = "tcp" if args.certs is None else "tls"
    listen = args.listen or [f"{scheme}/{DEFAULT_HOST}:{free_port()}"]
    config = router_config(listen, args.connect, certs=args.certs, identity=identity,
                           access_control=access)
    done, seen = threading.Event(), threading.Event()

    def on_up(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            seen.set()
            print(f"adnmesh router {identity}: adnmesh up is reachable", file=sys.stderr,
                  flush=True)
        elif seen.is_set() and args.until_run_ends:
            done.set()

    die_with_parent()     # a site router adnmesh up started ends with it
    recorder = _site_recorder(args)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        print(f"adnmesh router {identity}: cannot start: {str(exc).split(' at ')[0]}",
              file=sys.stderr)
        if recorder is not None:
            recorder.close()
        return 1
    previous = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT,
                                                                    signal.SIGTERM)}
    try:
        if recorder is not None:
            recorder.declare(session)
        watcher = session.liveliness().declare_subscriber(
            topology.keys.liveliness(LAUNCHER), on_up, history=True)
        print(f"adnmesh router {identity}: listening on {', '.join(listen)}, linked to "
              f"{', '.join(args.connect)}", file=sys.stderr, flush=True)
        while not done.wait(0.5):
            pass
        watcher.undeclare()
    finally:
        failed = recorder.close() if recorder is not None else None
        session.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if failed:
        print(f"adnmesh router {identity}: {failed}", file=sys.stderr, flush=True)
        return 1
    return 0
