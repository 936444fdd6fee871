"""Injected faults: from the config or a request to the ``fault`` messages ``up`` sends.

A fault is one ``fault`` message (:class:`adnmesh.wire.messages.Fault`): a number, a kind, a
target, a window ``[start_ns, end_ns)`` and the kind's parameters. :class:`FaultPlan` numbers
the faults of a run, turns the config's faults and ``adnmesh fault`` requests into such bodies,
checks that their targets exist and that they start within the scenario (a one-line
:class:`FaultError` otherwise) and moves a start
that lies before what the run can still change to the earliest instant it can (and says so).
Agents apply them in their nodes (:mod:`adnmesh.sim.node`); a kill with an end is a restart,
which ``up`` (or the in-process runner) carries out.
"""

from __future__ import annotations

from dataclasses import dataclass

from msgspec import UNSET

from adnmesh.config import Config
from adnmesh.names import AGENTS_IN_WORDS, ICT_LINKS, der_agent_id
from adnmesh.wire.units import ns

__all__ = ["FaultError", "FaultPlan", "PlannedFault", "describe", "fault_events", "resend_body"]

_NEEDS = {"link_outage": "link", "link_loss": "link", "link_delay": "link",
          "der_offline": "der", "kill": "agent", "ict_outage": None}


class FaultError(ValueError):
    """A fault that cannot be injected (unknown target, missing parameter); one line."""


@dataclass(frozen=True)
class PlannedFault:
    """A fault of a run: the body of its ``fault`` message and whether its start was moved."""

    body: dict
    moved_from_ns: int | None = None

    @property
    def fault_id(self) -> int:
        return self.body["fault_id"]


def describe(body: dict) -> str:
    """One line: ``fault 3: link_outage of cpfc_to_der from 25 s for 5 s``."""
    target = next((body[k] for k in ("link", "der", "agent") if body.get(k) not in (None, UNSET)),
                  "all ICT")
    kind = body["kind"]
    start, end = body["start_ns"] / 1e9, body["end_ns"]
    extra = ""
    if kind == "link_loss":
        extra = f" (loss {body['probability']:g})"
    elif kind == "link_delay":
        extra = f" (+{body['delay_ns'] / 1e9:g} s delay)"
    if kind == "kill":
        span = f" at {start:g} s" + ("" if end is None else f", restarted at {end / 1e9:g} s")
    else:
        span = f" from {start:g} s" + (" on" if end is None else f" for {end / 1e9 - start:g} s")
    return f"fault {body['fault_id']}: {kind} of {target}{extra}{span}"


class FaultPlan:
    """The faults of one run (see the module docstring).

    Parameters
    ----------
    config : Config
    agents : iterable of str
        The run's agent ids (kill targets).
    """

    def __init__(self, config: Config, agents) -> None:
        self.der_ids = frozenset(config.der_ids())
        self.end_ns = ns(config.scenario.duration_s)
        self.agents = frozenset(agents)
        self.faults: list[PlannedFault] = []

    def from_config(self, config: Config) -> list[PlannedFault]:
        """The config's ``runtime.faults``, numbered from 1 (their starts are never moved)."""
        planned = []
        for f in config.runtime.faults:
            span = f.restart_after_s if f.kind == "kill" else f.duration_s
            planned.append(self.add(
                f.kind, ns(f.t_s), None if span is None else ns(span), origin="config",
                link=f.link, der=f.der, agent=f.agent, probability=f.probability,
                delay_ns=None if f.delay_s is None else ns(f.delay_s)))
        return planned

    def add(self, kind: str, at_ns: int, for_ns: int | None, *, earliest_ns: int = 0,
            origin: str = "command", **target) -> PlannedFault:
        """Plan one fault; its start is ``max(at_ns, earliest_ns)``.

        Raises
        ------
        FaultError
            Unknown kind or target, a missing parameter, a start after the scenario's end
            (such a fault could never act: it is refused, not listed as one never detected).
        """
        body = {"kind": kind, **self._target(kind, target)}
        start = max(int(at_ns), int(earliest_ns))
        if start > self.end_ns:
            when = (f"at {start / 1e9:g} s" if start == int(at_ns)
                    else f"at the earliest at {start / 1e9:g} s")
            raise FaultError(f"{kind} {when}: after the end of the scenario "
                             f"({self.end_ns / 1e9:g} s)")
        moved = int(at_ns) if start != int(at_ns) else None
        if for_ns is not None and for_ns <= 0:
            raise FaultError(f"{kind}: the duration must be positive")
        body.update(fault_id=len(self.faults) + 1, start_ns=start,
                    end_ns=None if for_ns is None else start + int(for_ns), origin=origin)
        planned = PlannedFault(body, moved)
        self.faults.append(planned)
        return planned

    def restarts(self) -> list[tuple[str, int]]:
        """``(agent, restart ns)`` of every kill with an end."""
        return [(f.body["agent"], f.body["end_ns"]) for f in self.faults
                if f.body["kind"] == "kill" and f.body["end_ns"] is not None]

    def _target(self, kind: str, target: dict) -> dict:
        if kind not in _NEEDS:
            raise FaultError(f"unknown fault kind {kind!r} (kinds: {', '.join(_NEEDS)})")
        needed = _NEEDS[kind]
        given = {k: v for k, v in target.items() if v is not None and v is not UNSET}
        if needed is not None and needed not in given:
            raise FaultError(f"{kind} needs a {needed}")
        out = {}
        if needed == "link":
            if given["link"] not in ICT_LINKS:
                raise FaultError(f"unknown link {given['link']!r} (links: "
                                 f"{', '.join(ICT_LINKS)})")
            out["link"] = given["link"]
        elif needed == "der":
            if given["der"] not in self.der_ids:
                raise FaultError(f"unknown DER {given['der']!r} (known: "
                                 f"{', '.join(sorted(self.der_ids))})")
            out["der"] = given["der"]
        elif needed == "agent":
            agent = given["agent"]
            if agent not in self.agents and der_agent_id(agent) in self.agents:
                agent = der_agent_id(agent)
            if agent not in self.agents:
                raise FaultError(f"unknown agent {given['agent']!r} (agents: {AGENTS_IN_WORDS})")
            out["agent"] = agent
        if kind == "link_loss":
            if "probability" not in given:
                raise FaultError("link_loss needs a probability")
            out["probability"] = float(given["probability"])
        if kind == "link_delay":
            if "delay_ns" not in given:
                raise FaultError("link_delay needs a delay")
            out["delay_ns"] = int(given["delay_ns"])
        return out


def fault_events(planned: PlannedFault) -> dict:
    """The body of ``up``'s event that a fault was injected."""
    text = describe(planned.body)
    if planned.moved_from_ns is not None:
        text += (f" (asked for {planned.moved_from_ns / 1e9:g} s, which the run had passed: "
                 "from the earliest instant it could still change)")
    return {"level": "WARNING", "kind": "fault_injected", "text": text,
            "fault_id": planned.fault_id}


def resend_body(planned: PlannedFault, now_ns: int) -> dict | None:
    """The fault again for an agent that rejoins at ``now_ns`` (None if it is over by then)."""
    body = planned.body
    if body["kind"] == "kill":
        return body if body["start_ns"] > now_ns else None
    if body["end_ns"] is not None and body["end_ns"] <= now_ns:
        return None
    return body
