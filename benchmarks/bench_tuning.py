"""Benchmark and audit of the SimBench scheduling table.

Tunes the full table with each method (wall time on this machine), re-evaluates every entry
independently of the tuner (``adnmesh.loop.evaluate`` on ``plant_from_ders`` with the entry's
weights, full step info) and prints the distribution of paper rise time / global rise time.

    .venv/bin/python benchmarks/bench_tuning.py [--methods paper,global] [--workers 2]
    .venv/bin/python benchmarks/bench_tuning.py --audit tables/simbench.<sha12>.json
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from adnmesh.config import load_config
from adnmesh.loop import evaluate
from adnmesh.plant import plant_from_ders
from adnmesh.table import load_table, save_table
from adnmesh.tuning import tune_table

ROOT = Path(__file__).resolve().parent.parent


def audit(config, table) -> int:
    """Re-evaluate every feasible entry; print violations and the paper/global gap."""
    entries = [e for e in table.entries.values() if e.feasible]
    c = config.constraints
    violations = 0
    for start in range(0, len(entries), 256):
        batch = entries[start:start + 256]
        for e in batch:
            plant = plant_from_ders(config.ders_by_id(e.ders), config.design_t_com_s, config.t_meas_s,
                                    weights=e.w)
            f = evaluate(plant, e.kp, e.ki, band_pct=c.settling_band_pct, classical=False).row(0)
            if not (f["stable"] and f["disk_margin"] >= c.disk_margin_min
                    and f["overshoot_pct"] < c.overshoot_max_pct):
                violations += 1
                print(f"  VIOLATION {','.join(e.ders)}: alpha {f['disk_margin']}, "
                      f"overshoot {f['overshoot_pct']}")
    print(f"audit: {len(entries)} feasible entries re-evaluated, {violations} violations, "
          f"{len(table.entries) - len(entries)} infeasible entries")
    ratio = np.array([e.figures["design_rise_time_s"] / e.figures["global_rise_time_s"]
                      for e in entries if e.figures.get("global_rise_time_s")])
    if ratio.size:
        print(f"{table.method} rise time / global rise time over {ratio.size} subsets: "
              f"median {np.median(ratio):.4f}, 90th pct {np.quantile(ratio, 0.9):.4f}, "
              f"worst {ratio.max():.4f}, best {ratio.min():.4f}")
    weighted = sum(any(w < 1 for w in e.w.values()) for e in entries)
    backed = sum((e.figures.get("gain_back_off") or 1.0) < 1 for e in entries)
    print(f"entries with a lowered weight: {weighted}, with gains backed off: {backed}")
    if table.static is not None:
        s = table.static
        print(f"static: K_P {s.kp:.4g} 1/W, K_I {s.ki:.4g} 1/(W s), worst rise "
              f"{s.figures.get('worst_rise_time_s'):.4g} s on {s.figures.get('worst_rise_time_subset')}")
    return violations


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "simbench.yaml"))
    ap.add_argument("--methods", default="paper,global")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--audit", help="only audit this table")
    args = ap.parse_args(argv)
    config = load_config(args.config)
    if args.audit:
        return 1 if audit(config, load_table(args.audit, config)) else 0
    bad = 0
    for method in args.methods.split(","):
        t0 = time.perf_counter()
        table = tune_table(config, method, args.workers)
        dt = time.perf_counter() - t0
        out = Path("/tmp") / f"bench-table-{method}.json"
        save_table(table, out)
        print(f"method {method}: {len(table.entries)} subsets in {dt:.1f} s "
              f"({args.workers} workers) -> {out}")
        bad += audit(config, table)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
