"""Cost of ``adnmesh up`` on a hierarchy (every level as processes, a site router per ADN),
against the same levels run in one process.

The hierarchy file and the configs it names are copied to a temporary folder (``up`` writes
the upper level next to the hierarchy file). One ``up`` first makes the tables (not timed).
Then, alternating for ``--repeat`` rounds:

- ``up``: ``adnmesh up HIERARCHY`` as a subprocess; its start-up ("agents ready in"), the wall
  time of its clock and speed (its summary), the number of its processes and their summed PSS
  (``/proc/PID/smaps_rollup`` of every process below it, sampled every 0.5 s: the peak), and
  the wall time of the whole command;
- the peer: :func:`adnmesh.sim.hierarchy_run.run_hierarchy` of the levels file in this
  process (the in-process run ``adnmesh cascade --run`` makes), its wall time.

Printed: ranges over the rounds, the ratio of the medians of the clock's wall time, and the
load at the start.

    python benchmarks/bench_hierarchy_up.py configs/examples/hierarchy/hv.yaml --repeat 3
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_runtime import descendants, pss_kb

from adnmesh.config import load_hierarchy
from adnmesh.sim.hierarchy_levels import load_levels
from adnmesh.sim.hierarchy_run import Level, run_hierarchy

REPO = Path(__file__).resolve().parent.parent


def copied(hierarchy: Path, folder: Path) -> Path:
    """The repository's ``configs`` in ``folder``; the hierarchy file's path there."""
    configs = REPO / "configs"
    shutil.copytree(configs, folder / "configs", ignore=shutil.ignore_patterns("*-upper"))
    return folder / "configs" / hierarchy.resolve().relative_to(configs)


def up_round(path: Path, folder: Path) -> dict:
    """One ``adnmesh up`` of ``path``: its figures (see the module docstring)."""
    summary = folder / "s.json"
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "adnmesh", "up", str(path), "--out",
                             str(folder / "run.mcap"), "--summary-json", str(summary)],
                            cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    peak_mb, most = 0.0, 0
    while proc.poll() is None:
        pids = descendants(proc.pid) | {proc.pid}
        pss = [kb for kb in (pss_kb(p) for p in pids) if kb is not None]
        peak_mb, most = max(peak_mb, sum(pss) / 1024), max(most, len(pss))
        time.sleep(0.5)
    err = proc.stderr.read()
    command_s = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"adnmesh up failed ({proc.returncode}): {err[-2000:]}")
    levels = json.loads(summary.read_text())["levels"]
    upper = next(iter(levels.values()))
    ready = re.search(r"(\d+) agents ready in ([0-9.]+) s", err)
    return {"command_s": command_s, "clock_s": upper["wall_time_s"],
            "speed": upper["speed_factor"], "startup_s": float(ready.group(2)),
            "agents": int(ready.group(1)), "processes": most, "pss_mb": peak_mb,
            "messages": sum(s["extra"]["messages_recorded"] for s in levels.values())}


def in_process(levels_file: Path) -> float:
    """Wall time of :func:`run_hierarchy` of the levels file, s."""
    levels = load_levels(levels_file)
    upper = Level(levels.upper, levels.schedule(levels.upper.grid), levels.lower_switch_rule())
    adns = {a: Level(c, levels.schedule(a)) for a, c in levels.adns.items()}
    t0 = time.perf_counter()
    run_hierarchy(upper, adns, levels.offset_delay_s)
    return time.perf_counter() - t0


def show(label: str, values: list[float], unit: str = "", digits: int = 2) -> None:
    print(f"  {label}: {min(values):.{digits}f}–{max(values):.{digits}f}{unit} "
          f"(median {statistics.median(values):.{digits}f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("hierarchy")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = copied(Path(args.hierarchy), folder)
        hierarchy = load_hierarchy(path)
        levels_file = folder / "run.levels.json"          # beside up's --out
        print(f"{hierarchy.name}: {len(hierarchy.adns)} ADNs, {hierarchy.scenario.duration_s:g}"
              f" s; load {os.getloadavg()[0]:.1f} at the start; the tables first", flush=True)
        up_round(path, folder)
        ups, alone = [], []
        for round_ in range(args.repeat):
            first_up = round_ % 2 == 0
            if first_up:
                ups.append(up_round(path, folder))
            alone.append(in_process(levels_file))
            if not first_up:
                ups.append(up_round(path, folder))
            print(f"  round {round_ + 1}: up {ups[-1]['clock_s']:.2f} s, in one process "
                  f"{alone[-1]:.2f} s (load {os.getloadavg()[0]:.1f})", flush=True)
        u = ups[0]
        print(f"adnmesh up: {u['agents']} agents, up to {u['processes']} processes (up, fork "
              f"servers, site routers, agents), {u['messages']} messages recorded")
        show("start-up to agents ready", [r["startup_s"] for r in ups], " s")
        show("clock, wall", [r["clock_s"] for r in ups], " s")
        show("speed", [r["speed"] for r in ups], "x real time", 1)
        show("whole command", [r["command_s"] for r in ups], " s", 1)
        show("peak summed PSS", [r["pss_mb"] for r in ups], " MB", 0)
        show("in one process (run_hierarchy), wall", alone, " s")
        ratio = statistics.median(r["clock_s"] for r in ups) / statistics.median(alone)
        print(f"  up / in one process: {ratio:.2f}x (medians of the wall times)")


if __name__ == "__main__":
    main()
