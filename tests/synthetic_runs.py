"""A small, deterministic fake run, for tests and demonstrations of the recording tools.

Four DERs (two wind turbines, a CHP plant, a PV plant) under a PI controller with scheduled
gains, simulated in 0.1 s steps: P_ref steps up and down, the wind turbines become unavailable
(and the controller switches gains without a bump), the CHP plant goes offline for 2 s (its
watchdog falls back to the schedule). The messages have the shapes of the runtime's
(:mod:`adnmesh.wire.messages`: an envelope ``v, type, src, seq, t_send_ns, t_deliver_ns``
plus a flat body) on the same keys, but their own JSON Schemas (:data:`FAKE_SCHEMAS`), so tests
of the recording tools do not depend on the runtime. Nothing here is used by a real run.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from adnmesh.recording.writer import PUBLISHED_METADATA, Recorder

__all__ = ["FAKE_DERS", "FAKE_SCHEMAS", "FakeMessage", "fake_run", "write_fake_run"]

GRID = "fake"
FAKE_DERS = {  # id: (P_inst W, PT1 time constant s, P_sched W)
    "WT1": (2.0e6, 0.25, 1.2e6),
    "WT2": (2.0e6, 0.25, 1.2e6),
    "CHP1": (0.35e6, 4.0, 0.2e6),
    "PV1": (0.2e6, 0.05, 0.1e6),
}
"""The fake run's DERs: id -> (installed power W, time constant s, schedule W)."""

_NUMBER = {"type": "number"}
_GAIN = {"type": "number", "exclusiveMinimum": 0}


def _schema(name: str, body: dict[str, dict], required: tuple[str, ...]) -> dict:
    envelope = {"v": {"const": 1}, "type": {"const": name}, "src": {"type": "string"},
                "seq": {"type": "integer", "minimum": 0},
                "t_send_ns": {"type": "integer", "minimum": 0},
                "t_deliver_ns": {"type": "integer", "minimum": 0}}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": name,
            "type": "object", "properties": {**envelope, **body},
            "required": [*envelope, *required], "additionalProperties": False}


FAKE_SCHEMAS: dict[str, dict] = {
    "p_ref": _schema("p_ref", {"p_ref_w": _NUMBER}, ("p_ref_w",)),
    "p_ip": _schema("p_ip", {"p_ip_w": _NUMBER}, ("p_ip_w",)),
    "p_y": _schema("p_y", {
        "p_y": _NUMBER, "p_ref_w": _NUMBER, "kp": _GAIN, "ki": _GAIN,
        "entry": {"type": "integer", "minimum": 0},
        "w": {"type": "object", "additionalProperties": {"type": "number", "minimum": 0,
                                                         "maximum": 1}},
        "switch": {"type": "object", "properties": {
            "p_y_before": _NUMBER, "kp_before": _GAIN, "ki_before": _GAIN},
            "required": ["p_y_before", "kp_before", "ki_before"], "additionalProperties": False},
    }, ("p_y", "p_ref_w", "kp", "ki", "entry")),
    "der_state": _schema("der_state", {
        "p_w": _NUMBER, "setpoint_w": _NUMBER,
        "mode": {"enum": ["control", "schedule", "watchdog"]}}, ("p_w", "setpoint_w", "mode")),
    "heartbeat": _schema("heartbeat", {"available": {"type": "boolean"}}, ("available",)),
    "si": _schema("si", {"si": {"type": "object", "additionalProperties": {"type": "boolean"},
                                "minProperties": 1}}, ("si",)),
    "fault": _schema("fault", {"fault_id": {"type": "integer"}, "kind": {"type": "string"},
                               "der": {"type": "string"}, "start_ns": {"type": "integer"},
                               "end_ns": {"type": ["integer", "null"]}},
                     ("fault_id", "kind", "start_ns", "end_ns")),
}
"""JSON Schemas (draft 2020-12) of the fake run's message types."""


@dataclass(frozen=True)
class FakeMessage:
    """One message of the fake run: key, type, JSON payload, send and delivery time (ns)."""

    topic: str
    schema_name: str
    payload: bytes
    t_send_ns: int
    t_deliver_ns: int


_ENTRIES = {("WT1", "WT2", "CHP1", "PV1"): 15, ("CHP1", "PV1"): 12}  # table entry numbers


def _gains(active: tuple[str, ...]) -> tuple[float, float]:
    """PI gains (1/W, 1/(W s)) for the available DERs: fast with the WTs, slow without."""
    k = sum(FAKE_DERS[d][0] for d in active)
    return (0.3 / k, 1.5 / k) if any(d.startswith("WT") for d in active) else (0.35 / k, 0.4 / k)


