#!/usr/bin/env python3
"""The floor under realtime delivery errors: N bare Python + Zenoh processes waking together.

A realtime SimBench run has 14 processes whose timers fall on the same 10 ms instants (every
DER's sample, the CPFC's PI step, the measurement). This benchmark keeps only that pattern and
nothing of adnmesh's work: ``N`` child processes, each a Zenoh client of one router (a Python
session in mode "router", as in ``adnmesh up``), sleep to every multiple of the period on the
monotonic clock, publish one 64-byte sample stamped with the instant and go back to sleep; a
subscriber on the router's session (a callback, as ``up``'s recorder) takes each sample's
arrival time. Per N it prints the wake-up error (wake time minus the instant, in the children)
and the arrival error (arrival at the subscriber minus the instant): p50, p99 and max, and the
CPU used by children and router per sample. The arrival error is what an agent that acts on
another's sample at the same instant cannot beat on this machine with this stack; a realtime
run's delivery errors are that plus adnmesh's own work per event.

    .venv/bin/python benchmarks/bench_wake_burst.py                    # N = 1, 5, 14; 20 s each
    .venv/bin/python benchmarks/bench_wake_burst.py --counts 14 --seconds 30 --priority fifo

Everything runs on 127.0.0.1; every child is stopped by its PID.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adnmesh.runtime.bus import client_config, free_port, router_config  # noqa: E402
from adnmesh.runtime.os_scheduling import raise_priority, tighten_timers  # noqa: E402

KEY = "bench/burst"

CHILD = r"""
import os, struct, sys, time
sys.path.insert(0, {repo!r})
import zenoh
from adnmesh.runtime.bus import client_config
from adnmesh.runtime.os_scheduling import raise_priority, tighten_timers
endpoint, index, start_ns, period_ns, count, priority = sys.argv[1:7]
index, start_ns, period_ns, count = int(index), int(start_ns), int(period_ns), int(count)
tighten_timers()
session = zenoh.open(client_config([endpoint]))
raise_priority(priority)
pub = session.declare_publisher({key!r} + "/" + str(index))
pad = bytes(64 - 20)
late = []
cpu0 = time.process_time()
for k in range(count):
    target = start_ns + k * period_ns
    wait = (target - time.monotonic_ns()) * 1e-9
    if wait > 0:
        time.sleep(wait)
    now = time.monotonic_ns()
    late.append(now - target)
    pub.put(struct.pack("<qqi", target, now, index) + pad)
cpu = time.process_time() - cpu0
print(cpu, *late, flush=True)
session.close()
"""


def run(count: int, seconds: float, period_s: float, priority: str) -> dict:
    """One run with ``count`` children; figures in ms (CPU in µs per sample)."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(router_config([endpoint]))
    arrivals: list[tuple[int, int]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        target = int.from_bytes(sample.payload.to_bytes()[:8], "little", signed=True)
        with lock:
            arrivals.append((target, now))

    sub = router.declare_subscriber(KEY + "/**", on_sample)
    period_ns = int(period_s * 1e9)
    samples = int(seconds / period_s)
    start_ns = time.monotonic_ns() + int(3e9)          # time for every child to connect
    start_ns -= start_ns % period_ns
    code = CHILD.format(repo=str(REPO), key=KEY)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    procs = [subprocess.Popen([sys.executable, "-c", code, endpoint, str(i), str(start_ns),
                               str(period_ns), str(samples), priority],
                              stdout=subprocess.PIPE, text=True) for i in range(count)]
    try:
        outs = [p.communicate(timeout=seconds + 60)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    sub.undeclare()
    router.close()
    wake, child_cpu = [], 0.0
    for out in outs:
        fields = out.split()
        child_cpu += float(fields[0])
        wake.extend(int(x) for x in fields[1:])
    arr = np.array([now - target for target, now in arrivals], dtype=float) / 1e6
    wake = np.array(wake, dtype=float) / 1e6
    router_cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    n = max(1, count * samples)
    return {"count": count, "samples": n, "received": int(arr.size),
            "wake": (np.median(wake), np.quantile(wake, 0.99), wake.max()),
            "arrival": (np.median(arr), np.quantile(arr, 0.99), arr.max()),
            "child_cpu_us": child_cpu / n * 1e6, "router_cpu_us": router_cpu / n * 1e6}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--counts", default="1,5,14", help="processes per run")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--period", type=float, default=0.01, help="s")
    parser.add_argument("--priority", default="off", choices=["off", "nice", "fifo"])
    args = parser.parse_args()
    tighten_timers()
    granted = raise_priority(args.priority)
    if not granted.granted:
        print(granted.message)
    print(f"{os.cpu_count()} cores; period {args.period * 1e3:g} ms; {args.seconds:g} s per "
          f"run; priority {args.priority}; load {os.getloadavg()[0]:.1f}")
    for count in (int(c) for c in args.counts.split(",") if c.strip()):
        r = run(count, args.seconds, args.period, args.priority)
        w, a = r["wake"], r["arrival"]
        print(f"N={count:>3}: wake-up error p50 {w[0]:.3f} p99 {w[1]:.3f} max {w[2]:.1f} ms; "
              f"arrival p50 {a[0]:.3f} p99 {a[1]:.3f} max {a[2]:.1f} ms "
              f"({r['received']}/{r['samples']} samples); CPU per sample: child "
              f"{r['child_cpu_us']:.0f} µs, router + subscriber {r['router_cpu_us']:.0f} µs; "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
