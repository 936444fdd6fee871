"""The names everything on the bus goes by: ids, agent kinds, parties, ICT links, fault kinds.

A **DER id** or grid name is a short identifier (:data:`ID_PATTERN`). An **agent id** names one
agent process: the kind itself for the kinds that run once (``cpfc``, ``measurement``,
``availability``), ``der/<id>`` for the kind that runs once per DER. Besides the agents, two
parties send messages: ``up`` (:data:`LAUNCHER`: ``adnmesh up`` itself, its recorder and sim
clock) and ``operator`` (:data:`OPERATOR`: a person's ``adnmesh fault``).

The **ICT links** (:data:`ICT_LINKS`) are the communication paths of the channel model, the ones
faults disturb; :data:`FAULT_KINDS` are the faults a config or ``adnmesh fault`` can inject.

This is the foundation's vocabulary: the config validates names with it, the protocol table
(:mod:`adnmesh.wire.protocol`) builds keys from it, the secure profile names certificates after
it. Nothing here imports anything of adnmesh.
"""

from __future__ import annotations

from collections.abc import Iterable

__all__ = [
    "AGENT_KINDS",
    "AGENT_PATTERN",
    "AGENTS_IN_WORDS",
    "FAULT_KINDS",
    "ICT_LINKS",
    "ID_MAX_CHARS",
    "ID_PATTERN",
    "LAUNCHER",
    "OPERATOR",
    "PER_DER_KIND",
    "SINGLE_AGENT_KINDS",
    "agent_ids",
    "der_agent_id",
    "der_id_of",
    "kind_of",
]

ID_PATTERN = r"[A-Za-z][A-Za-z0-9_-]*"
"""A grid name or DER id: letters, digits, ``_`` and ``-``, starting with a letter."""

ID_MAX_CHARS = 64
"""Longest DER id or grid name."""

PER_DER_KIND = "der"
"""The agent kind that runs once per DER (agent id ``der/<id>``)."""

AGENT_KINDS = ("cpfc", "measurement", "availability", PER_DER_KIND)
"""Every kind of agent, in the order a run lists its agents."""

SINGLE_AGENT_KINDS = AGENT_KINDS[:-1]
"""The kinds that run once per run (agent id: the kind itself)."""

AGENT_PATTERN = rf"(?:{'|'.join(SINGLE_AGENT_KINDS)}|{PER_DER_KIND}/{ID_PATTERN})"
"""An agent id (a regular expression without anchors)."""

AGENTS_IN_WORDS = f"{', '.join(SINGLE_AGENT_KINDS)}, {PER_DER_KIND}/<id>"
"""The agent ids as a person reads them in an error message."""

ICT_LINKS = ("cpfc_to_der", "measurement_to_cpfc", "der_to_availability", "availability_to_cpfc")
"""The ICT links: P_Y to the DERs (delay ``t_com_s``), P_IP to the CPFC (``t_meas_s``), the DERs'
heartbeats to the availability monitor (and the CPFC), SI to the CPFC."""

FAULT_KINDS = ("link_outage", "link_loss", "link_delay", "der_offline", "ict_outage", "kill")
"""Kinds of injectable fault (:class:`adnmesh.wire.messages.Fault` says what each does)."""

LAUNCHER = "up"
"""The sender id of ``adnmesh up`` itself."""

OPERATOR = "operator"
"""The sender id of a person's command to a running ``up`` (``adnmesh fault``)."""


def der_agent_id(der_id: str) -> str:
    """Agent id of the local controller of DER ``der_id``: ``der/<id>``."""
    return f"{PER_DER_KIND}/{der_id}"


def der_id_of(agent_id: str) -> str | None:
    """The DER id of agent ``der/<id>``, else None."""
    prefix = f"{PER_DER_KIND}/"
    return agent_id[len(prefix):] if agent_id.startswith(prefix) else None


def kind_of(agent_id: str) -> str:
    """The kind of agent ``agent_id``: ``der`` for ``der/<id>``, else the id itself."""
    return PER_DER_KIND if der_id_of(agent_id) is not None else agent_id


def agent_ids(der_ids: Iterable[str]) -> tuple[str, ...]:
    """Every agent of a run with DERs ``der_ids``: the single kinds, then one per DER in the
    order given."""
    return (*SINGLE_AGENT_KINDS, *(der_agent_id(d) for d in der_ids))
