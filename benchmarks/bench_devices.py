"""Benchmark: what a DER gateway's protocol costs.

**Latency** (per repeat, on 127.0.0.1, in one process): a device simulator's server and the
gateway's link of each protocol — SunSpec/Modbus TCP, SunSpec over TLS, IEC 60870-5-104 — and
``--calls`` calls of ``write(P, Q)`` and of ``read()``: p50 and p99 in ms. Peers measured in the
same repeat: a bare TCP round trip of 16 bytes (the floor any request/response protocol pays on
this machine) and pysunspec2's own Modbus client reading model 701 of the same server (another
implementation of the same request); each protocol's p50 is also given as a ratio to the TCP
round trip.

    .venv/bin/python benchmarks/bench_devices.py [--repeat 3] [--calls 1000]
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "simbench.yaml"


def _quantiles(values: list[float]) -> tuple[float, float]:
    ordered = sorted(values)
    return ordered[len(ordered) // 2] * 1e3, ordered[min(len(ordered) - 1,
                                                          int(0.99 * len(ordered)))] * 1e3


def _timed(call, n: int) -> list[float]:
    out = []
    for i in range(n):
        began = time.perf_counter()
        call(i)
        out.append(time.perf_counter() - began)
    return out


def _tcp_round_trip(n: int) -> list[float]:
    """A bare TCP request/response of 16 bytes on 127.0.0.1."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def echo() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while data := conn.recv(64):
                conn.sendall(data)

    thread = threading.Thread(target=echo, daemon=True)
    thread.start()
    with socket.create_connection(("127.0.0.1", port)) as client:
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        times = _timed(lambda i: (client.sendall(b"x" * 16), client.recv(64)), n)
    thread.join()
    listener.close()
    return times


def _plant(config, der_index: int = 0):
    from adnmesh.devices.realtime_plant import RealtimePlant
    return RealtimePlant(config.ders[der_index], config)


def _certificates(directory: Path) -> tuple[str, str, str]:
    from adnmesh.runtime.certificates import cert_files, issue
    issue(directory, ["der/SGen1"], hosts=["127.0.0.1", "localhost"])
    files = cert_files(directory, "der/SGen1")
    return str(directory / "ca.pem"), str(files.cert), str(files.key)


def _protocol_latency(name: str, config, calls: int, certs) -> dict[str, tuple[float, float]]:
    from adnmesh.devices.iec104 import IEC104Link, IEC104Server
    from adnmesh.devices.sunspec import SunSpecLink, SunSpecServer
    plant = _plant(config)
    p_inst = config.ders[0].p_inst_w
    if name == "sunspec":
        server, link = SunSpecServer(plant), None
    elif name == "sunspec+tls":
        server = SunSpecServer(plant, host="127.0.0.1", tls=(certs[1], certs[2]))
    else:
        server = IEC104Server(plant)
    with server:
        if name == "sunspec":
            link = SunSpecLink("127.0.0.1", server.port, timeout_s=2.0)
        elif name == "sunspec+tls":
            link = SunSpecLink("127.0.0.1", server.port, timeout_s=2.0,
                               tls=(certs[0], None, None))
        else:
            link = IEC104Link("127.0.0.1", server.port, timeout_s=2.0)
        connect = _timed(lambda i: (link.close(), link.connect()), 20)
        out = {"connect": _quantiles(connect)}
        out["write"] = _quantiles(_timed(
            lambda i: link.write(p_inst * (0.4 + 0.2 * (i % 2)), 1e4 * (i % 3)), calls))
        out["read"] = _quantiles(_timed(lambda i: link.read(), calls))
        if name == "sunspec":
            out["pysunspec2 read 701"] = _pysunspec2_read(server.port, calls)
        link.close()
    return out


def _pysunspec2_read(port: int, calls: int) -> tuple[float, float]:
    """pysunspec2's own client reading model 701 of the same server."""
    import sunspec2.modbus.client as client
    device = client.SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr="127.0.0.1", ipport=port,
                                                  timeout=2.0)
    device.scan()
    model = device.models[701][0]
    times = _timed(lambda i: model.read(), calls)
    device.close()
    return _quantiles(times)


def latency(args, config) -> None:
    rows: dict[tuple[str, str], list[tuple[float, float]]] = {}
    floor: list[float] = []
    ratios: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        certs = _certificates(Path(tmp))
        for repeat in range(args.repeat):
            rtt = _quantiles(_tcp_round_trip(args.calls))
            floor.append(rtt[0])
            for name in ("sunspec", "sunspec+tls", "iec104"):
                for what, value in _protocol_latency(name, config, args.calls, certs).items():
                    rows.setdefault((name, what), []).append(value)
                    if what in ("write", "read"):
                        ratios.setdefault(f"{name} {what}", []).append(value[0] / rtt[0])
            print(f"repeat {repeat + 1}/{args.repeat} done (load {os.getloadavg()[0]:.1f})",
                  file=sys.stderr)
    print(f"\nlatency on 127.0.0.1, {args.calls} calls per figure, {args.repeat} repeats "
          "(ranges over repeats), ms")
    print(f"{'protocol':<13} {'call':<20} {'p50':>15} {'p99':>15} {'p50 / TCP RTT':>15}")
    print(f"{'tcp':<13} {'16-byte round trip':<20} {_span(floor):>15}")
    for (name, what), values in rows.items():
        ratio = _span(ratios[f"{name} {what}"], "x") if f"{name} {what}" in ratios else ""
        print(f"{name:<13} {what:<20} {_span([v[0] for v in values]):>15} "
              f"{_span([v[1] for v in values]):>15} {ratio:>15}")


def _span(values: list[float], unit: str = "") -> str:
    return f"{min(values):.3g}-{max(values):.3g}{unit}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--calls", type=int, default=1000)
    args = parser.parse_args()
    import logging
    logging.disable(logging.CRITICAL)          # pymodbus's and c104's complaints
    from adnmesh.config import load_config
    config = load_config(CONFIG)
    latency(args, config)


if __name__ == "__main__":
    main()
