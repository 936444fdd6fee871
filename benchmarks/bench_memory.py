"""The memory of ``adnmesh up`` over a run: its RSS after start-up and at the end.

Runs ``adnmesh up CONFIG`` as a subprocess (every argument after CONFIG is passed on) and reads
``VmRSS`` of the ``up`` process from ``/proc/<pid>/status`` every ``--every`` wall seconds. It
prints:

- **after start-up**: the RSS ``--settle`` wall seconds after ``up`` says its agents are ready
  (the first chunk buffers, Zenoh's queues and the first summary series are in by then);
- the RSS at every tenth of the run (wall time from ready to end, the sim clock runs about
  evenly), and the largest during the run;
- **at the end**: the last RSS before ``up`` prints its ``recording:`` line, which comes after
  the shutdown and before the summary is computed;
- the end against after start-up (absolute and %), and MB per 1,000 simulated seconds;
- the agents' RSS (the children of ``up``) after start-up and at the end, summed.

Usage::

    python benchmarks/bench_memory.py configs/examples/simbench-long.yaml --out /tmp/long.mcap
    python benchmarks/bench_memory.py configs/simbench.yaml --settle 5 --seed 3

The recording goes to a temporary folder (``--out`` to keep it). The run must finish (exit 0).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def _children(pid: int) -> list[int]:
    found = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                found += [int(c) for c in
                          Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
            except FileNotFoundError:
                continue
    except FileNotFoundError:
        pass
    return found


def _agents_mb(pid: int) -> float:
    return sum(_rss_mb(c) or 0.0 for c in _children(pid))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config")
    parser.add_argument("--table", help="gain table (passed on to up)")
    parser.add_argument("--out", help="recording (default: a temporary file)")
    parser.add_argument("--every", type=float, default=0.5, help="sampling period, wall s")
    parser.add_argument("--settle", type=float, default=10.0,
                        help="wall s after 'agents ready' that count as after start-up")
    # every other argument is up's (an argparse REMAINDER after CONFIG swallowed --out too)
    args, rest = parser.parse_known_args(argv)
    duration_s = float(yaml.safe_load(Path(args.config).read_text())["scenario"]["duration_s"])
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or str(Path(tmp) / "run.mcap")
        cmd = [sys.executable, "-m", "adnmesh", "up", args.config, "--out", out,
               *(["--table", args.table] if args.table else []),
               *[a for a in rest if a != "--"]]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        marks: dict[str, float] = {}
        err_lines: list[str] = []

        def read_stderr():
            for line in proc.stderr:
                err_lines.append(line)
                now = time.monotonic()
                if "agents ready" in line:
                    marks.setdefault("ready", now)
                elif line.startswith("adnmesh up: recording:"):
                    marks.setdefault("end", now)

        reader = threading.Thread(target=read_stderr, daemon=True)
        reader.start()
        out_text: list[str] = []
        out_reader = threading.Thread(target=lambda: out_text.append(proc.stdout.read()),
                                      daemon=True)
        out_reader.start()
        samples: list[tuple[float, float]] = []
        agents: dict[str, float] = {}
        while proc.poll() is None:
            rss = _rss_mb(proc.pid)
            now = time.monotonic()
            if rss is not None:
                samples.append((now, rss))
            ready = marks.get("ready")
            if ready is not None and "start" not in agents and now >= ready + args.settle:
                agents["start"] = _agents_mb(proc.pid)
            if "end" not in marks:
                agents["end"] = _agents_mb(proc.pid) or agents.get("end", 0.0)
            time.sleep(args.every)
        reader.join(5)
        out_reader.join(5)
    if proc.returncode != 0 or "ready" not in marks or "end" not in marks:
        sys.stderr.write("".join(err_lines[-20:]))
        print(f"up exited with {proc.returncode}; no figures", file=sys.stderr)
        return 1
    ready, end = marks["ready"], marks["end"]
    running = [(t, r) for t, r in samples if ready <= t <= end]
    after = next((r for t, r in samples if t >= ready + args.settle), None)
    at_end = [r for t, r in samples if t <= end][-1]
    print(f"adnmesh up {args.config}: {duration_s:g} s simulated, run {end - ready:.1f} s wall "
          f"(ready to end)")
    print("  wall s after ready   RSS MB")
    for k in range(11):
        t_k = ready + k * (end - ready) / 10
        r_k = next((r for t, r in running if t >= t_k), at_end)
        print(f"  {t_k - ready:12.1f}   {r_k:10.1f}")
    print(f"after start-up ({args.settle:g} s after ready): {after:.1f} MB")
    print(f"at the end (before the summary): {at_end:.1f} MB; largest while running "
          f"{max(r for _, r in running):.1f} MB")
    print(f"end - start: {at_end - after:+.1f} MB ({100 * (at_end / after - 1):+.1f} %), "
          f"{1000 * (at_end - after) / duration_s:+.2f} MB per 1,000 simulated s")
    print(f"agents, summed RSS: {agents.get('start', 0):.0f} MB after start-up, "
          f"{agents.get('end', 0):.0f} MB at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
