"""The site agent: an ADN as one actuator of the level above (docs/hierarchy.md), bus-free.

In a hierarchy of ADNs the upper grid's config has one DER per ADN (``adnmesh cascade``
writes it: a ``GEN`` with the ADN's equivalent model). At the ADN's site that DER is this agent
(agent id ``der/<adn>`` of the upper grid). It runs the ordinary DER controller
(:class:`~adnmesh.control.der_controller.DERController`: the upper ``P_Y`` with its entry's
weights, switches, handovers, heartbeats and watchdog) on a plant device that is the ADN itself
(:class:`AdnPlant`):

- **set-point → reference offset.** The DER's set-point ``P_set`` (W) asks the ADN for the
  offset ``P_set − P_sched`` of its reference from its own schedule. The agent sends it to the
  ADN's CPFC on ``der/<adn>/offset`` (``adn_offset``) when it changes, and again every
  ``heartbeat_period_s`` (so that a restarted CPFC hears it).
- **exchange → infeed.** The ADN's measurement sends each sample's ``P_IP`` at once on
  ``measurement/exchange`` (``adn_exchange``, the ``physical`` path). The DER's infeed is
  ``P_sched + P_IP − P_IP,0`` (``P_IP,0``: the ADN's operating point), limited to
  ``[0, P_inst]``: the upper DER's range is the ADN's (``adnmesh cascade`` sets ``P_sched`` to
  the ADN's room below its schedule and ``P_inst`` to its installed power).
- **limits.** The exchange says when every DER that follows the ADN's P_Y is held at a
  limit (``held``, as the ADN's own P_IP says it to its CPFC); the DER's state says so to the
  upper measurement, whose P_IP stops the upper integrator that way (the anti-windup).
- **health.** An ADN whose exchange has not arrived for ``watchdog_timeout_s`` is a stale
  device: unavailable to the level above until it reports again.

**The site cut off from the level above** (its link, router or the upper CPFC lost): the DER
controller's watchdog expires, its heartbeat says ``watchdog`` and the upper availability
monitor counts the ADN unavailable; the upper CPFC switches without it, bumplessly. Unlike a
plant's, the ADN's watchdog keeps the last set-point (``watchdog_holds``): the ADN runs on its
last reference, not on its schedule. When commands return, the DER controller hands over from
that set-point to its new share as every returning DER does
(docs/method.md#returning-ders-handover), and the offset follows it.
"""

from __future__ import annotations

from adnmesh.config import DER, Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.der_controller import DERController
from adnmesh.control.plant_device import DeviceStatus
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["AdnPlant", "AdnSite"]


class AdnPlant:
    """The ADN as its upper DER's plant device (see the module docstring).

    Parameters
    ----------
    der : DER
        The ADN's DER in the upper config (``p_sched_w``, ``p_inst_w``).
    p_ip0_w : float
        The ADN's exchange in its operating point, W.
    stale_after_ns : int
        An exchange older than this makes the device stale, ns.
    """

    def __init__(self, der: DER, p_ip0_w: float, stale_after_ns: int) -> None:
        self.der, self.p_ip0_w, self.stale_after_ns = der, p_ip0_w, stale_after_ns
        self.commanded_w = der.p_sched_w      # the DER controller's last set-point, W
        self.p_ip_w = p_ip0_w
        self.held = 0            # every DER that follows the ADN's P_Y at a limit: +1 up, -1 down
        self.last_exchange_ns = 0
        self.now_ns = 0
        self.counts = {"exchanges": 0}

    def command(self, p_w: float, q_var: float | None) -> None:
        self.commanded_w = p_w

    def status(self) -> DeviceStatus:
        p_w = self.der.p_sched_w + self.p_ip_w - self.p_ip0_w
        if self.now_ns - self.last_exchange_ns > self.stale_after_ns:
            return DeviceStatus(False, "stale", "no exchange from the ADN's measurement for "
                                f"{self.stale_after_ns / 1e9:g} s", p_w, None)
        return DeviceStatus(True, None, "", p_w, None, self.held)

    def stats(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.counts.items()}

    @property
    def offset_w(self) -> float:
        """The offset of the ADN's reference the last set-point asks for, W."""
        return self.commanded_w - self.der.p_sched_w


class AdnSite(Agent):
    """The site agent of ADN ``der.id`` (see the module docstring).

    Parameters
    ----------
    der : DER
        The ADN's DER in the upper config.
    upper : Config
        The upper config.
    p_ip0_w : float
        The ADN's exchange in its operating point, W
        (:func:`adnmesh.control.operating_point.initial_p_ip_w` of its config).
    """

    def __init__(self, der: DER, upper: Config, p_ip0_w: float) -> None:
        self.plant = AdnPlant(der, p_ip0_w, ns(upper.runtime.watchdog_timeout_s))
        self.der_controller = DERController(der, upper, der.p_inst_w, device=self.plant,
                                            watchdog_holds=True)
        self.agent_id = self.der_controller.agent_id
        self._offset_key = Keys(upper.grid).of("adn_offset", der.id)
        self._repeat_ns = ns(upper.runtime.heartbeat_period_s)
        self._sent_w: float | None = None     # the offset last sent
        self._next_repeat_ns = 0
        self._restarted = False
        self.counts = {"offsets": 0}

    def next_timer_ns(self) -> int:
        return self.der_controller.next_timer_ns()

    def resume(self, t_ns: int) -> None:
        """A restarted site agent: its DER controller resumes; it sends the offset again from
        its first command on (until then the ADN's CPFC keeps the last one it heard)."""
        self.der_controller.resume(t_ns)
        self.plant.last_exchange_ns = self.plant.now_ns = t_ns
        self._next_repeat_ns = t_ns
        self._restarted = True        # no offset before a command: the ADN keeps its last

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.type == "p_ip":                      # the ADN's exchange
            self.plant.p_ip_w = message.p_ip_w
            self.plant.held = {"up": 1, "down": -1}.get(message.held, 0)
            self.plant.last_exchange_ns = t_ns
            self.plant.counts["exchanges"] += 1
            return []
        return self._offset(t_ns, self.der_controller.on_message(t_ns, message))

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        self.plant.now_ns = t_ns
        return self._offset(t_ns, self.der_controller.on_timer(t_ns))

    def _offset(self, t_ns: int, out: list[Outgoing]) -> list[Outgoing]:
        """``out`` and the offset, if it changed or is due again (a restarted site agent
        sends none before its first command: it does not know the offset the ADN runs on)."""
        if self._restarted:
            if self.der_controller.entry is None:
                return out
            self._restarted = False
        offset = self.plant.offset_w
        if offset != self._sent_w or t_ns >= self._next_repeat_ns:
            out.append(Outgoing(self._offset_key, {"offset_w": offset}))
            self._sent_w = offset
            self._next_repeat_ns = t_ns + self._repeat_ns
            self.counts["offsets"] += 1
        return out

    def finish(self, t_ns: int) -> list[Outgoing]:
        return self.der_controller.finish(t_ns)

    def stats(self) -> dict[str, float]:
        return {**self.der_controller.stats(), **{k: float(v) for k, v in self.counts.items()}}
