"""``adnmesh schema NAME``: print the JSON Schema of one of adnmesh's file formats.

:data:`SCHEMAS` is the registry: a name and the function that returns its schema. The committed
``configs/config.schema.json`` is ``adnmesh schema config`` and ``configs/hierarchy.schema.json``
``adnmesh schema hierarchy`` (a test keeps them equal); editors
with the YAML language server use it through the first line of every config,
``# yaml-language-server: $schema=config.schema.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from adnmesh import config

__all__ = ["SCHEMAS", "add_parser", "render", "run"]

def _messages() -> dict[str, Any]:
    """The bus messages: one schema per message type, as recordings carry them."""
    from adnmesh.wire.schemas import message_schemas
    return message_schemas()


SCHEMAS: dict[str, Callable[[], dict[str, Any]]] = {"config": config.json_schema,
                                                   "hierarchy": config.hierarchy_json_schema,
                                                   "messages": _messages}
"""Schema name -> function returning the JSON Schema (a dict)."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``schema`` subparser."""
    parser = subparsers.add_parser(
        "schema",
        help="print the JSON Schema of a file format",
        description="Print the JSON Schema (draft 2020-12) of NAME to stdout: 'config' is the "
        "format of a config file, with every key's meaning and unit "
        "(configs/config.schema.json is its output); 'hierarchy' the format of a hierarchy "
        "file (adnmesh cascade; configs/hierarchy.schema.json); 'messages' the bus messages, "
        "one schema per message type (the schemas every recording carries). Exit code 0, 2 for an "
        "unknown NAME.",
    )
    parser.add_argument("name", metavar="NAME", choices=list(SCHEMAS),
                        help=f"which schema: {', '.join(SCHEMAS)}")
    return parser


def render(name: str) -> str:
    """Return the schema ``name`` as indented JSON text with a final newline."""
    return json.dumps(SCHEMAS[name](), indent=2, ensure_ascii=False) + "\n"


def run(args: argparse.Namespace) -> int:
    """Print the schema ``args.name``."""
    print(render(args.name), end="")
    return 0
