"""Test helper: bus payloads of any message type from a key and a body."""

from __future__ import annotations

from adnmesh.wire.envelope import decode, encode
from adnmesh.wire.keys import route
from adnmesh.wire.messages import MESSAGE_VERSION
from adnmesh.wire.protocol import STRUCTS


def payload(key: str, body: dict, *, src: str | None = None, seq: int = 0, t_send_ns: int = 0,
            t_deliver_ns: int | None = None) -> bytes:
    """The payload of a message on ``key`` (sender: the key's own unless given)."""
    found = route(key)
    cls = STRUCTS[found.type]
    t_deliver = t_send_ns if t_deliver_ns is None else t_deliver_ns
    return encode(cls(MESSAGE_VERSION, found.type, src or found.sender, seq, t_send_ns,
                      t_deliver, **body))


def message(key: str, t_ns: int, body: dict, *, src: str | None = None, seq: int = 0):
    """A decoded message as the runtime would deliver it."""
    return decode(key, payload(key, body, src=src, seq=seq, t_send_ns=t_ns))


BODIES = {
    "p_y": {"p_y": 0.25, "p_ref_w": 1e6, "kp": 5e-8, "ki": 2e-7, "entry": 1},
    "p_ref": {"p_ref_w": -2.5e6},
    "adn_actuator": {"entry": 0, "ders": ["SGen1"], "capacity_w": 2e6, "range_up_w": 2e6,
                     "range_down_w": 0.0, "kp": 1e-7, "ki": 3e-7, "t_com_s": 0.15,
                     "t_meas_s": 0.1, "groups": [{"t_delay_s": 0.01, "t_lag_s": 0.234,
                                                  "model": "pt1", "gain_w": 2e6}]},
    "adn_offset": {"offset_w": 2.5e5},
    "q_y": {"q_y": -0.25, "q_ref_var": 1e5, "kp": 5e-8, "ki": 2e-7, "entry": 1},
    "q_ref": {"q_ref_var": 2.5e5},
    "der_state": {"p_w": 1e5, "setpoint_w": 2e5, "mode": "control"},
    "heartbeat": {"available": True, "mode": "control", "p_y": 0.1, "entry": 0},
    "p_ip": {"p_ip_w": 3.5e6},
    "grid_state": {"v_min_pu": 0.98, "v_max_pu": 1.03, "line_loading_max_pct": 41.5,
                   "trafo_loading_max_pct": 30.0, "q_ip_var": 3.5e5, "samples": 100,
                   "outside_band": 0, "not_converged": 0},
    "grid_guard": {"p_up": ["SGen1"], "hold": False},
    "si": {"si": {"SGen1": True}},
    "fault": {"fault_id": 1, "kind": "ict_outage", "start_ns": 10, "end_ns": 20},
    "fault_request": {"request_id": "r", "kind": "ict_outage", "at_ns": None, "for_ns": None},
    "event": {"level": "INFO", "kind": "test", "text": "x"},
    "clock_report": {"next_ns": None, "granted_ns": 0, "received": 0, "sent": {}},
    "clock_grant": {"until_ns": 10, "expect": 0},
    "clock_start": {"clock": "sim", "epoch_ns": 0, "speed": 1.0, "end_ns": 9, "seed": 3},
    "clock_stop": {"reason": "test"},
    "agent_bye": {"published": {}, "rejected": {}, "lost": 0, "stats": {}},
}
"""A valid body of every message type."""
