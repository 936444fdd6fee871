"""The message types on the bus: one msgspec struct each, envelope fields first.

Every payload is one flat JSON object, the **envelope** (version ``v`` = 1) followed by the
body of its type::

    {"v": 1, "type": "p_ip", "src": "measurement", "seq": 41,
     "t_send_ns": 4100000000, "t_deliver_ns": 4200000000, "p_ip_w": 1000012.5}

``type`` is fixed by the key (the protocol table, :mod:`adnmesh.wire.protocol`), ``src`` is the sending agent,
``seq`` counts one sender's messages on one key from 0, and the two times are ns of sim time
(:mod:`adnmesh.wire.units`): when the sender sent it and when the ICT channel model delivers it.

The structs are the single description of the format: decoding with them validates every field
(:mod:`adnmesh.wire.envelope`) and the JSON Schemas published with recordings are generated from
them (:mod:`adnmesh.wire.schemas`), so code, validation and schemas cannot drift apart. Every
number is bounded (finite, in a physical range, integers that fit the recorder's 64-bit
fields), every string and mapping has a length limit, and unknown fields are refused.
"""

from __future__ import annotations

from typing import Annotated, Literal

from msgspec import UNSET, Meta, Struct, UnsetType

from adnmesh.names import (AGENT_PATTERN, FAULT_KINDS, ICT_LINKS, ID_MAX_CHARS, ID_PATTERN,
                           LAUNCHER, OPERATOR)
from adnmesh.wire.units import NS_MAX

__all__ = [
    "MESSAGE_VERSION",
    "ActuatorGroup",
    "AdnActuator",
    "AdnOffset",
    "AgentBye",
    "ClockGrant",
    "ClockReport",
    "ClockStart",
    "ClockStop",
    "DERState",
    "Design",
    "Envelope",
    "Fault",
    "FaultRequest",
    "GridGuard",
    "GridState",
    "Event",
    "Heartbeat",
    "PIP",
    "PRef",
    "PY",
    "QRef",
    "QY",
    "SI",
    "Switch",
]

MESSAGE_VERSION = 1
"""Version ``v`` of the envelope and of every body defined here."""

MAX_DERS = 1000
"""Most DERs a mapping in a message (weights, SI) may name."""

CUT_KEYS_MAX = 4 * MAX_DERS
"""Most keys a clock grant may cut (the keys of every quarantined DER a receiver takes)."""

NS = Annotated[int, Meta(ge=0, le=NS_MAX, description="ns of sim time")]
Count = Annotated[int, Meta(ge=0, le=NS_MAX)]
Power = Annotated[float, Meta(ge=-1e15, le=1e15, description="W")]
Ratio = Annotated[float, Meta(ge=-1e9, le=1e9, description="dimensionless")]
Gain = Annotated[float, Meta(gt=0.0, le=1e3)]
Weight = Annotated[float, Meta(ge=0.0, le=1.0)]
DERId = Annotated[str, Meta(pattern=f"^{ID_PATTERN}$", max_length=ID_MAX_CHARS)]
RunDER = Annotated[str, Meta(max_length=ID_MAX_CHARS,
                             extra_json_schema={"pattern": f"^{ID_PATTERN}$"})]
"""A DER id in a mapping or list that every receiver's gate checks against the run's own DERs
(:func:`adnmesh.wire.gate.names_known_ders`, reason ``unknown_der``): a stronger rule than the
pattern, which the schema states and decoding leaves to the gate. The CPFC's weights name every
DER of the run about once a second, and every DER decodes them: matching 1,000 ids against the
pattern cost 0.65 ms of the 0.76 ms each decode took (msgspec 0.23, measured here)."""
GridName = DERId                 # a grid's name follows the same rule
Sender = Annotated[str, Meta(max_length=2 * ID_MAX_CHARS,
                             extra_json_schema={"pattern": f"^({LAUNCHER}|{OPERATOR}|{AGENT_PATTERN})$"})]
