"""What every agent state machine looks like to the runtime that drives it.

An agent is a plain object with no I/O: the sim layer (:class:`adnmesh.sim.node.Node`) feeds it
delivered messages and timer expiries in time order and sends what it returns. Times are
integer nanoseconds of sim time (scaled wall time on the realtime clock); an agent never reads a
clock itself, so the same agent runs unchanged on both clocks and in tests.

Lifecycle, in this order: construction (from the config) → :meth:`resume` if the agent is a
restarted one that begins later than 0 → any number of :meth:`on_message` and :meth:`on_timer`
calls, in time order, at equal times messages first → :meth:`finish` once the run stops (what to
send before the goodbye) → :meth:`stats` for the goodbye.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, NamedTuple

from adnmesh.wire.messages import Envelope

__all__ = ["Agent", "Outgoing"]


class Outgoing(NamedTuple):
    """A message an agent wants sent: its key and the body fields of the key's message type
    (the runtime adds the envelope). A named tuple: agents make one per message."""

    key: str
    body: dict[str, Any]


class Agent(ABC):
    """The interface of an agent state machine (see the module docstring)."""

    agent_id: str
    """``cpfc``, ``measurement``, ``availability`` or ``der/<id>``."""

    @abstractmethod
    def next_timer_ns(self) -> int | None:
        """Time of the agent's next timer, ns (None: no timer)."""

    @abstractmethod
    def on_timer(self, t_ns: int) -> list[Outgoing]:
        """Handle every timer due at ``t_ns`` (== :meth:`next_timer_ns`); return what to send."""

    @abstractmethod
    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        """Handle ``message`` (validated, from the key's sender) delivered at ``t_ns``."""

    def on_clock(self, mode: str) -> None:
        """The run's clock is known, ``"sim"`` or ``"realtime"`` (called before any event)."""

    def resume(self, t_ns: int) -> None:
        """Start at ``t_ns`` instead of 0: a restarted agent (called before any event)."""
        raise NotImplementedError(f"{type(self).__name__} cannot be restarted")

    def finish(self, t_ns: int) -> list[Outgoing]:
        """The run stops at ``t_ns``: return what to send before saying goodbye."""
        return []

    def stats(self) -> dict[str, float]:
        """Counters for the goodbye and the summary (name -> number)."""
        return {}
