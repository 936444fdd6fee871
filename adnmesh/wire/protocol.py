"""The protocol table: one row per message kind on the bus. Everything else is derived from it.

Each row (:class:`MessageKind`) says what a kind of message is: its key below ``adn/<grid>/``,
its struct (:mod:`adnmesh.wire.messages`), who sends it, who receives it, the ICT link that
carries it and the numbers tools plot of it. From the table come the key builders and the key
parser (:mod:`adnmesh.wire.keys`), the JSON Schemas of a recording (:mod:`adnmesh.wire.schemas`),
the run's routes, lookahead and subscriptions (:mod:`adnmesh.sim.topology`), the access control of
the secure profile (:mod:`adnmesh.runtime.acl`), which keys the recorder accepts
(:mod:`adnmesh.runtime.tap`) and the key patterns of the series tools read
(:mod:`adnmesh.results.rules`).

Key templates hold at most one placeholder: ``{der}`` a DER id, ``{agent}`` an agent id
(``cpfc``, ``der/SGen1``, ...; :mod:`adnmesh.names`), ``{party}`` an agent id or ``up``. In
``sender`` and ``receivers`` a name is an agent kind (``der``: every DER's agent, or for a
``{der}`` key the one it names), ``up``, ``operator``, ``*`` (every agent), or the placeholder
itself (the agent the key names).

===================  =========================  ==============  =====================  ===================
kind                 key (``adn/<grid>/``)      sender          receivers              link
===================  =========================  ==============  =====================  ===================
``p_y``              ``cpfc/p_y``               ``cpfc``        every DER              ``cpfc_to_der``
``p_ref``            ``scenario/p_ref``         ``cpfc``        (recorded)             ``local``
``adn_actuator``     ``cpfc/actuator``          ``cpfc``        (recorded)             ``local``
``adn_offset``       ``der/{der}/offset``       the DER (site)  the ADN's ``cpfc``     ``local``
``adn_exchange``     ``measurement/exchange``   ``measurement`` the ADN's site         ``physical``
``q_y``              ``cpfc/q_y``               ``cpfc``        every DER              ``cpfc_to_der``
``q_ref``            ``scenario/q_ref``         ``cpfc``        (recorded)             ``local``
``der_state``        ``der/{der}/state``        the DER         ``measurement``        ``physical``
``heartbeat``        ``der/{der}/heartbeat``    the DER         availability, cpfc     ``der_to_availability``
``p_ip``             ``measurement/p_ip``       ``measurement`` ``cpfc``               ``measurement_to_cpfc``
``grid_state``       ``measurement/grid``       ``measurement`` (recorded)             ``local``
``grid_guard``       ``measurement/guard``      ``measurement`` ``cpfc``               ``measurement_to_cpfc``
``si``               ``availability/si``        availability    ``cpfc``               ``availability_to_cpfc``
``fault``            ``faults``                 ``up``          every agent            (``up``'s own)
``fault_request``    ``control/fault``          ``operator``    ``up``                 (``adnmesh fault``)
``event``            ``event/{party}``          the party       (recorded)             ``local``
``clock_report``     ``clock/report/{agent}``   the agent       ``up``                 (sim clock)
``clock_grant``      ``clock/grant/{agent}``    ``up``          the agent              (sim clock)
``clock_start``      ``clock/start``            ``up``          every agent            (sim clock)
``clock_stop``       ``clock/stop``             ``up``          every agent            (sim clock)
``agent_bye``        ``clock/bye/{agent}``      the agent       ``up``                 (sim clock)
``clock_kill``       ``clock/kill/{agent}``     ``up``          the agent              (a kill noted: die)
===================  =========================  ==============  =====================  ===================

The two ``hierarchy`` kinds cross from one grid to another in a hierarchy of ADNs
(docs/hierarchy.md): ``adn_offset`` is sent in the upper grid by the site agent that stands as
the ADN's DER there, and received by the ADN's CPFC; ``adn_exchange`` is the ADN's exchange with
the level above at each sample, received by its site agent. The table names no receiver of
theirs; the hierarchy's topology (:mod:`adnmesh.sim.hierarchy_topology`) adds them.

**Adding a message kind** is one struct in :mod:`adnmesh.wire.messages` and one row here; an
agent then returns ``Outgoing(keys.of("<kind>"), {...})`` and handles the message in
``on_message``. Links with a ``link`` go through the ICT channel model of the sender's node
(fate, delay) and count for the sim clock; ``clock`` rows are the clock protocol the agent
process speaks itself.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import msgspec.inspect

from adnmesh.names import AGENT_PATTERN, ICT_LINKS, ID_PATTERN, LAUNCHER, OPERATOR
from adnmesh.wire import messages as m

__all__ = [
    "EVERY_AGENT",
    "KINDS",
    "LOCAL_LINKS",
    "MessageKind",
    "PROTOCOL",
    "STRUCTS",
    "SeriesField",
]

EVERY_AGENT = "*"
"""In ``receivers``: every agent of the run."""

LOCAL_LINKS = ("physical", "local")
"""Links without delay that no fault disturbs: ``physical`` (a DER's infeed is physics, not
communication) and ``local`` (records nobody receives)."""

_PLACEHOLDERS = {"der": ID_PATTERN, "agent": AGENT_PATTERN, "party": f"(?:{AGENT_PATTERN}|{LAUNCHER})"}


@dataclass(frozen=True)
class SeriesField:
    """A number tools plot of every message of a kind (``adnmesh replay``, ``plot``, the live
    view).

    Attributes
    ----------
    field : str
        The body field (a number; booleans become 0/1).
    name : str
        The series' name; ``{der}`` is filled in with the key's DER id.
    role : str
        What the series is, for plots and layouts (``p_ref``, ``p_ip``, ``p_y``, ...).
    unit : str
        Its unit (SI; ``"1"`` for dimensionless).
    step : bool
        The value holds until the next sample (drawn as steps).
    """

    field: str
    name: str
    role: str
    unit: str = "W"
    step: bool = False


@dataclass(frozen=True)
class MessageKind:
    """One row of the protocol table (see the module docstring).

    Attributes
    ----------
    name : str
        The kind's name; the message ``type`` is its struct's.
    key : str
        Key template below ``adn/<grid>/``.
    struct : type
        The message's struct (:class:`~adnmesh.wire.messages.Envelope` subclass).
    sender : str
        Who may send it.
    receivers : tuple of str
        Who gets it (empty: it is recorded only).
    link : str or None
        The link from sender to receivers (:data:`adnmesh.names.ICT_LINKS`, :data:`LOCAL_LINKS`); None for
        the messages ``up`` and ``operator`` send and for the clock protocol.
    series : tuple of SeriesField
        What tools plot of it.
    clock : bool
        Part of the sim-clock protocol, spoken by the agent process, not by the agent.
    quiet : bool
        Tools keep none of its numbers as series of their own (clock traffic, heartbeats).
    feature : str or None
        The config section a run needs for this kind to exist at all (``reactive``: the Q
        loop's messages); a run without it neither routes nor allows the kind.
    """

    name: str
    key: str
    struct: type[m.Envelope]
    sender: str
    receivers: tuple[str, ...]
    link: str | None
    series: tuple[SeriesField, ...] = ()
    clock: bool = False
    quiet: bool = False
    feature: str | None = None
    type: str = field(init=False)
    placeholder: str | None = field(init=False)

    def __post_init__(self) -> None:
        (type_field,) = (f for f in msgspec.inspect.type_info(self.struct).fields
                         if f.name == "type")
        object.__setattr__(self, "type", type_field.type.values[0])
        found = re.findall(r"\{(\w+)\}", self.key)
        if len(found) > 1 or (found and found[0] not in _PLACEHOLDERS):
            raise ValueError(f"{self.name}: a key holds at most one of {sorted(_PLACEHOLDERS)}")
        if self.link is not None and self.link not in (*ICT_LINKS, *LOCAL_LINKS):
            raise ValueError(f"{self.name}: unknown link {self.link!r}")
        object.__setattr__(self, "placeholder", found[0] if found else None)

    @property
    def pattern(self) -> str:
        """The key as tools match it: ``adn/{grid}/`` + the template, a ``{der}`` capturing
        one level, ``{agent}`` and ``{party}`` (one or two levels) as ``**``."""
        return "adn/{grid}/" + re.sub(r"\{(agent|party)\}", "**", self.key)

    def regex(self) -> str:
        """The key template below ``adn/<grid>/`` as a regular expression (one named group
        for the placeholder)."""
        parts = re.split(r"\{(\w+)\}", self.key)
        return "".join(re.escape(p) if i % 2 == 0 else f"(?P<{p}>{_PLACEHOLDERS[p]})"
                       for i, p in enumerate(parts))


_S = SeriesField   # short, for the rows below

PROTOCOL: tuple[MessageKind, ...] = (
    MessageKind("p_y", "cpfc/p_y", m.PY, "cpfc", ("der",), "cpfc_to_der", (
        _S("p_y", "P_Y", "p_y", unit="1"),
        _S("kp", "K_P", "kp", unit="1/W", step=True),
        _S("ki", "K_I", "ki", unit="1/(W s)", step=True),
        _S("entry", "table entry", "entry", unit="1", step=True))),
    MessageKind("p_ref", "scenario/p_ref", m.PRef, "cpfc", (), "local", (
        _S("p_ref_w", "P_ref", "p_ref", step=True),
        _S("offset_w", "P_ref offset from above", "p_ref_offset", step=True))),
    MessageKind("adn_actuator", "cpfc/actuator", m.AdnActuator, "cpfc", (), "local", (
        _S("capacity_w", "ADN capacity", "adn_capacity", step=True),)),
    MessageKind("adn_offset", "der/{der}/offset", m.AdnOffset, "der", (), "local", (
        _S("offset_w", "{der} reference offset", "adn_offset", step=True),), feature="hierarchy"),
    MessageKind("adn_exchange", "measurement/exchange", m.PIP, "measurement", (), "physical",
                quiet=True, feature="hierarchy"),
    MessageKind("q_y", "cpfc/q_y", m.QY, "cpfc", ("der",), "cpfc_to_der", (
        _S("q_y", "Q_Y", "q_y", unit="1"),
        _S("kp", "K_P of Q", "q_kp", unit="1/var", step=True),
        _S("ki", "K_I of Q", "q_ki", unit="1/(var s)", step=True),
        _S("entry", "Q table entry", "q_entry", unit="1", step=True)), feature="reactive"),
    MessageKind("q_ref", "scenario/q_ref", m.QRef, "cpfc", (), "local", (
        _S("q_ref_var", "Q_ref", "q_ref", unit="var", step=True),), feature="reactive"),
    MessageKind("der_state", "der/{der}/state", m.DERState, "der", ("measurement",), "physical", (
        _S("p_w", "{der} infeed", "der_infeed"),
        _S("setpoint_w", "{der} setpoint", "der_setpoint", step=True),
        _S("q_var", "{der} reactive infeed", "der_q_infeed", unit="var"),
        _S("q_setpoint_var", "{der} reactive setpoint", "der_q_setpoint", unit="var",
           step=True))),
    MessageKind("heartbeat", "der/{der}/heartbeat", m.Heartbeat, "der", ("availability", "cpfc"),
                "der_to_availability", quiet=True),
    MessageKind("p_ip", "measurement/p_ip", m.PIP, "measurement", ("cpfc",),
                "measurement_to_cpfc", (_S("p_ip_w", "P_IP", "p_ip"),
                                        _S("q_ip_var", "Q_IP", "q_ip", unit="var"))),
    MessageKind("grid_state", "measurement/grid", m.GridState, "measurement", (), "local", (
        _S("v_min_pu", "lowest bus voltage", "grid_v_min", unit="p.u.", step=True),
        _S("v_max_pu", "highest bus voltage", "grid_v_max", unit="p.u.", step=True),
        _S("line_loading_max_pct", "highest line loading", "grid_line_loading", unit="%",
          step=True),
        _S("trafo_loading_max_pct", "highest transformer loading", "grid_trafo_loading",
          unit="%", step=True),
        _S("q_ip_var", "Q_IP at the report", "grid_q_ip", unit="var", step=True),
        _S("tap_pos", "tap position", "tap_pos", unit="1", step=True))),
    MessageKind("grid_guard", "measurement/guard", m.GridGuard, "measurement", ("cpfc",),
                "measurement_to_cpfc", (_S("hold", "guard holds the control", "guard_hold",
                                           unit="1", step=True),), feature="guard"),
    MessageKind("si", "availability/si", m.SI, "availability", ("cpfc",), "availability_to_cpfc"),
    MessageKind("fault", "faults", m.Fault, LAUNCHER, (EVERY_AGENT,), None),
    MessageKind("fault_request", "control/fault", m.FaultRequest, OPERATOR, (LAUNCHER,), None),
    MessageKind("event", "event/{party}", m.Event, "{party}", (), "local"),
    MessageKind("clock_report", "clock/report/{agent}", m.ClockReport, "{agent}", (LAUNCHER,),
                None, clock=True, quiet=True),
    MessageKind("clock_grant", "clock/grant/{agent}", m.ClockGrant, LAUNCHER, ("{agent}",), None,
                clock=True, quiet=True),
    MessageKind("clock_start", "clock/start", m.ClockStart, LAUNCHER, (EVERY_AGENT,), None,
                clock=True, quiet=True),
    MessageKind("clock_stop", "clock/stop", m.ClockStop, LAUNCHER, (EVERY_AGENT,), None,
                clock=True, quiet=True),
    MessageKind("agent_bye", "clock/bye/{agent}", m.AgentBye, "{agent}", (LAUNCHER,), None,
                clock=True, quiet=True),
    MessageKind("clock_kill", "clock/kill/{agent}", m.ClockStop, LAUNCHER, ("{agent}",), None,
                clock=True, quiet=True),
)
"""The message kinds, in the order of the module docstring's table."""

KINDS: dict[str, MessageKind] = {kind.name: kind for kind in PROTOCOL}
"""Kind name -> its row."""

STRUCTS: dict[str, type[m.Envelope]] = {kind.type: kind.struct for kind in PROTOCOL}
"""Message type -> its struct (two kinds may share one: ``clock_kill`` is a ``clock_stop``)."""
