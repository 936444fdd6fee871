"""The CPFC with reactive power control: the P loop and the Q loop in one agent.

Both loops are :class:`~adnmesh.control.cpfc_controller.CPFC` state machines, one per quantity
(:mod:`adnmesh.control.loop_quantity`); they run in one process (agent id ``cpfc``) because
they share every input — SI, the DERs' heartbeats, the measurement's ``p_ip``, which carries
P_IP and Q_IP — and sample at the same instants. Each delivered message goes to both loops,
each timer to the loop whose sample is due; the Q loop sends ``cpfc/q_y`` and
``scenario/q_ref`` (docs/method.md#reactive-power).
"""

from __future__ import annotations

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.cpfc_controller import CPFC, GainSchedule, initial_p_ref_w
from adnmesh.control.loop_quantity import Q_LOOP
from adnmesh.control.operating_point import initial_q_ip_var
from adnmesh.reactive import q_reference, reactive_view
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["CPFCPair", "reactive_cpfc"]


def reactive_cpfc(config: Config, schedule: GainSchedule | None = None,
                  reachable: tuple[float, float] | None = None) -> CPFC:
    """The Q loop of ``config`` (its reactive view; ``schedule`` default: the Q gains tuned
    on demand, no table; ``reachable``: the Q_IP range Q_ref is clipped to, var)."""
    view = reactive_view(config)
    if schedule is None:
        schedule = GainSchedule(view, None)
    start, steps = q_reference(config, initial_p_ref_w(config), initial_q_ip_var(config))
    top = {der.id: der.p_inst_w for der in view.ders}      # C_d^Q: the whole reactive range
    return CPFC(view, schedule, Q_LOOP, start_ref=start, available=top,
                steps=[(ns(t_s), change) for t_s, change in steps],
                known_ids=config.der_ids(), reachable=reachable)


class CPFCPair(Agent):
    """The P loop ``p`` and the Q loop ``q`` as one agent (see the module docstring)."""

    agent_id = "cpfc"

    def __init__(self, p: CPFC, q: CPFC) -> None:
        self.p, self.q = p, q
        self.loops = (p, q)

    def next_timer_ns(self) -> int:
        return min(self.p.next_timer_ns(), self.q.next_timer_ns())

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out: list[Outgoing] = []
        for loop in self.loops:
            if loop.next_timer_ns() == t_ns:
                out += loop.on_timer(t_ns)
        return out

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        return self.p.on_message(t_ns, message) + self.q.on_message(t_ns, message)

    def on_clock(self, mode: str) -> None:
        for loop in self.loops:
            loop.on_clock(mode)

    def resume(self, t_ns: int) -> None:
        for loop in self.loops:
            loop.resume(t_ns)

    def finish(self, t_ns: int) -> list[Outgoing]:
        return self.p.finish(t_ns) + self.q.finish(t_ns)

    def stats(self) -> dict[str, float]:
        return {**self.p.stats(), **self.q.stats()}
