"""Benchmark of the wire layer: decode + validate and encode of the bus's commonest messages.

Prints, per message type, microseconds per call (min / median / max over repeats) for

- adnmesh's :func:`adnmesh.wire.decode` (msgspec: parse and validate in one pass, then the
  sender and time-order checks) and :func:`adnmesh.wire.encode`;
- the same payload through the standard library's ``json.loads`` and the ``jsonschema``
  validator of the recording's JSON Schema (a well-known peer, measured in the same run);
- optionally the implementation of an older git revision (``--baseline-rev``, e.g. the commit
  before the wire layer): its ``adnmesh/runtime/messages.py`` and ``validator.py`` are taken
  from git into a temporary package and timed on the same payloads.

Run: ``.venv/bin/python benchmarks/bench_messages.py [--baseline-rev 1c0efb4] [--repeat 7]``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import statistics
import subprocess
import sys
import tempfile
import timeit
from pathlib import Path

import jsonschema

from adnmesh.wire.envelope import decode, encode
from adnmesh.wire.keys import Keys, route
from adnmesh.wire.messages import MESSAGE_VERSION
from adnmesh.wire.protocol import STRUCTS
from adnmesh.wire.schemas import message_schemas

REPO = Path(__file__).resolve().parent.parent
KEYS = Keys("simbench-1-MV-rural")
CASES = {
    "der_state": (KEYS.of("der_state", "SGen1"), {"p_w": 1000012.5123, "setpoint_w": 1000000.0,
                                            "mode": "control"}),
    "p_ip": (KEYS.of("p_ip"), {"p_ip_w": 5712345.678}),
    "p_y": (KEYS.of("p_y"), {"p_y": 0.123456789, "p_ref_w": 6.7e6, "kp": 1.7e-8, "ki": 6.8e-8,
                       "entry": 0}),
}


def payload_of(key: str, body: dict) -> bytes:
    found = route(key)
    cls = STRUCTS[found.type]
    return encode(cls(MESSAGE_VERSION, found.type, found.sender, 1234, 5_000_000_000,
                      5_100_000_000, **body))


def per_call_us(function, repeat: int, number: int) -> list[float]:
    return [t / number * 1e6 for t in timeit.repeat(function, repeat=repeat, number=number)]


def baseline_decoder(rev: str):
    """``decode(key, payload)`` of git revision ``rev`` (its runtime/messages.py)."""
    tmp = Path(tempfile.mkdtemp(prefix="adnmesh-baseline-"))
    package = tmp / "baseline_wire"
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name in ("messages", "validator"):
        text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:adnmesh/runtime/{name}.py"],
                              check=True, capture_output=True, text=True).stdout
        text = text.replace("from adnmesh.runtime.validator", "from baseline_wire.validator")
        (package / f"{name}.py").write_text(text)
    sys.path.insert(0, str(tmp))
    return importlib.import_module("baseline_wire.messages").decode


def show(label: str, times: list[float]) -> float:
    median = statistics.median(times)
    print(f"  {label:<38} {min(times):7.2f} {median:7.2f} {max(times):7.2f}")
    return median


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--number", type=int, default=50_000)
    parser.add_argument("--baseline-rev", metavar="REV",
                        help="also time the decoder of this git revision")
    args = parser.parse_args()
    old = baseline_decoder(args.baseline_rev) if args.baseline_rev else None
    schemas = message_schemas()
    print("microseconds per call: min median max")
    for name, (key, body) in CASES.items():
        data = payload_of(key, body)
        message = decode(key, data)
        validator = jsonschema.Draft202012Validator(schemas[name])
        print(f"{name} ({len(data)} bytes)")
        ours = show("adnmesh decode + validate (msgspec)",
                    per_call_us(lambda: decode(key, data), args.repeat, args.number))
        show("adnmesh encode", per_call_us(lambda: encode(message), args.repeat, args.number))
        peer = show("json.loads + jsonschema validate",
                    per_call_us(lambda: validator.validate(json.loads(data)), args.repeat,
                                args.number // 10))
        print(f"  -> peer / adnmesh = {peer / ours:.1f}x")
        if old is not None:
            before = show(f"revision {args.baseline_rev} decode + validate",
                          per_call_us(lambda: old(key, data), args.repeat, args.number))
            print(f"  -> before / after = {before / ours:.2f}x")


if __name__ == "__main__":
    main()
