#!/usr/bin/env python3
"""Benchmark of the realtime clock: how fast ``adnmesh up --clock realtime`` can go on this
machine and still give the sim clock's control result.

For one config (default: the SimBench reference case cut to ``--duration`` s, its P_ref steps
and availability changes kept where they fall inside) it runs ``adnmesh up`` once on the sim
clock and then on the realtime clock at every ``--speeds`` factor (``--repeat`` times each), as
a user would (the CLI, ``--summary-json``), and prints per run:

- the delivery error (processing time minus scheduled time, ms of sim time) per link: the
  largest p50, p99 and maximum over the links;
- overruns (events later than the tolerance), messages that arrived after their delivery time
  (the only thing that can change the control result) and alarms the lateness caused;
- every step's rise time, settling time and overshoot against the sim run's, and the largest
  difference against the bound of tests/test_runtime_up.py (2 x (largest delivery error + PI
  period)), and whether the run was real time.

``--variants`` runs each speed once per variant, interleaved: ``off``, ``nice`` or ``fifo``
(``up --rt-priority``), each optionally with ``+spin:US`` (``ADNMESH_RT_SPIN_US``: the agents
poll the clock for the last US µs before each event); every row also gives the CPU time of
``up`` and its agents.

The highest sustainable speed is the highest with no overrun in every repeat (of the first
variant). Beside it, the peer measured during each run: the machine's own wake-up error
(``threading.Condition.wait`` for 2 ms, again and again in this process while the run goes, at
the variant's priority: p50, p99, max), the floor under any delivery error. It measures, it
asserts nothing. Usage::

    .venv/bin/python benchmarks/bench_realtime.py                       # SimBench 120 s; 1,2,4,8
    .venv/bin/python benchmarks/bench_realtime.py --speeds 1,2 --duration 60 --repeat 2
    .venv/bin/python benchmarks/bench_realtime.py --speeds 1 --variants off,fifo,fifo+spin:300
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adnmesh.config import load_config  # noqa: E402
from adnmesh.runtime.os_scheduling import SPIN_ENV, raise_priority  # noqa: E402


def cut_config(source: Path, duration_s: float, workdir: Path) -> Path:
    """The config with the scenario ended at ``duration_s`` (events after it dropped)."""
    document = yaml.safe_load(source.read_text())
    scenario = document["scenario"]
    scenario["duration_s"] = min(float(scenario["duration_s"]), duration_s)
    for name in ("p_ref_steps", "availability"):
        scenario[name] = [e for e in scenario.get(name, []) if e["t_s"] < duration_s]
    path = workdir / f"{source.stem}-{duration_s:g}s.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def table_for(config_path: Path, workdir: Path) -> Path:
    """A gain table with every subset the scenario needs, built once outside the runs
    (``bench_runtime.simbench_table``: the two subsets of the SimBench scenario)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_runtime import simbench_table  # noqa: PLC0415

    return simbench_table(load_config(config_path), workdir)


def variant_args(variant: str) -> tuple[list[str], dict[str, str]]:
    """A ``--variants`` entry -- ``off``, ``nice`` or ``fifo`` (``--rt-priority``), optionally
    ``+spin:US`` (the agents spin the last US µs before each event) -- as extra ``up``
    arguments and environment."""
    priority, _, spin = variant.partition("+")
    args = [] if priority == "off" else ["--rt-priority", priority]
    env = {SPIN_ENV: spin.removeprefix("spin:")} if spin else {SPIN_ENV: "0"}
    return args, env


def up(config: Path, table: Path, workdir: Path, *extra: str,
       env: dict[str, str] | None = None) -> dict:
    """One ``adnmesh up`` run; its summary JSON."""
    summary = workdir / "summary.json"
    summary.unlink(missing_ok=True)
    argv = [sys.executable, "-m", "adnmesh", "up", str(config), "--table", str(table),
            "--out", str(workdir / "run.mcap"), "--summary-json", str(summary), *extra]
    t0, cpu0 = time.perf_counter(), _children_cpu_s()
    result = subprocess.run(argv, cwd=workdir, capture_output=True, text=True, timeout=3600,
                            check=False, env={**os.environ, **(env or {})})
    if result.returncode not in (0, 3) or not summary.exists():
        raise SystemExit(f"adnmesh up {' '.join(extra)} failed ({result.returncode}): "
                         f"{result.stderr.strip().splitlines()[-1:]}")
    data = json.loads(summary.read_text())
    data["wall_total_s"] = time.perf_counter() - t0
    data["cpu_s"] = _children_cpu_s() - cpu0    # up and its agents (up reaps them)
    return data


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def step_figures(summary: dict) -> list[tuple[float, float, float]]:
    out = []
    for step in summary["steps"]:
        f = step["figures"] or {}
        out.append(tuple(np.nan if f.get(k) is None else f[k]
                         for k in ("rise_time_s", "settling_time_s", "overshoot_pct")))
    return out


