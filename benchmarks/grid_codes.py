"""Benchmark: every SimBench MV and HV code through the grid model, against pandapower's runpp.

For each code (``--codes`` to choose; default the 36 MV and HV codes): the time simbench takes
to read it, the time of the grid build (``build_grid_data``: two runpp, the conversion and the
check against runpp), the model's size, and then, with the five largest static generators at
``--points`` random powers, the median time of one warm-started solve (``GridSolver.solve``)
beside that of pandapower's ``runpp`` on the same points (the peer, same run), their ratio and
the largest differences from runpp in P_IP and Q_IP (every external grid, sign turned).

With ``--every-case`` it also builds each code at every study case of its net with both load
models (12 builds a code) and prints how many pass the check against runpp.

    .venv/bin/python benchmarks/grid_codes.py [--codes 1-HV-mixed--0-sw,...] [--points 20]
                                              [--every-case]
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _codes() -> list[str]:
    import simbench

    return [c for c in simbench.collect_all_simbench_codes()
            if c.startswith(("1-MV-", "1-HV-"))]


def measure(code: str, points: int, rng) -> dict:
    import pandapower as pp

    from adnmesh.grid import GridSolver
    from adnmesh.grid.from_net import build_grid_data
    from adnmesh.grid.simbench_net import grid_net

    t0 = time.perf_counter()
    net = grid_net(code, "lW")
    t1 = time.perf_counter()
    data = build_grid_data(net, code, "lW", "impedance")
    t2 = time.perf_counter()
    sgen = net.sgen[net.sgen.in_service.astype(bool)].sort_values("p_mw", ascending=False)
    names = tuple(sgen.name.iloc[:5])
    rows = [net.sgen.index[net.sgen.name == n][0] for n in names]
    p0 = net.sgen.p_mw.loc[rows].to_numpy() * 1e6
    solver = GridSolver(data, names)
    solve_s, runpp_s, dp, dq = [], [], 0.0, 0.0
    for _ in range(points):
        p = p0 * rng.uniform(0.0, 1.5, len(p0))
        a = time.perf_counter()
        sample = solver.solve(p)
        b = time.perf_counter()
        net.sgen.loc[rows, "p_mw"] = p / 1e6
        pp.runpp(net)
        c = time.perf_counter()
        solve_s.append(b - a)
        runpp_s.append(c - b)
        dp = max(dp, abs(sample.p_ip_w + net.res_ext_grid.p_mw.sum() * 1e6))
        dq = max(dq, abs(sample.q_ip_var + net.res_ext_grid.q_mvar.sum() * 1e6))
    solve, peer = float(np.median(solve_s)), float(np.median(runpp_s))
    return dict(code=code, read_s=t1 - t0, build_s=t2 - t1, buses=data.lsgrid.total_bus(),
                ext=int(net.ext_grid.in_service.sum()), solve_us=solve * 1e6,
                runpp_ms=peer * 1e3, ratio=peer / solve, dp_w=dp, dq_var=dq)


def every_case(code: str) -> tuple[int, int, list[str]]:
    """Build ``code`` at each of its study cases with each load model: (built, tried,
    failures)."""
    import copy

    from adnmesh.errors import GridError
    from adnmesh.grid import simbench_net as sn
    from adnmesh.grid.from_net import build_grid_data

    base = sn.load_simbench_net(code)
    built, tried, failures = 0, 0, []
    for case in sn.study_cases(base):
        for load_model in sn.LOAD_MODELS:
            net = copy.deepcopy(base)
            sn.apply_study_case(net, case)
            if load_model == "impedance":
                sn.loads_as_impedances(net)
            tried += 1
            try:
                build_grid_data(net, code, case, load_model)
                built += 1
            except GridError as exc:
                failures.append(f"{case}/{load_model}: {exc}")
    return built, tried, failures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--codes", help="comma-separated SimBench codes (default: every MV/HV)")
    parser.add_argument("--points", type=int, default=20, help="operating points per code")
    parser.add_argument("--every-case", action="store_true",
                        help="also build each code at every study case, both load models")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    codes = args.codes.split(",") if args.codes else _codes()
    rng = np.random.default_rng(1)
    print(f"{'code':24s} {'read':>6s} {'build':>6s} {'buses':>5s} {'ext':>3s} "
          f"{'solve':>9s} {'runpp':>8s} {'ratio':>6s} {'|dP_IP|':>9s} {'|dQ_IP|':>9s}")
    for i, code in enumerate(codes, 1):
        r = measure(code, args.points, rng)
        print(f"{r['code']:24s} {r['read_s']:5.1f}s {r['build_s']:5.2f}s {r['buses']:5d} "
              f"{r['ext']:3d} {r['solve_us']:7.0f}µs {r['runpp_ms']:6.1f}ms {r['ratio']:5.0f}x "
              f"{r['dp_w']:7.3f} W {r['dq_var']:5.3f} var   [{i}/{len(codes)}]", flush=True)
    if args.every_case:
        total = tried_all = 0
        for code in codes:
            built, tried, failures = every_case(code)
            total, tried_all = total + built, tried_all + tried
            print(f"{code:24s} every study case, both load models: {built} of {tried} built"
                  + "".join(f"\n  {f}" for f in failures), flush=True)
        print(f"every case: {total} of {tried_all} builds pass the check against runpp")
    return 0


if __name__ == "__main__":
    sys.exit(main())
