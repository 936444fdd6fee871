"""The measurement at the interconnection point, as a bus-free state machine.

Every ``measurement_period_s`` it samples

    P_IP = rest_of_grid_w + Σ_d P_d,

the DER infeeds reported at the same instant (the DERs report at the same sampling times, over
the lossless zero-delay ``physical`` path, and the runtime delivers them before the sampling timer
of that instant) plus a constant for the rest of the grid, and sends it to the CPFC on
``measurement/p_ip`` over the ``measurement_to_cpfc`` link (delay ``T_meas``). A power flow of the
SimBench grid replaces the sum in the grid issue.
"""

from __future__ import annotations

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import Envelope
from adnmesh.wire.units import ns

__all__ = ["Measurement"]


class Measurement(Agent):
    """Samples ``P_IP`` (agent id ``measurement``; see the module docstring)."""

    agent_id = "measurement"

    def __init__(self, config: Config) -> None:
        keys = Keys(config.grid)
        self._p_ip_key = keys.p_ip
        self.period_ns = ns(config.runtime.measurement_period_s)
        self.rest_of_grid_w = config.runtime.rest_of_grid_w
        # infeed per DER agent, in config order (fixed summation order: reproducible sums)
        self.infeed_w = {f"der/{d.id}": d.p_sched_w for d in config.ders}
        self.next_sample_ns = 0

    def next_timer_ns(self) -> int:
        return self.next_sample_ns

    def resume(self, t_ns: int) -> None:
        """A restarted measurement at ``t_ns``: samples from the next sampling instant on."""
        self.next_sample_ns = -(-t_ns // self.period_ns) * self.period_ns

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if message.src in self.infeed_w:
            self.infeed_w[message.src] = message.p_w
        return []

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        p_ip = self.rest_of_grid_w
        for p_w in self.infeed_w.values():
            p_ip += p_w
        self.next_sample_ns += self.period_ns
        return [Outgoing(self._p_ip_key, {"p_ip_w": p_ip})]
