"""The wire protocol: what goes over the bus, below control and runtime.

- :mod:`~adnmesh.wire.keys`: the bus keys, their message types and legitimate senders;
- :mod:`~adnmesh.wire.messages`: one msgspec struct per message type (envelope and body);
- :mod:`~adnmesh.wire.envelope`: decode (validating) and encode, envelope times, framing;
- :mod:`~adnmesh.wire.schemas`: the JSON Schemas of the types, generated from the structs;
- :mod:`~adnmesh.wire.units`: integer nanoseconds of sim time.

The wire layer imports nothing of adnmesh above it (numerics, control, sim, runtime).
"""

from adnmesh.wire.envelope import MessageError, decode, encode, envelope_times, frames, split_frame
from adnmesh.wire.keys import Keys, Route, der_agent_id, route
from adnmesh.wire.messages import MESSAGE_TYPES, MESSAGE_VERSION, Envelope
from adnmesh.wire.schemas import message_schemas
from adnmesh.wire.units import NS_MAX, ns

__all__ = ["MESSAGE_TYPES", "MESSAGE_VERSION", "NS_MAX", "Envelope", "Keys", "MessageError",
           "Route", "decode", "der_agent_id", "encode", "envelope_times", "frames",
           "message_schemas", "ns", "route", "split_frame"]
