#!/usr/bin/env python3
"""Latency a second Zenoh router adds, open and secure profile: round trips CPFC -> DER -> CPFC.

A ping is what the control loop does: the CPFC's session puts on ``cpfc/p_y``, the DER's session
answers on its ``der/<id>/heartbeat``, the CPFC's session takes the answer. Measured in four
set-ups, all sessions on 127.0.0.1 in this one process:

- one router: CPFC and DER clients of the same router (``adnmesh up``'s embedded one);
- two routers: the DER is a client of a site router (``adnmesh router``) linked to the first;

each in the open profile (TCP) and the secure profile (mutual TLS, the run's access control on
both routers, certificates made for the benchmark). Every round trip is timed; reported are the
median and the 10th/90th percentiles in microseconds, what the second router adds to one
way (half the difference of the medians), and the CPU time of one round trip: this process's
(every session and router of the set-up is in it) over the timed pings, microseconds: what
two samples cost that cross the router from one client to another, as an agent's report and
the grant it lets out do in a sim-clock run. The set-ups alternate, ``--repeat`` times, so that
changes of the machine's speed hit them alike. It measures; it asserts nothing. Usage::

    .venv/bin/python benchmarks/bench_latency.py [--pings 2000] [--repeat 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adnmesh.config import load_config  # noqa: E402
from adnmesh.runtime.acl import access_control  # noqa: E402
from adnmesh.runtime.bus import client_config, free_port, router_config  # noqa: E402
from adnmesh.runtime.certificates import issue  # noqa: E402
from adnmesh.runtime.identity import identities  # noqa: E402
from adnmesh.sim.topology import Topology  # noqa: E402

CONFIG = REPO / "configs" / "examples" / "runtime-step.yaml"
DER = "SGen2"


def routers(topology: Topology, certs: Path | None, two: bool):
    """Open the first router (and the site router linked to it); return (sessions, endpoint of
    the CPFC's router, endpoint of the DER's router)."""
    scheme = "tcp" if certs is None else "tls"
    a = f"{scheme}/127.0.0.1:{free_port()}"
    acl = {} if certs is None else {"certs": certs}
    first = zenoh.open(router_config([a], identity="up", access_control=access_control(
        topology, ["router/site"]), **acl))
    if not two:
        return [first], a, a
    b = f"{scheme}/127.0.0.1:{free_port()}"
    second = zenoh.open(router_config([b], [a], identity="router/site",
                                      access_control=access_control(topology, ["up"]), **acl))
    return [second, first], a, b


def round_trips(topology: Topology, certs: Path | None, two: bool,
                pings: int) -> tuple[list[float], float]:
    """``pings`` timed round trips, microseconds (after 100 untimed ones), and this process's
    CPU time per timed round trip, microseconds."""
    keys = topology.keys
    sessions, cpfc_at, der_at = routers(topology, certs, two)
    answered = threading.Event()
    try:
        cpfc = zenoh.open(client_config([cpfc_at], certs, "cpfc"))
        der = zenoh.open(client_config([der_at], certs, f"der/{DER}"))
        sessions[:0] = [der, cpfc]
        der.declare_subscriber(keys.of("p_y"), lambda s: der.put(keys.of("heartbeat", DER),
                                                           s.payload.to_bytes()))
        cpfc.declare_subscriber(keys.of("heartbeat", DER), lambda s: answered.set())
        times, cpu = [], 0.0
        for i in range(pings + 100):
            if i == 100:
                cpu = time.process_time()
            answered.clear()
            t0 = time.perf_counter_ns()
            cpfc.put(keys.of("p_y"), str(i).encode())
            while not answered.wait(5):           # the routes may still be forming
                cpfc.put(keys.of("p_y"), str(i).encode())
            if i >= 100:
                times.append((time.perf_counter_ns() - t0) / 1e3)
        return times, (time.process_time() - cpu) / pings * 1e6
    finally:
        for session in sessions:
            session.close()


def figures(found: tuple[list[float], float]) -> dict:
    times, cpu_us = found
    deciles = statistics.quantiles(times, n=10)
    return {"median_us": round(statistics.median(times), 1), "p10_us": round(deciles[0], 1),
            "p90_us": round(deciles[-1], 1), "cpu_us": round(cpu_us, 1), "pings": len(times)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pings", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", metavar="PATH")
    args = parser.parse_args()
    topology = Topology.from_config(load_config(CONFIG))
    results: dict = {}
    with tempfile.TemporaryDirectory(prefix="adnmesh-latency-") as tmp:
        certs = Path(tmp) / "certs"
        issue(certs, [*identities(load_config(CONFIG)), "router/site"])
        for repeat in range(args.repeat):
            for profile, directory in (("open", None), ("secure", certs)):
                for setup, two in (("one router", False), ("two routers", True)):
                    found = figures(round_trips(topology, directory, two, args.pings))
                    results.setdefault(f"{profile}, {setup}", []).append(found)
                    print(json.dumps({"repeat": repeat, "profile": profile, "setup": setup,
                                      **found}), flush=True)
    summary = {}
    for profile in ("open", "secure"):
        one = [r["median_us"] for r in results[f"{profile}, one router"]]
        two = [r["median_us"] for r in results[f"{profile}, two routers"]]
        added = sorted((b - a) / 2 for a, b in zip(one, two))
        cpu = sorted(r["cpu_us"] for r in results[f"{profile}, one router"])
        summary[profile] = {"one_router_median_us": one, "two_routers_median_us": two,
                            "added_one_way_us": [round(x, 1) for x in added],
                            "one_router_cpu_us": cpu}
        print(f"{profile}: round trip median {min(one):g} .. {max(one):g} us with one router, "
              f"{min(two):g} .. {max(two):g} us with two; the second router adds "
              f"{added[0]:.0f} .. {added[-1]:.0f} us one way; CPU per round trip with one "
              f"router {cpu[0]:g} .. {cpu[-1]:g} us", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"runs": results, "summary": summary},
                                              indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
