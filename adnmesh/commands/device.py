"""``adnmesh device sunspec|iec104 CONFIG --der ID``: a DER's plant behind a real protocol.

Runs the DER's model (:class:`~adnmesh.devices.realtime_plant.RealtimePlant`, as its agent would
run it) in real time behind a protocol server on the address of the DER's ``plant:`` section
(or ``--host``/``--port``): Modbus TCP with the SunSpec DER models, or IEC 60870-5-104 — a
device simulator a lab can swap for the real device. ``adnmesh up`` starts one per DER whose
``plant.simulator`` is true. ``--fault KIND@START+DURATION`` plays a field link's faults, in
seconds from the simulator's start (``down``: the server stops and starts again, a device
restart). It prints one line when it listens and runs until SIGTERM or Ctrl-C.
"""

from __future__ import annotations

import argparse
import re
import signal
import threading
import time

from adnmesh.errors import UsageError

__all__ = ["add_parser", "parse_fault", "run"]

_FAULT = re.compile(r"^([a-z_]+)@([0-9]+(?:\.[0-9]*)?)\+([0-9]+(?:\.[0-9]*)?)$")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``device`` subparser."""
    from adnmesh.devices.faults import FAULT_KINDS
    parser = subparsers.add_parser(
        "device", help="a DER's plant in real time behind SunSpec/Modbus or IEC 104",
        description="Run the DER's model in real time behind a protocol server (a device "
        "simulator for the DER's gateway): sunspec (Modbus TCP, SunSpec DER models 701/704) or "
        "iec104 (IEC 60870-5-104). The address is the DER's plant: section's, or --host/--port. "
        "Runs until SIGTERM or Ctrl-C; exit code 0 then, 2 for a user error.")
    parser.add_argument("protocol", choices=["sunspec", "iec104"], help="the protocol")
    parser.add_argument("config", metavar="CONFIG", help="configuration file (YAML)")
    parser.add_argument("--der", required=True, metavar="ID", help="the DER it simulates")
    parser.add_argument("--host", help="address to listen on (default: the plant's host, "
                        "else 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (default: the plant's port)")
    parser.add_argument("--p-avail-w", type=float, metavar="W",
                        help="its available power, W (default: from the config's grid model)")
    parser.add_argument("--model-params", metavar="JSON",
                        help="its model's parameters (default: from the config)")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND@START+DURATION",
                        help="play a fault, s from the start: " + ", ".join(FAULT_KINDS)
                        + " (e.g. silent@30+5; again for more)")
    return parser


def parse_fault(text: str) -> tuple[str, float, float]:
    """``KIND@START+DURATION`` -> ``(kind, start s, end s)``.

    Raises
    ------
    UsageError
        Not such a text, an unknown kind, or a zero duration.
    """
    from adnmesh.devices.faults import FAULT_KINDS
    found = _FAULT.match(text)
    if found is None or found[1] not in FAULT_KINDS or float(found[3]) <= 0:
        raise UsageError(f"--fault {text!r}: must be KIND@START+DURATION (seconds, duration "
                         f"> 0), KIND one of {', '.join(FAULT_KINDS)}")
    start = float(found[2])
    return found[1], start, start + float(found[3])


def run(args: argparse.Namespace) -> int:
    """Serve until stopped; return the exit code."""
    from adnmesh.config import load_config
    from adnmesh.control.der_model import params_from_json
    from adnmesh.devices.connect import server_for
    from adnmesh.devices.faults import DeviceFaults
    from adnmesh.devices.realtime_plant import RealtimePlant

    config = load_config(args.config)
    (der,) = config.ders_by_id([args.der])
    faults = [parse_fault(text) for text in args.fault]
    plant_config = der.plant if der.plant is not None else None
    if plant_config is not None and plant_config.protocol != args.protocol:
        raise UsageError(f"{config.path}: {der.id}'s plant speaks {plant_config.protocol}, "
                         f"not {args.protocol}")
    port = args.port if args.port is not None else \
        plant_config.port if plant_config is not None else None
    if port is None or not 1 <= port <= 65535:
        raise UsageError(f"--port: {der.id} has no device port in {config.path}; give one "
                         "in [1, 65535]" if port is None else
                         f"--port must be in [1, 65535], got {port}")
    host = args.host or (plant_config.host if plant_config is not None else "127.0.0.1")
    params = None
    if args.model_params is not None:
        try:
            params = params_from_json(args.model_params)
        except ValueError as exc:
            raise UsageError(f"--model-params: {exc}") from None
    p_avail_w = args.p_avail_w
    if p_avail_w is None:
        from adnmesh.control.operating_point import available_power_w
        p_avail_w = available_power_w(config)[der.id]
    if not p_avail_w > 0:
        raise UsageError(f"--p-avail-w must be positive, got {p_avail_w:g}")
    _die_with_parent()
    plant = RealtimePlant(der, config, p_avail_w, params)
    switches = DeviceFaults()
    server = server_for(args.protocol, der, config, plant, host, port, switches)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    try:
        server.start()
    except OSError as exc:
        detail = exc.strerror or str(exc)
        raise UsageError(detail if detail.startswith("cannot listen") else
                         f"cannot listen on {host}:{port}: {detail}") from None
    print(f"adnmesh device: {der.id} ({der.type}, {der.p_inst_w / 1e6:g} MW) as a "
          f"{args.protocol} device on {host}:{port}", flush=True)
    try:
        _play(faults, switches, server, stop)
    finally:
        server.stop()
    return 0


def _play(faults, switches, server, stop: threading.Event) -> None:
    """Switch the faults on and off at their times until ``stop`` is set."""
    t0 = time.monotonic()
    edges = sorted([(start, kind, True) for kind, start, _ in faults]
                   + [(end, kind, False) for kind, _, end in faults])
    for at, kind, on in edges:
        if stop.wait(max(0.0, t0 + at - time.monotonic())):
            return
        if kind == "down":
            (server.stop if on else server.start)()
        else:
            setattr(switches, kind, on)
        print(f"adnmesh device: {'start' if on else 'end'} of {kind} at {at:g} s", flush=True)
    stop.wait()


def _die_with_parent() -> None:
    """Started by ``adnmesh up``: end with it."""
    from adnmesh.runtime.process import die_with_parent
    die_with_parent()
