"""Benchmark: what a DER gateway's protocol costs, and how many device connections one machine
serves.

**Latency** (per repeat, on 127.0.0.1, in one process): a device simulator's server and the
gateway's link of each protocol — SunSpec/Modbus TCP, SunSpec over TLS, IEC 60870-5-104 — and
``--calls`` calls of ``write(P, Q)`` and of ``read()``: p50 and p99 in ms. Peers measured in the
same repeat: a bare TCP round trip of 16 bytes (the floor any request/response protocol pays on
this machine) and pysunspec2's own Modbus client reading model 701 of the same server (another
implementation of the same request); each protocol's p50 is also given as a ratio to the TCP
round trip.

**Connections**: ``K`` SunSpec (or 104) devices served by one "device farm" process (``K``
servers, each a DER's model), ``K`` gateways in this process each polling its device every
``--poll`` s for ``--seconds`` s: the reads achieved against those asked for, their p99 and the
CPU both processes used. ``K`` grows until fewer than 95 % of the reads are achieved.

    .venv/bin/python benchmarks/bench_devices.py [--repeat 3] [--calls 1000]
        [--connections 10,50,100,200] [--poll 0.1] [--seconds 10]
"""
from __future__ import annotations

import argparse
import os
import resource
import socket
import statistics
import subprocess
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


FARM = """
import signal, sys, threading
from adnmesh.config import load_config
from adnmesh.devices.realtime_plant import RealtimePlant
protocol, count = sys.argv[1], int(sys.argv[2])
config = load_config(sys.argv[3])
if protocol == "sunspec":
    from adnmesh.devices.sunspec import SunSpecServer as Server
else:
    from adnmesh.devices.iec104 import IEC104Server as Server
servers = [Server(RealtimePlant(config.ders[i % len(config.ders)], config)) for i in range(count)]
for s in servers:
    s.start()
print(" ".join(str(s.port) for s in servers), flush=True)
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
stop.wait()
for s in servers:
    s.stop()
"""


def connections(args, config) -> None:
    from adnmesh.devices.gateway import Gateway
    from adnmesh.devices.iec104 import IEC104Link
    from adnmesh.devices.sunspec import SunSpecLink
    print(f"\ndevice connections: gateways polling every {args.poll:g} s for {args.seconds:g} s "
          "against one device-farm process")
    print(f"{'protocol':<9} {'K':>5} {'reads asked':>12} {'achieved':>9} {'read p99 ms':>12} "
          f"{'CPU s (gateways)':>17} {'CPU s (farm)':>13} {'load':>5}")
    for protocol in args.protocols.split(","):
        for count in [int(k) for k in args.connections.split(",")]:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            farm = subprocess.Popen([sys.executable, "-c", FARM, protocol, str(count),
                                     str(CONFIG)], stdout=subprocess.PIPE, text=True)
            try:
                ports = [int(p) for p in farm.stdout.readline().split()]
                link = SunSpecLink if protocol == "sunspec" else IEC104Link
                gateways = [Gateway(link("127.0.0.1", port, timeout_s=1.0), args.poll, 5.0,
                                    1.0) for port in ports]
                cpu0 = time.process_time()
                for gateway in gateways:
                    gateway.start()
                time.sleep(args.seconds)
                for gateway in gateways:
                    gateway.stop()
                cpu = time.process_time() - cpu0
                stats = [g.stats() for g in gateways]
            finally:
                farm.terminate()
                farm.wait()
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            farm_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            reads = sum(s["device_reads"] for s in stats)
            asked = count * args.seconds / args.poll
            p99 = max(s.get("device_read_p99_ms", float("nan")) for s in stats)
            print(f"{protocol:<9} {count:>5} {asked:>12.0f} {reads / asked:>8.1%} {p99:>12.3g} "
                  f"{cpu:>17.2f} {farm_cpu:>13.2f} "
                  f"{os.getloadavg()[0]:>5.1f}")
            if reads / asked < 0.95:
                break


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--connections", default="10,50,100,200")
    parser.add_argument("--protocols", default="sunspec,iec104")
    parser.add_argument("--poll", type=float, default=0.1)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--only", choices=["latency", "connections"])
    args = parser.parse_args()
    import logging
    logging.disable(logging.CRITICAL)          # pymodbus's and c104's complaints
    from adnmesh.config import load_config
    config = load_config(CONFIG)
    if args.only != "connections":
        latency(args, config)
    if args.only != "latency":
        connections(args, config)


if __name__ == "__main__":
    main()
