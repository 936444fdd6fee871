#!/usr/bin/env python3
"""Benchmark of the commands that read a recording, beside independent readers, in one run.

Runs ``adnmesh inspect``, ``adnmesh plot`` and ``adnmesh replay`` on one recording, each as its
own process, and two readers that are not adnmesh's over the same file in the same session:

- ``mcap iteration``: the ``mcap`` library's plain pass over every message
  (``make_reader(f).iter_messages()``, each message as a Python object, nothing decoded);
- ``rerun mcap convert``: Rerun's own MCAP importer (``rerun mcap convert RUN -o OUT.rrd``; it
  does not decode JSON channels), if the ``rerun`` program is there.

For every process: wall time and peak resident memory (``ru_maxrss`` of that child, from
``os.wait4``). Every measurement is repeated (``--repeat``, default 3), in turns (all commands
once, then again), and shown as min / median / max with the ratio of the medians to the mcap
iteration's, and the load average before each turn: the machine is shared, its speed varies
2-3x from hour to hour, so the ratio to a reader measured in the same minutes is the figure to
compare. Targets (issue 15): each command at most 5 s wall and 250 MB peak RSS on the 600 s
SimBench recording, where the mcap iteration took 6.7 s (on a busier machine: a wall-time
ratio of at most 0.75 to it). It measures; it asserts nothing.

Usage::

    .venv/bin/python benchmarks/bench_recordings.py                     # records one first
    .venv/bin/python benchmarks/bench_recordings.py logs/RUN.mcap --repeat 5 --json out.json

Without a recording it makes one: ``adnmesh up configs/simbench.yaml`` (600 s of sim time,
1-3 minutes; the first run on a machine builds the grid model's cache, tens of seconds more).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

TARGET_WALL_S, TARGET_RSS_MB = 5.0, 250.0
ISSUE_MCAP_ITERATION_S = 6.7
"""The mcap iteration's wall time on the machine and load where the 5 s target was set
(issue 15): on a busier machine a command meets the target if its ratio to the mcap iteration
measured in the same turns is at most 5 / 6.7."""

MCAP_ITERATION = """
import sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as stream:
    count = sum(1 for _ in make_reader(stream).iter_messages())
print(count, "messages")
"""


def load() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def measure(argv: list[str]) -> dict:
    """Run ``argv``; return its wall time (s), peak RSS (MB) and exit code."""
    start = time.perf_counter()
    child = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,  # noqa: S603
                             cwd=REPO)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    error = child.stderr.read().decode(errors="replace").strip().splitlines()
    child.stderr.close()
    return {"wall_s": wall, "rss_mb": usage.ru_maxrss / 1024, "exit": child.returncode,
            "stderr": error[-1] if error and child.returncode else ""}


def rerun_program() -> list[str] | None:
    """The ``rerun`` program that came with rerun-sdk, if installed."""
    try:
        from adnmesh.results.rerun_export import rerun_executable
    except ImportError:
        return None
    command = rerun_executable()
    return command if Path(command[0]).name.startswith("rerun") else None


def commands(recording: Path, scratch: Path) -> dict[str, list[str]]:
    """What is measured: name -> argv."""
    adnmesh = [sys.executable, "-m", "adnmesh"]
    found = {
        "inspect": [*adnmesh, "inspect", str(recording)],
        "plot": [*adnmesh, "plot", str(recording), "-o", str(scratch / "run.png")],
        "replay": [*adnmesh, "replay", str(recording), "--rrd", str(scratch / "run.rrd")],
        "mcap iteration": [sys.executable, "-c", MCAP_ITERATION, str(recording)],
    }
    rerun = rerun_program()
    if rerun is not None:
        found["rerun mcap convert"] = [*rerun, "mcap", "convert", str(recording), "-o",
                                       str(scratch / "rerun-convert.rrd")]
    return found


def record(scratch: Path) -> Path:
    """Record the 600 s SimBench scenario into ``scratch``."""
    out = scratch / "simbench.mcap"
    print(f"recording the SimBench scenario to {out} (adnmesh up, 1-3 min) ...", flush=True)
    subprocess.run([sys.executable, "-m", "adnmesh", "up", "configs/simbench.yaml", "--out",  # noqa: S603
                    str(out)], cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return out


def spread(values: list[float]) -> dict:
    values = sorted(values)
    return {"min": values[0], "median": statistics.median(values), "max": values[-1]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", nargs="?", type=Path,
                        help="MCAP recording (default: record the SimBench scenario first)")
    parser.add_argument("--repeat", type=int, default=3, help="turns (default 3)")
    parser.add_argument("--only", help="comma-separated names of what to measure")
    parser.add_argument("--json", type=Path, help="also write every measurement as JSON")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-recordings-") as tmp:
        scratch = Path(tmp)
        recording = args.recording.resolve() if args.recording else record(scratch)
        size_mb = recording.stat().st_size / 1e6
        todo = commands(recording, scratch)
        if args.only:
            todo = {k: v for k, v in todo.items() if k in args.only.split(",")}
        print(f"{recording}: {size_mb:.1f} MB; {args.repeat} turns; cpus {os.cpu_count()}")
        runs: dict[str, list[dict]] = {name: [] for name in todo}
        for turn in range(args.repeat):
            print(f"turn {turn + 1}: load average {load()}", flush=True)
            for name, argv in todo.items():
                result = measure(argv)
                runs[name].append(result)
                problem = f"  FAILED (exit {result['exit']}): {result['stderr']}" \
                    if result["exit"] else ""
                print(f"  {name:20s} {result['wall_s']:7.2f} s {result['rss_mb']:7.0f} MB"
                      f"{problem}", flush=True)
    report(runs)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"recording": str(recording), "runs": runs}, indent=1))
    return 0


def report(runs: dict[str, list[dict]]) -> None:
    """Min / median / max per command, ratio of the medians to the mcap iteration's, targets."""
    peer = runs.get("mcap iteration")
    peer_median = statistics.median(r["wall_s"] for r in peer) if peer else None
    print(f"\n{'':20s} {'wall [s] min / median / max':>30s} {'peak RSS [MB]':>16s} "
          f"{'/ mcap iteration':>17s}  target")
    for name, results in runs.items():
        wall = spread([r["wall_s"] for r in results])
        rss = spread([r["rss_mb"] for r in results])
        ratio = f"{wall['median'] / peer_median:17.2f}" if peer_median else f"{'':17s}"
        target = ""
        if name in ("inspect", "plot", "replay"):
            fast = wall["max"] <= TARGET_WALL_S or (
                peer_median is not None
                and wall["median"] / peer_median <= TARGET_WALL_S / ISSUE_MCAP_ITERATION_S)
            ok = fast and rss["max"] <= TARGET_RSS_MB
            target = "met" if ok else "NOT met"
        print(f"{name:20s} {wall['min']:8.2f} / {wall['median']:6.2f} / {wall['max']:6.2f}   "
              f"{rss['min']:6.0f}-{rss['max']:<6.0f}   {ratio}  {target}")
    print(f"(targets: at most {TARGET_WALL_S:g} s, or a ratio of at most "
          f"{TARGET_WALL_S / ISSUE_MCAP_ITERATION_S:.2f} to the mcap iteration (5 s where it "
          f"takes {ISSUE_MCAP_ITERATION_S:g} s), and {TARGET_RSS_MB:g} MB per command; "
          f"load average now {load()})")


if __name__ == "__main__":
    sys.exit(main())
