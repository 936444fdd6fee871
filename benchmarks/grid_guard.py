"""Benchmark: what the grid guard and the tap changer do to the stress cases, and what it costs.

Runs each config in one process on the sim clock (:func:`adnmesh.sim.local.run_local`, the same
nodes and messages as ``adnmesh up``; gains tuned on demand) and prints, per run, what the
summary says of the grid: violations, time outside the band, worst line loading and voltage,
the guard's time and cost (``∫ |P_ref - P_IP| dt`` while it acted, the steps not delivered),
the tap changer's steps, and the wall time beside that of the guard-off run of the same case
(interleaved repeats: the VM's speed varies 2-3x hour to hour, compare the ratios).

    .venv/bin/python benchmarks/grid_guard.py [--repeat 3] [CONFIG ...]

Default: the stress case of configs/examples/stress-rural1-lW.yaml (guard off), its variant
with the guard (directional) and the one with block mode and a tap changer.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ["stress-rural1-lW.yaml", "stress-rural1-lW-guard.yaml", "stress-rural1-lW-tap.yaml"]


def run(path: Path):
    from adnmesh.config import load_config
    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.results.summary import RunSeries, summarize
    from adnmesh.sim.local import run_local
    from adnmesh.wire.envelope import decode

    config = load_config(path)
    start = time.perf_counter()
    result = run_local(config, GainSchedule(config, None, tuning_delay_s=0.0))
    wall = time.perf_counter() - start
    series = RunSeries()
    for key, payload in result.messages:
        series.take(decode(key, payload))
    summary = summarize(series, end_ns=int(config.scenario.duration_s * 1e9))
    return config, summary, wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("configs", nargs="*", type=Path)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    paths = args.configs or [ROOT / "configs" / "examples" / name for name in DEFAULT]
    walls: dict[Path, list[float]] = {p: [] for p in paths}
    rows = {}
    run(paths[0])                                   # warm the grid cache and the tuner
    for _ in range(args.repeat):
        for path in paths:
            config, summary, wall = run(path)
            walls[path].append(wall)
            rows[path] = (config, summary)
    base = walls[paths[0]]
    print(f"{'config':32} {'mode':11} {'viol':>4} {'out s':>6} {'line %':>6} {'v_max':>7} "
          f"{'guard s':>7} {'kWh':>6} {'not delivered':>14} {'taps':>4}  wall s (x first)")
    for path in paths:
        config, s = rows[path]
        g = s.grid
        mode = config.grid_model.guard.mode
        ratios = [w / b for w, b in zip(walls[path], base)]
        short = ",".join(f"{t:g}" for t in g.steps_short) or "-"
        print(f"{path.name:32} {mode:11} {g.violations:4d} {g.outside_s:6.2f} "
              f"{g.line_loading_max_pct:6.1f} {g.v_max_pu:7.4f} {g.guarded_s:7.2f} "
              f"{g.energy_short_kwh or 0.0:6.2f} {short:>14} {g.tap_moves:4d}  "
              f"{min(walls[path]):.2f}-{max(walls[path]):.2f} "
              f"({min(ratios):.2f}-{max(ratios):.2f})")


if __name__ == "__main__":
    main()