def compare(real: dict, sim: dict, pi_period_s: float) -> dict:
    timing = real["realtime"]
    links = timing["links"]
    worst_ms = max((e["max_ms"] for e in links), default=0.0)
    worst_p99 = max(links, key=lambda e: e["p99_ms"], default={})
    ours, theirs = np.array(step_figures(real)), np.array(step_figures(sim))
    diff = np.abs(ours - theirs) if ours.shape == theirs.shape else np.full((1, 3), np.inf)
    return {
        "speed": timing["speed"], "real_time": timing["real_time"],
        "p50_ms": max((e["p50_ms"] for e in links), default=0.0),
        "p99_ms": max((e["p99_ms"] for e in links), default=0.0),
        "max_ms": worst_ms, "tolerance_ms": timing["tolerance_ms"],
        "p99_link": worst_p99.get("link", ""),
        "links": {e.get("link", ""): [e["p50_ms"], e["p99_ms"], e["max_ms"]] for e in links},
        "overruns": timing["overruns"], "late_arrivals": timing["late_arrivals"],
        "late_alarms": len(timing["late_alarms"]),
        "d_rise_max_s": float(np.nanmax(diff[:, 0])), "d_settling_max_s":
            float(np.nanmax(diff[:, 1])), "d_overshoot_max_pct": float(np.nanmax(diff[:, 2])),
        "bound_s": 2 * (worst_ms / 1e3 + pi_period_s),
        "speed_factor": real["speed_factor"],
    }


class WakeUpPeer(threading.Thread):
    """The machine's own timer error while a run goes: ``Condition.wait(period)`` overshoot,
    ms, sampled in this (otherwise idle) process until stopped, at the run's ``priority``
    (``--rt-priority``: the floor under the agents' errors at that priority)."""

    def __init__(self, period_s: float = 2e-3, priority: str = "off") -> None:
        super().__init__(daemon=True)
        self.period_s, self.errors, self.done = period_s, [], threading.Event()
        self.priority = priority

    def run(self) -> None:
        raise_priority(self.priority, threads=lambda: [threading.get_native_id()])
        condition = threading.Condition()
        with condition:
            while not self.done.is_set():
                t0 = time.perf_counter()
                condition.wait(self.period_s)
                self.errors.append((time.perf_counter() - t0 - self.period_s) * 1e3)

    def figures(self) -> dict:
        self.done.set()
        self.join()
        e = np.array(self.errors or [np.nan])
        return {"p50_ms": float(np.median(e)), "p99_ms": float(np.quantile(e, 0.99)),
                "max_ms": float(e.max()), "samples": len(self.errors)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(REPO / "configs" / "simbench.yaml"))
    parser.add_argument("--duration", type=float, default=120.0, help="sim s per run")
    parser.add_argument("--speeds", default="1,2,4,8")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--variants", default="off",
                        help="comma-separated: off, nice, fifo (--rt-priority), each with an "
                        "optional +spin:US (e.g. off,off+spin:300,fifo+spin:300): every one is "
                        "run at every speed, interleaved per repeat")
    parser.add_argument("--table", help="gain table of the cut config (default: built here "
                                          "for the SimBench scenario's subsets)")
    parser.add_argument("--json", metavar="PATH", help="also write every figure as JSON")
    args = parser.parse_args()
    speeds = [float(s) for s in args.speeds.split(",") if s.strip()]
    figures: dict = {"cpus": os.cpu_count(), "runs": [], "wake_up": []}
    with tempfile.TemporaryDirectory(prefix="adnmesh-bench-rt-") as tmp:
        workdir = Path(tmp)
        config = cut_config(Path(args.config), args.duration, workdir)
        pi_period_s = load_config(config).runtime.pi_period_s
        table = Path(args.table) if args.table else table_for(config, workdir)
        sim = up(config, table, workdir)
        figures["sim"] = {"speed_factor": sim["speed_factor"], "cpu_s": sim["cpu_s"]}
        print(f"{config.name}: sim clock {sim['speed_factor']:.1f}x real time, CPU "
              f"{sim['cpu_s']:.0f} s; steps "
              f"(rise s, settling s, overshoot %): "
              f"{[tuple(round(v, 3) for v in f) for f in step_figures(sim)]}", flush=True)
        variants = [v.strip() for v in args.variants.split(",") if v.strip()]
        for speed, _, variant in ((s, r, v) for s in speeds for r in range(args.repeat)
                                  for v in variants):
            extra, env = variant_args(variant)
            peer = WakeUpPeer(priority=variant.partition("+")[0])
            peer.start()
            real = up(config, table, workdir, "--clock", "realtime", "--speed",
                      f"{speed:g}", *extra, env=env)
            row = compare(real, sim, pi_period_s)
            peer = peer.figures()
            row["load"] = os.getloadavg()[0]
            row["variant"] = variant
            row["cpu_s"] = real["cpu_s"]
            figures["runs"].append(row)
            figures["wake_up"].append(peer)
            print(f"speed {speed:4g} [{variant}]: delivery error p50 {row['p50_ms']:.2f} p99 "
                  f"{row['p99_ms']:.2f} ({row['p99_link']}) max {row['max_ms']:.1f} ms (tolerance "
                  f"{row['tolerance_ms']:g}); wake-up peer p50 {peer['p50_ms']:.2f} p99 "
                  f"{peer['p99_ms']:.2f} ms; overruns {row['overruns']}, late arrivals "
                  f"{row['late_arrivals']}, late alarms {row['late_alarms']}; |d rise| "
                  f"{row['d_rise_max_s'] * 1e3:.1f} ms |d settling| "
                  f"{row['d_settling_max_s'] * 1e3:.1f} ms |d overshoot| "
                  f"{row['d_overshoot_max_pct']:.3f} % (bound {row['bound_s'] * 1e3:.0f} "
                  f"ms); {'real time' if row['real_time'] else 'NOT real time'}; load "
                  f"{row['load']:.1f}; CPU {row['cpu_s']:.0f} s", flush=True)
    sustained = [s for s in speeds if all(r["real_time"] for r in figures["runs"]
                                          if r["speed"] == s and r["variant"] == variants[0])]
    figures["highest_sustainable_speed"] = max(sustained) if sustained else None
    print(f"highest sustainable speed (no overrun in any repeat): "
          f"{figures['highest_sustainable_speed']}", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
