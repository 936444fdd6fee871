"""``adnmesh certs DIR [--config CONFIG]``: the certificates of the secure profile.

Creates in DIR one CA and one key and certificate per identity (:mod:`adnmesh.runtime.certificates`):
every agent of CONFIG (``cpfc``, ``measurement``, ``availability``, ``der/<id>`` per DER),
``up`` (router, recorder, clock) and ``operator`` (``adnmesh fault``); without CONFIG the
identities that do not depend on it. For a hierarchy file: every level's agents as
``<grid>:<agent>`` and each ADN's site router ``router/<adn>`` (docs/hierarchy.md). ``--router NAME`` adds a site router (``router/NAME``),
``--host`` the host names and addresses routers are reached at. Keys are readable by their
owner only; existing keys are kept unless ``--renew`` (those identities, signed by the same
CA: the rotation of a certificate) or ``--force`` (everything, a new CA) says otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from adnmesh.commands import comma_list, output_path
from adnmesh.errors import UsageError

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``certs`` subparser."""
    parser = subparsers.add_parser(
        "certs", help="create the CA and certificates of the secure profile",
        description="Create a CA and one key and certificate per identity in DIR: the agents "
        "of CONFIG, up (router, recorder, clock) and operator (adnmesh fault). Existing keys "
        "are never overwritten unless --renew or --force says so. Keys are mode 0600. Exit "
        "code 0 when the certificates are there, 2 for a user error (config, names, DIR).")
    parser.add_argument("directory", metavar="DIR", help="certificate directory (created)")
    parser.add_argument("--config", metavar="CONFIG",
                        help="config whose agents get certificates (without it: cpfc, "
                        "measurement, availability, up, operator); a hierarchy file: every "
                        "level's agents as <grid>:<agent> and each site's router")
    parser.add_argument("--router", metavar="NAME", action="append", default=[],
                        help="also a site router router/NAME (repeatable)")
    parser.add_argument("--host", metavar="HOST", action="append",
                        help="host name or IP address in every certificate (repeatable; "
                        "default: 127.0.0.1 and localhost)")
    parser.add_argument("--days", type=int, default=365, help="validity, days (default 365)")
    parser.add_argument("--renew", metavar="ID,...",
                        help="issue these identities again with new keys (rotation)")
    parser.add_argument("--force", action="store_true",
                        help="replace everything, the CA included")
    return parser


def run(args: argparse.Namespace) -> int:
    """Create what is missing; print what was created and kept."""
    from adnmesh.runtime.certificates import DEFAULT_HOSTS, issue
    from adnmesh.runtime.identity import identities, router_identity
    from adnmesh.names import LAUNCHER, OPERATOR, SINGLE_AGENT_KINDS

    if args.config:
        from adnmesh.config import is_hierarchy_file, load_config, load_hierarchy
        from adnmesh.runtime.identity import hierarchy_identities
        names = list(hierarchy_identities(load_hierarchy(args.config))
                     if is_hierarchy_file(args.config) else identities(load_config(args.config)))
    else:
        names = [*SINGLE_AGENT_KINDS, LAUNCHER, OPERATOR]
    names += [router_identity(n) for n in args.router]
    renew = comma_list(args.renew)
    directory = Path(args.directory)
    if directory.exists() and not directory.is_dir():
        raise UsageError(f"{directory}: not a directory")
    output_path(directory, "DIR", directory=True)
    result = issue(directory, names, hosts=args.host or DEFAULT_HOSTS, days=args.days,
                   force=args.force, renew=renew)
    ca = "created" if result.ca_created else "kept"
    print(f"adnmesh certs: {directory}: CA {ca}; {len(result.created)} certificate(s) "
          f"created, {len(result.kept)} kept")
    for name in result.created:
        print(f"  created {name}")
    return 0
