"""Test helper: a rogue Zenoh session that attacks a running ``adnmesh up``.

The attacks are the issue's: forged but *valid* messages with the right sender id (a correcting
variable driving the DERs to full rating, another DER's state, a measurement of 50 MW, an SI
that takes every DER away, a clock stop; plus a clock grant, a fault, a fault request and
``up``'s liveliness token), each delivered at a sim time the run has not reached, so that a
receiver that accepts it acts on it. In the secure profile the rogue holds a DER's certificate
and also sends junk on that DER's own keys (the only keys its certificate may publish), which
the receivers reject and count. Every attempt is counted by the rogue.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from adnmesh.wire.keys import Keys
from payloads import BODIES, payload

AT_NS = 300 * 10 ** 9
"""When the forged messages claim to be sent and delivered unless told: 300 s of sim time."""


@dataclass(frozen=True)
class Attempt:
    """One thing the rogue tries: publish ``payload`` on ``key``."""

    name: str
    key: str
    payload: bytes


@dataclass
class RogueReport:
    """What the rogue did and saw."""

    sent: list[str] = field(default_factory=list)          # attempt names, in order
    received: dict[str, int] = field(default_factory=dict)  # key -> samples it got


def forged_attacks(grid: str, victim: str = "SGen2", at_ns: int = AT_NS) -> list[Attempt]:
    """Valid forged messages with the right sender, sent and delivered at ``at_ns``."""
    keys = Keys(grid)
    seq = 10 ** 9            # newer than anything the run has sent on any key
    forged = [
        ("correcting variable P_Y = 1 (every DER to its full rating)", keys.of("p_y"),
         {**BODIES["p_y"], "p_y": 1.0}),
        (f"state of der/{victim} (10 MW)", keys.of("der_state", victim),
         {"p_w": 1e7, "setpoint_w": 1e7, "mode": "control"}),
        ("measurement P_IP = 50 MW", keys.of("p_ip"), {"p_ip_w": 5e7}),
        ("SI: every DER unavailable", keys.of("si"), {"si": {"SGen1": False, victim: False}}),
        ("clock stop", keys.of("clock_stop"), {"reason": "rogue"}),
        ("clock grant to the CPFC", keys.of("clock_grant", "cpfc"),
         {"until_ns": 10 ** 15, "expect": 0}),
        ("fault: ICT outage", keys.of("fault"),
         {**BODIES["fault"], "start_ns": at_ns, "end_ns": at_ns + 10 ** 10}),
        ("fault request (operator)", keys.of("fault_request"), {**BODIES["fault_request"],
                                                          "request_id": "rogue"}),
    ]
    return [Attempt(name, key, payload(key, body, seq=seq, t_send_ns=at_ns))
            for name, key, body in forged]


def junk_on_own_keys(grid: str, der: str, n: int) -> list[Attempt]:
    """``n`` invalid payloads on each of DER ``der``'s own keys (state, heartbeat)."""
    keys = Keys(grid)
    found = []
    for key in (keys.of("der_state", der), keys.of("heartbeat", der)):
        for i in range(n):
            body = b'{"v":1,"type":' + str(i).encode() if i % 2 else b"\xff\xfe junk"
            found.append(Attempt(f"junk on {key}", key, body))
    return found


def rogue_config(endpoint: str, certs: Path | None, identity: str | None):
    """The rogue's session config (with ``identity``'s certificate from ``certs``)."""
    from adnmesh.runtime.bus import client_config
    return client_config([endpoint], certs, identity)


def attack(config, attempts: list[Attempt], grid: str, listen_to=(),
           up_token: bool = False) -> RogueReport:
    """Open a session with ``config``; subscribe to ``listen_to``; with ``up_token`` declare
    ``up``'s liveliness token (and withdraw it at the end, as a departing ``up`` would); send
    every attempt (in order, on one session); close."""
    import zenoh

    report = RogueReport()
    keys = Keys(grid)
    with zenoh.open(config) as session:
        subscribers = [session.declare_subscriber(
            key, lambda s, k=key: report.received.update({k: report.received.get(k, 0) + 1}),
            allowed_origin=zenoh.Locality.REMOTE) for key in listen_to]
        token = session.liveliness().declare_token(keys.liveliness("up")) if up_token else None
        for attempt in attempts:
            session.put(attempt.key, attempt.payload,
                        congestion_control=zenoh.CongestionControl.BLOCK)
            report.sent.append(attempt.name)
        if token is not None:
            report.sent.append("liveliness token of up, declared and withdrawn")
            token.undeclare()
        for subscriber in subscribers:
            subscriber.undeclare()
    return report


def describe(report: RogueReport) -> str:
    """One line for a test's failure message."""
    return json.dumps({"sent": len(report.sent), "received": report.received})
