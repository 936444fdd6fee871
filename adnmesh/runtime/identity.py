"""Identities of the secure profile, and where their certificates are.

An **identity** is who a process is on the bus: an agent id (``cpfc``, ``measurement``,
``availability``, ``der/<id>``; in a hierarchy's run ``<grid>:<agent id>``, for agent ids repeat
across its levels), ``up`` (``adnmesh up``: router, recorder, clock), ``operator``
(``adnmesh fault``) or ``router/<name>`` (a site router, ``adnmesh router``). It is the
certificate's common name (CN), which Zenoh's access control matches
(:mod:`adnmesh.runtime.acl`), and the file name below the certificate directory::

    DIR/ca.pem  DIR/ca.key                       the CA (its key signs; keep it off the hosts)
    DIR/<identity>.pem  DIR/<identity>.key       e.g. DIR/der/SGen1.pem, DIR/router/site.key

Creating them: :mod:`adnmesh.runtime.certificates` (``adnmesh certs``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from adnmesh.errors import UsageError
from adnmesh.names import AGENT_PATTERN, AGENTS_IN_WORDS, ID_PATTERN, LAUNCHER, OPERATOR, agent_ids

__all__ = ["CA", "CertFiles", "cert_files", "check_identity", "hierarchy_identities",
           "identities", "router_identity"]

CA = "ca"
"""File stem of the CA's certificate and key."""

_IDENTITY = re.compile(rf"^(?:(?:{ID_PATTERN}:)?{AGENT_PATTERN}|{LAUNCHER}|{OPERATOR}|"
                       rf"router/{ID_PATTERN})$")


MAX_IDENTITY_CHARS = 64
"""The longest identity: a certificate's common name (X.509's upper bound)."""


def router_identity(name: str) -> str:
    """Identity of the site router ``name``: ``router/<name>``."""
    return check_identity(f"router/{name}")


def check_identity(identity: str) -> str:
    """``identity`` if it is one (see the module docstring); else a :class:`UsageError`."""
    if len(identity) > MAX_IDENTITY_CHARS or not _IDENTITY.fullmatch(identity):
        raise UsageError(f"not an identity: {identity!r} ({AGENTS_IN_WORDS}, each also as "
                         f"<grid>:<agent> in a hierarchy, {LAUNCHER}, {OPERATOR}, "
                         f"router/<name>; at most {MAX_IDENTITY_CHARS} characters, an X.509 "
                         "common name's)")
    return identity


def identities(config) -> tuple[str, ...]:
    """Every identity a run of ``config`` needs: its agents, ``up`` and ``operator``."""
    return (*agent_ids(config.der_ids()), LAUNCHER, OPERATOR)


def hierarchy_identities(hierarchy) -> tuple[str, ...]:
    """Every identity ``adnmesh up`` of ``hierarchy`` needs: each level's agents as
    ``<grid>:<agent>`` (the upper grid's DERs are its ADNs' site agents), each ADN's site
    router ``router/<adn>``, ``up`` and ``operator``."""
    from adnmesh.config import load_config

    upper = [f"{hierarchy.name}:{a}" for a in agent_ids(a.id for a in hierarchy.adns)]
    lower = [f"{adn.id}:{a}" for adn in hierarchy.adns
             for a in agent_ids(load_config(hierarchy.config_path(adn)).der_ids())]
    routers = [router_identity(adn.id) for adn in hierarchy.adns]
    return tuple(check_identity(i) for i in (*upper, *lower, *routers, LAUNCHER, OPERATOR))


@dataclass(frozen=True)
class CertFiles:
    """Where an identity's certificate and key are, and the CA that signed them."""

    identity: str
    cert: Path
    key: Path
    ca: Path

    def check(self) -> CertFiles:
        """Self, if all three files are readable; else a one-line :class:`UsageError`."""
        for path in (self.ca, self.cert, self.key):
            if not os.access(path, os.R_OK):
                raise UsageError(f"{path}: missing or unreadable (the certificate of "
                                 f"{self.identity}; create it with 'adnmesh certs "
                                 f"{self.ca.parent} --config CONFIG')")
        return self


def cert_files(directory: str | os.PathLike, identity: str) -> CertFiles:
    """The files of ``identity`` below ``directory`` (not checked; see :meth:`CertFiles.check`)."""
    root = Path(directory)
    stem = root / check_identity(identity)
    return CertFiles(identity, stem.with_suffix(".pem"), stem.with_suffix(".key"),
                     root / f"{CA}.pem")
