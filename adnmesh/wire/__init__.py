"""The wire protocol: what goes over the bus, below control and runtime.

- :mod:`~adnmesh.wire.protocol`: **the protocol table**, one row per message kind (key, struct,
  sender, receivers, link, plotted fields); everything below is derived from it;
- :mod:`~adnmesh.wire.messages`: one msgspec struct per message type (envelope and body);
- :mod:`~adnmesh.wire.keys`: the bus keys, built and parsed from the table;
- :mod:`~adnmesh.wire.envelope`: decode (validating) and encode, envelope times, framing;
- :mod:`~adnmesh.wire.gate`: the accept rules every receiver applies, and its reject counts;
- :mod:`~adnmesh.wire.outbox`: how every sender builds its envelopes;
- :mod:`~adnmesh.wire.schemas`: the JSON Schemas of the types, generated from the structs;
- :mod:`~adnmesh.wire.units`: integer nanoseconds of sim time.

The wire layer imports nothing of adnmesh above the foundation (:mod:`adnmesh.names`).
"""

from adnmesh.wire.envelope import MessageError, decode, encode, envelope_times, frames, split_frame
from adnmesh.wire.gate import Gate
from adnmesh.wire.keys import Keys, Route, route
from adnmesh.wire.messages import MESSAGE_VERSION, Envelope
from adnmesh.wire.outbox import Outbox
from adnmesh.wire.protocol import KINDS, PROTOCOL, STRUCTS, MessageKind
from adnmesh.wire.schemas import message_schemas
from adnmesh.wire.units import NS_MAX, ns

__all__ = ["KINDS", "MESSAGE_VERSION", "NS_MAX", "PROTOCOL", "STRUCTS", "Envelope", "Gate",
           "Keys", "MessageError", "MessageKind", "Outbox", "Route", "decode", "encode",
           "envelope_times", "frames", "message_schemas", "ns", "route", "split_frame"]
