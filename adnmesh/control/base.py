"""What every agent state machine looks like to the runtime that drives it.

An agent is a plain object with a few methods and no I/O: the runtime
(:class:`adnmesh.runtime.node.Node`) feeds it delivered messages and timer expiries in time order
and publishes what it returns. Times are integer nanoseconds of sim time (scaled wall time in
realtime mode); an agent never reads a clock itself, so the same agent runs unchanged in both
clocks and in tests.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

from adnmesh.runtime.messages import Message

__all__ = ["Agent", "Outgoing"]


class Outgoing(NamedTuple):
    """A message an agent wants sent: its key and its body (the runtime adds the envelope).
    A named tuple: agents make one per message."""

    key: str
    body: dict[str, Any]


class Agent(Protocol):
    """The interface of an agent state machine."""

    agent_id: str
    """``cpfc``, ``measurement``, ``availability`` or ``der/<id>``."""

    def next_timer_ns(self) -> int | None:
        """Time of the agent's next timer, ns (None: no timer)."""

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        """Handle every timer due at ``t_ns`` (== :meth:`next_timer_ns`); return what to send."""

    def on_message(self, t_ns: int, message: Message) -> list[Outgoing]:
        """Handle ``message`` delivered at ``t_ns``; return what to send."""

