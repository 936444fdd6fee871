"""JSON Schemas of the message types, generated from their structs.

Recordings carry one schema per message type (schema encoding ``jsonschema``, draft 2020-12) so
that Foxglove and any JSON Schema validator read them without adnmesh. They are generated from
the structs of the protocol table (:mod:`adnmesh.wire.protocol`) by msgspec, so they say exactly what decoding
accepts: field types, bounds, string and mapping lengths, required fields, no other fields. The
one check a schema cannot state (``t_deliver_ns >= t_send_ns``, and the sender of a key) is in
each schema's description. One pattern a schema states is checked after decoding: the DER ids
in the CPFC's weights, SI, a switch's ``keep`` and the grid guard's lists
(:data:`~adnmesh.wire.messages.RunDER`), which every receiver's gate checks against the run's
own DERs instead (``unknown_der``).
"""

from __future__ import annotations

import functools

import msgspec

from adnmesh.wire.messages import MESSAGE_VERSION
from adnmesh.wire.protocol import STRUCTS

__all__ = ["SCHEMA_DIALECT", "message_schema", "message_schemas"]

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
"""The JSON Schema dialect of every schema."""


def message_schema(type_name: str) -> dict:
    """The JSON Schema of one message type (a self-contained document, no top-level $ref)."""
    cls = STRUCTS[type_name]
    generated = msgspec.json.schema(cls)
    definitions = dict(generated.get("$defs", {}))
    name = generated["$ref"].rsplit("/", 1)[-1]
    schema = definitions.pop(name)
    description = (" ".join(schema.get("description", "").split()) + " Also: t_deliver_ns >= t_send_ns; src is "
                   "the one sender of the key it is published on.").strip()
    document = {"$schema": SCHEMA_DIALECT,
                "$id": f"https://adnmesh.invalid/schemas/v{MESSAGE_VERSION}/{type_name}.json",
                **schema, "title": type_name, "description": description}
    if definitions:
        document["$defs"] = definitions
    return document


@functools.cache
def message_schemas() -> dict[str, dict]:
    """Message type -> its JSON Schema, for every type."""
    return {name: message_schema(name) for name in STRUCTS}
