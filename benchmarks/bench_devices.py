"""Benchmark: what a DER gateway's protocol costs.

**Latency** (per repeat, on 127.0.0.1, in one process): a device simulator's server and the
gateway's link of each protocol — SunSpec/Modbus TCP, SunSpec over TLS, IEC 60870-5-104 — and
``--calls`` calls of ``write(P, Q)`` and of ``read()``: p50 and p99 in ms. Peers measured in the
same repeat: a bare TCP round trip of 16 bytes (the floor any request/response protocol pays on
this machine) and pysunspec2's own Modbus client reading model 701 of the same server (another
implementation of the same request); each protocol's p50 is also given as a ratio to the TCP
round trip.

**Connections** (``--connections 25,50,100``): how many devices one machine serves. For each
protocol and count N, one process serves N device simulators (N protocol servers, each with a
DER's model) and another runs N gateways (:class:`~adnmesh.devices.gateway.Gateway`, as N DER
agents would, in one process) polling every ``--poll-period`` s for ``--seconds`` s. Printed:
the reads done as a share of those due, the read p50/p99 over all gateways, connection
errors, and each side's CPU in percent of one core. The machine serves N devices at that
period while the share stays near 100 % and p99 well under the period. Peer in the same
run: the latency figures' TCP round trip (``--repeat 0`` skips the latency part).

    .venv/bin/python benchmarks/bench_devices.py [--repeat 3] [--calls 1000]
        [--connections 25,50,100,200 --poll-period 0.02 --seconds 20]
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


def _serve(protocol: str, count: int) -> None:
    """The server side of ``--connections``: ``count`` simulators of DER 0, their ports as one
    JSON line on stdout, then this process's CPU seconds for each line on stdin, until it
    closes."""
    import json
    import resource
    from adnmesh.config import load_config
    from adnmesh.devices.iec104 import IEC104Server
    from adnmesh.devices.sunspec import SunSpecServer
    config = load_config(CONFIG)
    kind = SunSpecServer if protocol == "sunspec" else IEC104Server
    servers = [kind(_plant(config)) for _ in range(count)]
    for server in servers:
        server.start()
    print(json.dumps([server.port for server in servers]), flush=True)
    for _ in sys.stdin:                       # each line asks for the CPU seconds so far
        usage = resource.getrusage(resource.RUSAGE_SELF)
        print(json.dumps(usage.ru_utime + usage.ru_stime), flush=True)
    for server in servers:
        server.stop()


def _server_cpu(server) -> float:
    """The server process's CPU seconds so far (nan if it is gone)."""
    try:
        server.stdin.write("\n")
        server.stdin.flush()
        return float(server.stdout.readline() or "nan")
    except (BrokenPipeError, ValueError):
        return float("nan")


def _gateways(protocol: str, count: int, args) -> dict[str, float]:
    """``count`` gateways against ``count`` simulators in a process of their own."""
    import json
    import resource
    import subprocess
    from adnmesh.devices.gateway import Gateway
    from adnmesh.devices.iec104 import IEC104Link
    from adnmesh.devices.sunspec import SunSpecLink
    server = subprocess.Popen([sys.executable, __file__, "--serve", protocol, str(count)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    gateways = []
    try:
        ports = json.loads(server.stdout.readline())
        kind = SunSpecLink if protocol == "sunspec" else IEC104Link
        gateways = [Gateway(kind("127.0.0.1", port, timeout_s=1.0), args.poll_period,
                            stale_after_s=60.0, retry_s=1.0) for port in ports]
        for gateway in gateways:
            gateway.start()
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and any(g.stats()["device_reads"] < 1
                                                  for g in gateways):
            time.sleep(0.1)
        reads0 = sum(g.stats()["device_reads"] for g in gateways)
        server_cpu0 = _server_cpu(server)
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        began = time.monotonic()
        time.sleep(args.seconds)
        took = time.monotonic() - began
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        server_cpu = _server_cpu(server) - server_cpu0
        stats = [g.stats() for g in gateways]
        server.stdin.close()
    finally:
        for gateway in gateways:
            gateway.stop()
        if server.poll() is None:
            server.kill()
        server.wait()
    reads = sum(s["device_reads"] for s in stats) - reads0
    p50 = sorted(s.get("device_read_p50_ms", float("nan")) for s in stats)
    p99 = max(s.get("device_read_p99_ms", float("nan")) for s in stats)
    return {"done_pct": 100 * reads / (count * took / args.poll_period),
            "p50_ms": p50[len(p50) // 2], "p99_ms": p99,
            "errors": sum(s["device_errors"] for s in stats),
            "gateway_cpu_pct": 100 * (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime
                                      - cpu0.ru_stime) / took,
            "server_cpu_pct": 100 * server_cpu / took}


def _row(protocol: str, count: int, args) -> dict[str, float] | str:
    """One row of ``--connections`` in a process of its own: a library that aborts its
    process under overload (c104 does, when a callback waits over 100 ms for its lock)
    ends that row, not the benchmark. The row, or why there is none."""
    import json
    import subprocess
    argv = [sys.executable, __file__, "--row", protocol, str(count), "--poll-period",
            str(args.poll_period), "--seconds", str(args.seconds)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=args.seconds + 300)
    if done.returncode == 0:
        return json.loads(done.stdout.strip().splitlines()[-1])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    why = next((line.strip() for line in lines if "what()" in line), lines[-1] if lines else "")
    return f"aborted (exit code {done.returncode}): {why[:90]}"


def connections(args) -> None:
    print(f"\nconnections: N gateways polling every {args.poll_period * 1e3:g} ms for "
          f"{args.seconds:g} s against N simulators (two processes)")
    print(f"{'protocol':<9} {'N':>5} {'reads done':>11} {'p50 ms':>8} {'p99 ms':>8} "
          f"{'errors':>7} {'gateway CPU':>12} {'server CPU':>11} {'load':>5}")
    for protocol in ("sunspec", "iec104"):
        for count in args.connections:
            row = _row(protocol, count, args)
            if isinstance(row, str):
                print(f"{protocol:<9} {count:>5} {row}", flush=True)
                break
            print(f"{protocol:<9} {count:>5} {row['done_pct']:>10.1f}% {row['p50_ms']:>8.2f} "
                  f"{row['p99_ms']:>8.2f} {row['errors']:>7.0f} "
                  f"{row['gateway_cpu_pct']:>11.0f}% {row['server_cpu_pct']:>10.0f}% "
                  f"{os.getloadavg()[0]:>5.1f}", flush=True)


def _span(values: list[float], unit: str = "") -> str:
    return f"{min(values):.3g}-{max(values):.3g}{unit}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--connections", type=lambda text: [int(n) for n in text.split(",")],
                        default=[])
    parser.add_argument("--poll-period", type=float, default=0.02)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--serve", nargs=2, metavar=("PROTOCOL", "N"), help=argparse.SUPPRESS)
    parser.add_argument("--row", nargs=2, metavar=("PROTOCOL", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    import logging
    logging.disable(logging.CRITICAL)          # pymodbus's and c104's complaints
    if args.serve:
        _serve(args.serve[0], int(args.serve[1]))
        return
    if args.row:
        import json
        print(json.dumps(_gateways(args.row[0], int(args.row[1]), args)))
        return
    from adnmesh.config import load_config
    config = load_config(CONFIG)
    if args.repeat:
        latency(args, config)
    if args.connections:
        connections(args)


if __name__ == "__main__":
    main()