Agent = Annotated[str, Meta(pattern=f"^{AGENT_PATTERN}$", max_length=2 * ID_MAX_CHARS)]
Key = Annotated[str, Meta(max_length=256)]
Text = Annotated[str, Meta(max_length=500)]
Stat = Annotated[float, Meta(ge=-1e300, le=1e300)]


class Envelope(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """Fields every payload carries before its body."""

    v: Literal[1]
    type: str
    src: Sender
    seq: Count
    t_send_ns: NS
    t_deliver_ns: NS


class Switch(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """A bumpless gain switch: the output with the old gains, scaled (``scale``: so that the
    DERs' total commanded power stays continuous) and limited to the new range; ``handover_s``
    (absent: 0) how long the DERs take to move from the setpoints they have to their shares
    of the new entry (docs/method.md#returning-ders-handover), s; ``direction`` on a switch
    made because the DERs move the other way now, the direction the new entry's DERs can move
    in (absent: a switch for a change of availability or a tuned entry;
    docs/method.md#directional-availability); ``keep`` the DERs the grid guard leaves out
    that keep the power they were commanded instead of returning to their schedules
    (docs/method.md#grid-guard)."""

    p_y_before: Ratio
    p_y_limited: Ratio
    kp_before: Gain
    ki_before: Gain
    scale: Annotated[float, Meta(ge=0.0, le=1e9)] = 1.0
    handover_s: Annotated[float, Meta(gt=0.0, le=1e6)] | UnsetType = UNSET
    direction: Literal["up", "down"] | UnsetType = UNSET
    keep: Annotated[list[RunDER], Meta(max_length=MAX_DERS)] | UnsetType = UNSET


Seconds = Annotated[float, Meta(ge=0.0, le=1e9, description="s")]


class Design(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """What a table entry was certified for (docs/method.md#said-when-over): the step
    response of its as-deployed loop (reference model, weights applied) in the table, 10-90 %
    rise time and settling time in ``settling_band_pct`` % (s), overshoot (%), and the
    overshoot limit it was certified against (``constraints.overshoot_max_pct``, %)."""

    rise_time_s: Seconds
    settling_time_s: Seconds
    overshoot_pct: Annotated[float, Meta(ge=0.0, le=1e6, description="%")]
    overshoot_max_pct: Annotated[float, Meta(gt=0.0, le=1e6, description="%")]
    settling_band_pct: Annotated[float, Meta(gt=0.0, le=100.0, description="%")]


class _Output(Envelope, kw_only=True):
    """What P_Y and Q_Y carry besides the value and its reference: the gains in use, the
    number of the table entry, and on occasion the weights, a switch record, a hold and the
    design figures (:class:`PY`). Keyword-only, so that each output's own fields come first in
    the payload, right after the envelope."""

    kp: Gain
    ki: Gain
    entry: Count
    w: Annotated[dict[RunDER, Weight], Meta(max_length=MAX_DERS)] | UnsetType = UNSET
    switch: Switch | UnsetType = UNSET
    hold: Literal["measurement", "actuators", "resuming", "grid"] | UnsetType = UNSET
    design: Design | UnsetType = UNSET


class PY(_Output):
    """CPFC output P_Y (dimensionless) with the gains in use (K_P 1/W, K_I 1/(W s)) and the
    number of the table entry; the entry's weights W on a switch and periodically; ``hold``
    while output and integrator are held (no measurement, no actuator, resuming); ``design``
    with the first P_Y of an entry that has certified figures (the table's or an on-demand
    tuned entry, not the static controller)."""

    type: Literal["p_y"]
    p_y: Ratio
    p_ref_w: Power


class QY(_Output):
    """CPFC output Q_Y of the reactive power loop (docs/method.md#reactive-power): the fields
    of :class:`PY` for Q (gains in 1/var and 1/(var s), ``q_ref_var`` in var, weights and the
    entry of the Q table)."""

    type: Literal["q_y"]
    q_y: Ratio
    q_ref_var: Power


class ActuatorGroup(Struct, forbid_unknown_fields=True):
    """One group of identical dynamics in an ADN's entry (reference model, docs/method.md):
    dead time ``t_delay_s`` (s), time constant ``t_lag_s`` of its ``model`` (s), and its gain
    ``gain_w`` = the sum of its DERs' ``w_d P_inst,d`` (W)."""

    t_delay_s: Seconds
    t_lag_s: Annotated[float, Meta(gt=0.0, le=1e9, description="s")]
    model: Literal["pt1", "pt2", "rhpz"]
    gain_w: Annotated[float, Meta(ge=0.0, le=1e15, description="W")]


class AdnActuator(Envelope):
    """The ADN as an actuator of the level above (docs/hierarchy.md), sent by its CPFC with
    the first output of every entry and when its gains go on to other DERs (no entry for the
    set left): the entry's number and DERs in use, the installed power
    of those DERs (``capacity_w``, the ADN's C_i, W), its range above and below their
    schedules (W), and the entry's exact closed loop: PI gains (1/W, 1/(W s)), the loop's
    design T_com and T_meas (s) and its groups; ``grid``: the ADN's grid (its id in a
    hierarchy)."""

    type: Literal["adn_actuator"]
    entry: Count
    ders: Annotated[list[DERId], Meta(max_length=MAX_DERS)]
    capacity_w: Annotated[float, Meta(ge=0.0, le=1e15, description="W")]
    range_up_w: Annotated[float, Meta(ge=0.0, le=1e15, description="W")]
    range_down_w: Annotated[float, Meta(ge=0.0, le=1e15, description="W")]
    kp: Gain
    ki: Gain
    t_com_s: Seconds
    t_meas_s: Seconds
    groups: Annotated[list[ActuatorGroup], Meta(max_length=MAX_DERS)]
    grid: GridName | UnsetType = UNSET


class AdnOffset(Envelope):
    """The level above's share for one ADN, sent by the ADN's site agent to the ADN's CPFC: the
    offset of its reference P_ref from its own schedule, W (docs/hierarchy.md)."""

    type: Literal["adn_offset"]
    offset_w: Power


class PRef(Envelope):
    """Reference P_ref at the interconnection point, W; of an ADN below a level (a hierarchy),
    also the part of it that is the level above's offset, W (its steps are the changes of the
    rest: docs/hierarchy.md)."""

    type: Literal["p_ref"]
    p_ref_w: Power
    offset_w: Power | UnsetType = UNSET


class QRef(Envelope):
    """Reference Q_ref at the interconnection point, var."""

    type: Literal["q_ref"]
    q_ref_var: Power


class DERState(Envelope):
    """A DER's infeed and setpoint at a sampling instant, W, and where its setpoint comes from;
    while it follows P_Y (``control``, a weight > 0), whether a limit holds its output back:
    +1 from rising, -1 from falling, 0 free (absent while it does not follow). With reactive
    power control its reactive infeed and setpoint, var, and ``q_held`` as ``held`` for Q_Y
    (its P-Q capability)."""

    type: Literal["der_state"]
    p_w: Power
    setpoint_w: Power
    mode: Literal["control", "schedule", "watchdog"]
    held: Literal[-1, 0, 1] | UnsetType = UNSET
    q_var: Power | UnsetType = UNSET
    q_setpoint_var: Power | UnsetType = UNSET
    q_held: Literal[-1, 0, 1] | UnsetType = UNSET


class Heartbeat(Envelope):
    """A DER's heartbeat: its availability flag, where its setpoint comes from (``mode``) and
    the last P_Y it applied with the number of the CPFC's table entry of that command (its
    acknowledgement of the CPFC's commands); with reactive power control the last Q_Y too."""

    type: Literal["heartbeat"]
    available: bool
    mode: Literal["control", "schedule", "watchdog"] = "control"
    p_y: Ratio = 0.0
    entry: Count | None = None
    q_y: Ratio | UnsetType = UNSET


class PIP(Envelope):
    """Measured active power at the interconnection point, W (MV -> HV positive), with the grid
    model (or reactive power control) its reactive power, var; ``held`` when every DER that
    follows P_Y is held back by a limit in that direction (the CPFC's anti-windup), ``q_held``
    the same for Q_Y."""

    type: Literal["p_ip"]
    p_ip_w: Power
    q_ip_var: Power | UnsetType = UNSET
    held: Literal["up", "down"] | UnsetType = UNSET
    q_held: Literal["up", "down"] | UnsetType = UNSET


PerUnit = Annotated[float, Meta(ge=0.0, le=10.0, description="p.u.")]
Element = Annotated[str, Meta(max_length=200, description="a bus, line or transformer")]
Percent = Annotated[float, Meta(ge=0.0, le=1e6, description="%")]


class GridState(Envelope):
    """The grid over the last report period (the measurement's power flows): the lowest and
    highest bus voltage, the highest line and transformer loading, the samples outside the
    config's band and those whose power flow did not converge, and Q_IP at the period's end."""

    type: Literal["grid_state"]
    v_min_pu: PerUnit
    v_max_pu: PerUnit
    line_loading_max_pct: Percent
    trafo_loading_max_pct: Percent
    q_ip_var: Power
    samples: Count
    outside_band: Count
    not_converged: Count
    outside_s: Annotated[float, Meta(ge=0.0, le=1e9, description="s")] | UnsetType = UNSET
    v_min_at: Element | UnsetType = UNSET
    v_max_at: Element | UnsetType = UNSET
    line_max_at: Element | UnsetType = UNSET
    trafo_max_at: Element | UnsetType = UNSET
    tap_pos: Annotated[int, Meta(ge=-1000, le=1000)] | UnsetType = UNSET


DERList = Annotated[list[RunDER], Meta(max_length=MAX_DERS)]


class GridGuard(Envelope):
    """The grid guard's state (docs/method.md#grid-guard), sent when it changes and with every
    grid report: the DERs blocked from raising (``p_up``) or lowering (``p_down``) their active
    power and likewise their reactive power (``q_up``, ``q_down``), because that would worsen a
    voltage or loading at or near its limit; ``hold`` (guard mode ``block``): a limit is
    violated and the whole control holds."""

    type: Literal["grid_guard"]
    p_up: DERList = []
    p_down: DERList = []
    q_up: DERList = []
    q_down: DERList = []
    hold: bool = False


class SI(Envelope):
    """The availability vector SI: one boolean per DER."""

    type: Literal["si"]
    si: Annotated[dict[RunDER, bool], Meta(min_length=1, max_length=MAX_DERS)]



class Fault(Envelope):
    """A fault ``up`` injects, sent to every agent (and recorded), delivered at its start.

    ``kind``: ``link_outage`` (every message sent on ``link`` in the window is lost),
    ``link_loss`` (lost with ``probability``), ``link_delay`` (``delay_ns`` more delay),
    ``der_offline`` (DER ``der`` neither receives nor sends over ICT), ``ict_outage`` (every ICT
    link out), ``kill`` (``agent`` is SIGKILLed at ``start_ns``; restarted at ``end_ns`` if set).
    The window is ``[start_ns, end_ns)``; ``fault_id`` numbers the faults of a run from 1.
    ``origin``: the config, a command (``adnmesh fault``), or ``up`` itself quarantining an
    agent whose identity someone else sends with (a kill; every receiver cuts it off).
    """

    type: Literal["fault"]
    fault_id: Annotated[int, Meta(ge=1, le=NS_MAX)]
    kind: Literal[FAULT_KINDS]
    start_ns: NS
    end_ns: NS | None
    link: Literal[ICT_LINKS] | UnsetType = UNSET
    der: DERId | UnsetType = UNSET
    agent: Agent | UnsetType = UNSET
    probability: Annotated[float, Meta(ge=0.0, le=1.0)] | UnsetType = UNSET
    delay_ns: Annotated[int, Meta(ge=0, le=3_600 * 10**9)] | UnsetType = UNSET
    origin: Literal["config", "command", "quarantine"] = "config"


class FaultRequest(Envelope):
    """A request (``adnmesh fault``) to inject a fault into a running ``up``: the fields of
    :class:`Fault` but no number; ``at_ns`` None means as soon as possible, ``for_ns`` None a
    fault without end (a kill without restart). Targets are any short strings here, so that
    ``up`` can answer an unknown one with a reason."""

    type: Literal["fault_request"]
    request_id: Annotated[str, Meta(max_length=64)]
    kind: Literal[FAULT_KINDS]
    at_ns: NS | None
    for_ns: NS | None
    link: Annotated[str, Meta(max_length=128)] | UnsetType = UNSET
    der: Annotated[str, Meta(max_length=128)] | UnsetType = UNSET
    agent: Annotated[str, Meta(max_length=128)] | UnsetType = UNSET
    probability: Annotated[float, Meta(ge=0.0, le=1.0)] | UnsetType = UNSET
    delay_ns: Annotated[int, Meta(ge=0, le=3_600 * 10**9)] | UnsetType = UNSET


class Event(Envelope):
    """Something an agent or ``up`` noticed or did: a fault injected, detected or over, a
    fallback, a hold, an agent lost or back (``kind``), said in one line (``text``)."""

    type: Literal["event"]
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"]
    kind: Annotated[str, Meta(pattern="^[a-z_]+$", max_length=64)]
    text: Text
    subject: Annotated[str, Meta(max_length=2 * ID_MAX_CHARS)] | UnsetType = UNSET
    fault_id: Annotated[int, Meta(ge=1, le=NS_MAX)] | UnsetType = UNSET
    request_id: Annotated[str, Meta(max_length=64)] | UnsetType = UNSET


class ClockReport(Envelope):
    """Sim clock: an agent's next event, how far it was granted, what it received so far and,
    per key, how many messages it sent in the window and the earliest delivery among them;
    ``killed_ns`` when an injected kill ends it there; ``cuts``: the quarantines its count
    leaves out (:class:`ClockGrant`)."""

    type: Literal["clock_report"]
    next_ns: NS | None
    granted_ns: NS
    received: Count
    sent: Annotated[dict[Key, tuple[Annotated[int, Meta(ge=1, le=NS_MAX)], NS]],
                    Meta(max_length=64)]
    killed_ns: NS | UnsetType = UNSET
    cuts: Count = 0


class ClockGrant(Envelope):
    """Sim clock: process every event before ``until_ns`` once ``expect`` messages arrived,
    not counting those on ``cut_keys`` (quarantined senders' keys; ``cuts``: the quarantines
    so far, :mod:`adnmesh.sim.clock`)."""

    type: Literal["clock_grant"]
    until_ns: NS
    expect: Count
    cut_keys: Annotated[tuple[Key, ...], Meta(max_length=CUT_KEYS_MAX)] = ()
    cuts: Count = 0


class ClockStart(Envelope):
    """The run starts (realtime: sim time = (wall - epoch_ns) * speed, and an event processed
    more than ``tolerance_ns`` of sim time late is an overrun) with this ICT seed."""

    type: Literal["clock_start"]
    clock: Literal["sim", "realtime"]
    epoch_ns: NS
    speed: Annotated[float, Meta(gt=0.0, le=1e6)]
    end_ns: NS
    seed: Count
    tolerance_ns: NS = 0


class ClockStop(Envelope):
    """The run ends; agents say goodbye and exit."""

    type: Literal["clock_stop"]
    reason: Text


class AgentBye(Envelope):
    """An agent's final counts: messages published per key, rejected per key and reason, lost
    on its links, its statistics and (realtime) its delivery errors per link: ``[max ns, counts
    per bin]`` (:mod:`adnmesh.sim.latency`)."""

    type: Literal["agent_bye"]
    published: Annotated[dict[Key, Count], Meta(max_length=4096)]
    rejected: Annotated[dict[Key, Annotated[dict[Text, Count], Meta(max_length=64)]],
                        Meta(max_length=4096)]
    lost: Count
    stats: Annotated[dict[Annotated[str, Meta(max_length=64)], Stat], Meta(max_length=256)]
    latency: Annotated[dict[Annotated[str, Meta(max_length=64)],
                            Annotated[list[Count], Meta(max_length=128)]],
                       Meta(max_length=64)] | UnsetType = UNSET
