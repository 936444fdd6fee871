"""Benchmark: one call of the grid's limit sensitivities beside one pandapower runpp of the grid.

On SimBench 1-MV-rural at lW (loads as impedances) with the eleven DERs of
configs/simbench.yaml as actuators, each at its schedule, every repeat times, interleaved so
that they share the machine's speed of the moment:

- ``limit_sensitivities(method="jacobian")`` (the default: one sparse LU of the power flow's
  Jacobian), per call;
- ``limit_sensitivities(method="differences")`` (central differences of the warm-started solver,
  44 power flows), per call;
- ``pandapower.runpp`` of the same grid at the same point (the peer), per call.

It prints each repeat's median per call (wall clock and the thread's CPU time), then their
range over the repeats and the ratios taken within each repeat (the VM's speed varies 2-3x hour
to hour: compare ratios, not times).

    .venv/bin/python benchmarks/sensitivity_speed.py [--repeat 5] [--calls 200] [--runpp 20]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CODE, CASE = "1-MV-rural--0-no_sw", "lW"


def per_call(function, calls: int) -> tuple[float, float]:
    """Median wall-clock and thread CPU time of one call of ``function()``, s."""
    wall, cpu = np.empty(calls), np.empty(calls)
    for k in range(calls):
        c0, t0 = time.thread_time(), time.perf_counter()
        function()
        wall[k], cpu[k] = time.perf_counter() - t0, time.thread_time() - c0
    return float(np.median(wall)), float(np.median(cpu))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--calls", type=int, default=200, help="sensitivity calls per repeat")
    parser.add_argument("--runpp", type=int, default=20, help="runpp calls per repeat")
    args = parser.parse_args()

    import pandapower as pp

    from adnmesh.config import load_config
    from adnmesh.grid import GridSolver, load_grid
    from adnmesh.grid.sensitivity import limit_sensitivities
    from adnmesh.grid.simbench_net import grid_net

    ders = load_config(ROOT / "configs" / "simbench.yaml").ders
    names = [d.sgen for d in ders]
    data = load_grid(CODE, CASE, "impedance")
    solver = GridSolver(data, names)
    p = np.array([d.p_sched_w for d in ders], dtype=float)
    q = data.sgen_q_mvar[data.sgen_index(names)] * 1e6
    net = grid_net(CODE, CASE, "impedance")
    rows = [int(net.sgen.index[net.sgen.name == n][0]) for n in names]
    net.sgen.loc[rows, "p_mw"], net.sgen.loc[rows, "q_mvar"] = p / 1e6, q / 1e6
    pp.runpp(net)                                          # imports and first-call set-up
    sens = {m: limit_sensitivities(solver, p, q, method=m) for m in ("jacobian", "differences")}
    print(f"{CODE} at {CASE}: {len(solver.bus_names)} buses, {len(data.line_names)} lines, "
          f"{len(data.trafo_names)} transformers, {len(names)} DERs; largest difference of "
          f"the two methods: dv/dP {_worst(sens, 'dv_dp'):.1e}, dline/dP "
          f"{_worst(sens, 'dline_dp'):.1e} (of each one's largest)")

    columns = ("jacobian", "differences", "runpp")
    rows_ms = []
    for r in range(args.repeat):
        times = {
            "jacobian": per_call(lambda: limit_sensitivities(solver, p, q), args.calls),
            "differences": per_call(
                lambda: limit_sensitivities(solver, p, q, method="differences"),
                max(1, args.calls // 4)),
            "runpp": per_call(lambda: pp.runpp(net), args.runpp),
        }
        rows_ms.append({k: (w * 1e3, c * 1e3) for k, (w, c) in times.items()})
        print(f"repeat {r + 1}: " + ", ".join(
            f"{k} {rows_ms[-1][k][0]:.3f} ms (cpu {rows_ms[-1][k][1]:.3f})" for k in columns))

    def spread(values) -> str:
        return f"{min(values):.3g}-{max(values):.3g}"

    print(f"\nper call over {args.repeat} repeats (wall clock, ms):")
    for k in columns:
        print(f"  {k:12s} {spread([row[k][0] for row in rows_ms])}   "
              f"(cpu {spread([row[k][1] for row in rows_ms])})")
    print("ratios within each repeat (wall clock):")
    for a, b in (("runpp", "jacobian"), ("differences", "jacobian"), ("runpp", "differences")):
        print(f"  {a} / {b}: {spread([row[a][0] / row[b][0] for row in rows_ms])}")
    return 0


def _worst(sens: dict, field: str) -> float:
    a, b = (getattr(sens[m], field) for m in ("jacobian", "differences"))
    return float(np.abs(a - b).max() / np.abs(a).max())


if __name__ == "__main__":
    raise SystemExit(main())