def fake_run(duration_s: float = 60.0) -> Iterator[FakeMessage]:
    """Yield the messages of the fake run in send order.

    Events: P_ref +1 MW at 5 s, -1 MW at 15 s; WT1 and WT2 unavailable at 25 s (gain switch);
    +0.2 MW at 30 s, -0.2 MW at 50 s; CHP1 offline from 40 s to 42 s (a fault; its watchdog
    takes it to its schedule from 41 s until it is back).
    """
    dt_ns, delay_ns, short_ns = 100_000_000, 100_000_000, 10_000_000
    ids = tuple(FAKE_DERS)
    seq: Counter[tuple[str, str]] = Counter()

    def msg(topic: str, msg_type: str, src: str, t_ns: int, lag_ns: int, **body) -> FakeMessage:
        envelope = {"v": 1, "type": msg_type, "src": src, "seq": seq[src, topic],
                    "t_send_ns": t_ns, "t_deliver_ns": t_ns + lag_ns}
        seq[src, topic] += 1
        data = json.dumps({**envelope, **body}, separators=(",", ":")).encode()
        return FakeMessage(topic, msg_type, data, t_ns, t_ns + lag_ns)

    p_load = -1.0e6
    infeed = {d: FAKE_DERS[d][2] for d in ids}
    p_ref = p_load + sum(infeed.values())
    active = ids
    kp, ki = _gains(active)
    x_i = 0.0
    p_y = 0.0
    last_p_ip = p_ref
    p_y_heard = {d: 0.0 for d in ids}  # the last P_Y each DER received
    steps = {50: 1.0e6, 150: -1.0e6, 300: 0.2e6, 500: -0.2e6}
    for k in range(int(round(duration_s * 10)) + 1):
        t = k * dt_ns
        if k in steps or k == 0:
            p_ref += steps.get(k, 0.0)
            yield msg(f"adn/{GRID}/scenario/p_ref", "p_ref", "cpfc", t, short_ns, p_ref_w=p_ref)
        if k == 250:
            active = ("CHP1", "PV1")
        if k % 10 == 0 or k == 250:
            yield msg(f"adn/{GRID}/availability/si", "si", "availability", t, short_ns,
                      si={d: d in active for d in ids})
        if k == 400:
            yield msg(f"adn/{GRID}/faults", "fault", "up", t, 0, fault_id=1,
                      kind="der_offline", der="CHP1", start_ns=t, end_ns=t + 2_000_000_000)
        # measurement of P_IP (sampled now, arrives one delay later), PI on the last arrival
        p_ip = p_load + sum(infeed.values())
        yield msg(f"adn/{GRID}/measurement/p_ip", "p_ip", "measurement", t, delay_ns, p_ip_w=p_ip)
        new_kp, new_ki = _gains(active)
        error = p_ref - last_p_ip
        switch = None
        if (new_kp, new_ki) != (kp, ki):  # bumpless: P_Y stays where it was
            switch = {"p_y_before": p_y, "kp_before": kp, "ki_before": ki}
            x_i = (p_y - new_kp * error) / new_ki
            kp, ki = new_kp, new_ki
        x_i += error * dt_ns / 1e9
        p_y = kp * error + ki * x_i
        last_p_ip = p_ip
        extra = {} if switch is None else {"w": dict.fromkeys(active, 1.0), "switch": switch}
        yield msg(f"adn/{GRID}/cpfc/p_y", "p_y", "cpfc", t, delay_ns, p_y=p_y, p_ref_w=p_ref,
                  kp=kp, ki=ki, entry=_ENTRIES[active], **extra)
        for d in ids:
            p_inst, tau_s, p_sched = FAKE_DERS[d]
            offline = d == "CHP1" and 400 <= k < 420
            if not offline:
                p_y_heard[d] = p_y
            if d not in active:
                mode, setpoint = "schedule", p_sched
            elif offline and k >= 410:  # the watchdog (1 s) takes it to its schedule
                mode, setpoint = "watchdog", p_sched
            else:
                mode, setpoint = "control", min(max(p_sched + p_y_heard[d] * p_inst, 0.0), p_inst)
            infeed[d] += (setpoint - infeed[d]) * (1.0 - math.exp(-0.1 / tau_s))
            yield msg(f"adn/{GRID}/der/{d}/state", "der_state", f"der/{d}", t, short_ns,
                      p_w=infeed[d], setpoint_w=setpoint, mode=mode)
            if k % 10 == 0:
                yield msg(f"adn/{GRID}/der/{d}/heartbeat", "heartbeat", f"der/{d}", t, short_ns,
                          available=d in active)


def write_fake_run(path: str | Path, *, duration_s: float = 60.0, flush_interval_s: float = 1.0,
                   metadata: dict[str, str] | None = None) -> dict[str, int]:
    """Record :func:`fake_run` to ``path``; return the published count per topic.

    Like a real run, the recording ends with the publishers' counts (``adnmesh.published``).
    """
    published: Counter[str] = Counter()
    run = {"run_id": "fake", "clock": "sim", "seed": "0", "config_sha256": "0" * 64,
           "table_sha256": "1" * 64, "config": f"grid: {GRID}\n", **(metadata or {})}
    with Recorder(path, metadata=run, schemas=FAKE_SCHEMAS,
                  flush_interval_s=flush_interval_s) as recorder:
        for m in fake_run(duration_s):
            recorder.write(m.topic, m.schema_name, m.payload, log_time_ns=m.t_deliver_ns,
                           publish_time_ns=m.t_send_ns)
            published[m.topic] += 1
        recorder.add_metadata(PUBLISHED_METADATA, {t: str(n) for t, n in published.items()})
    return dict(published)
