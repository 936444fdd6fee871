"""The four SimBench MV grids of ``configs/grids/`` tuned: the paper's comparison over four
grids (docs/performance.md#four-simbench-mv-grids).

For each config (written by ``adnmesh init``): the ADN from its header (buses, generators),
actuators by type, the controllable range at the schedules, then ``adnmesh tune CONFIG --method
M`` in a subprocess (every subset; ``--subsets scenario`` beyond 16 DERs, as tune refuses more),
timed, and from the table: entries, feasible entries, median and worst rise time over the
feasible entries (as deployed), the static pair and its worst rise time over the subsets it was
designed on. One markdown row per grid.

Usage::

    .venv/bin/python benchmarks/grid_table.py                   # all four, --method global
    .venv/bin/python benchmarks/grid_table.py --method paper configs/grids/1-MV-comm.yaml
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from adnmesh.config import load_config  # noqa: E402


def _row(path: Path, method: str, workdir: Path) -> str:
    config = load_config(path)
    header = path.read_text()
    size = re.search(r"(\d+) buses, (\d+) static generators", header)
    counts: dict[str, int] = {}
    for der in config.ders:
        counts[der.type] = counts.get(der.type, 0) + 1
    # init schedules each actuator at half its study-case infeed: both ranges are the sum of
    # the schedules (to a watt per DER)
    up = down = sum(d.p_sched_w for d in config.ders)
    out = workdir / f"{path.stem}.json"
    subsets = ["--subsets", "scenario"] if len(config.ders) > 16 else []
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "adnmesh", "tune", str(path), "--method", method,
                    "--out", str(out), *subsets], check=True, capture_output=True)
    wall = time.perf_counter() - t0
    table = json.loads(out.read_text())
    rise = [e["rise_time_s"] for e in table["entries"] if e["feasible"]]
    static = table.get("static") or {}
    static_text = (f"K_P {static['kp'] * 1e6:.3g} / K_I {static['ki'] * 1e6:.3g} (1/MW, "
                   f"1/(MW s)); worst rise {static.get('worst_rise_time_s', float('nan')):.2f} s"
                   if static.get("kp") else "none")
    return (f"| {path.stem} | {size.group(1)} | {size.group(2)} | "
            f"{', '.join(f'{n} {t}' for t, n in counts.items())} | +{up / 1e6:.2f} / "
            f"-{down / 1e6:.2f} MW | {len(table['entries'])}{' (scenario)' if subsets else ''}"
            f" | {len(rise)} | {wall:.1f} s | {statistics.median(rise):.2f} s | "
            f"{max(rise):.2f} s | {static_text} |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("configs", nargs="*", type=Path,
                        default=sorted((REPO / "configs" / "grids").glob("1-MV-*.yaml")))
    parser.add_argument("--method", default="global", choices=("paper", "global"))
    args = parser.parse_args(argv)
    print("| grid | buses | sgens | actuators | range up / down | entries | feasible | "
          "tune wall | median rise | worst rise | static pair |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.configs:
            print(_row(path, args.method, Path(tmp)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
